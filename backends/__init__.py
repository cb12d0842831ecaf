"""Simulator backends (one module per engine) behind comexp.simulator.Simulator."""
