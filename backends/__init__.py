"""Simulator backends (one module per engine) behind comexp.experiment.interface.Simulator."""
