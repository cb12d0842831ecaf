"""The simulators (one module per engine) behind the engine interface
(`comexp.sim.simulator.Simulator`), each chosen by its config group option
(conf/backend/NAME.yaml: `_target_`)."""
