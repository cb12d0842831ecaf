"""comexp: centre-of-mass estimation by dynamic pushing.

The package is laid out by concern, from the job down to the method:

- `comexp.cli` (the `comexp` and `comexp-db` commands) and `comexp.api` (the notebook's `run`,
  `load_results`, `replay`): thin adapters;
- `comexp.experiment`: the driver side: a job's config and checks, the objects, the grid of
  episodes, and the job service (`job.run_job`);
- `comexp.workers`: Ray: the pool of worker actors, the Ray session, the kernels' warm-up;
- `comexp.results`: the store (database), reports, plots, claims;
- `comexp.episode`: the worker side: an episode's task and the loop that runs it;
- `comexp.backends`: the simulators (planar reference, pybullet, MuJoCo);
- `comexp.sim`: the engine interface, the one push protocol and the scene's vocabulary;
- `comexp.method`: frames, geometry, perception and the estimators, free of any simulator
  (`comexp.method.estimator` is the estimator library for a robot's own observations).

`comexp.run(overrides)`, `comexp.load_results(db, table="episodes")` and
`comexp.replay(db, episode_id)` are `comexp.api`'s, imported on first use: the workers import
this package too, and the episode side never loads Hydra, pandas or SQLAlchemy.
"""

from __future__ import annotations

import importlib
from typing import Any

from comexp.workers import kept as _kept_ray

__version__ = "0.1.0"
__all__ = ["load_results", "replay", "run"]

# A kept Ray's token (`comexp-ray start`) goes into the environment now, before anything
# imports Ray, which reads its auth settings once, when it is imported.
_kept_ray.export_auth()


def __getattr__(name: str) -> Any:
    if name in __all__:  # the notebook API, imported on first use (see above)
        return getattr(importlib.import_module("comexp.api"), name)
    raise AttributeError(f"module 'comexp' has no attribute {name!r}")
