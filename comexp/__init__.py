"""comexp: centre-of-mass estimation by dynamic pushing.

The package is laid out by concern, in the order data flows through it:

- `comexp.experiment`: config -> objects -> grid -> task and episode loop -> simulator
  interface (registry, view and contact geometry beside it);
- `comexp.method`: scene (frames, units), geometry, perception (observation, tracking,
  rendering), estimator;
- `comexp.backends`: the simulators (planar reference, pybullet, MuJoCo);
- `comexp.workers`: Ray actors that run episodes;
- `comexp.results`: store (database), reports, plots, the notebook API;
- `comexp.cli`: the `comexp` and `comexp-db` commands.

`comexp.run(overrides)` (runs a job, returns its episodes), `comexp.load_results(db,
table="episodes")` (a pandas DataFrame) and `comexp.replay(db, episode_id)` are imported on
first use, so `import comexp` stays light.
The short module names the README and docs use (`comexp.estimator`, `comexp.perception`,
`comexp.scene`, `comexp.objects`, `comexp.simulator`, `comexp.reports`) are thin modules that
re-export the module in its room (`comexp/estimator.py` -> `comexp.method.estimator`, ...);
as attributes of `comexp` they too are imported on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"
__all__ = ["load_results", "replay", "run"]

# the re-export modules beside this file (comexp/<name>.py)
SHORT_MODULES = ("estimator", "perception", "scene", "objects", "simulator", "reports")


def __getattr__(name: str) -> Any:
    if name in __all__:
        from comexp.results import api

        return getattr(api, name)
    if name in SHORT_MODULES:
        return importlib.import_module(f"comexp.{name}")
    raise AttributeError(f"module 'comexp' has no attribute {name!r}")
