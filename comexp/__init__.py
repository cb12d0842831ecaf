"""comexp: centre-of-mass estimation by dynamic pushing.

The package is laid out by concern, in the order data flows through it:

- `comexp.experiment`: config -> objects -> grid -> episode -> simulator interface;
- `comexp.method`: scene (frames, units), geometry, perception, estimator;
- `comexp.backends`: the simulators (planar reference, pybullet, MuJoCo);
- `comexp.workers`: Ray actors that run episodes;
- `comexp.results`: store (database), reports, plots, the notebook API;
- `comexp.cli`: the `comexp` and `comexp-db` commands.

`comexp.load_results(db, table="episodes")` (a pandas DataFrame) and
`comexp.replay(db, episode_id)` are imported on first use, so `import comexp` stays light.
The module names the README and docs document (`comexp.estimator`, `comexp.perception`,
`comexp.reports`, ...) are the same modules under their room (`_ALIASES`), imported on first
use too: one module, two names, no copy.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
from types import ModuleType
from typing import Any

__version__ = "0.1.0"
__all__ = ["load_results", "replay"]

# documented name -> the module in its room
_ALIASES = {
    "comexp.estimator": "comexp.method.estimator",
    "comexp.perception": "comexp.method.perception",
    "comexp.scene": "comexp.method.scene",
    "comexp.objects": "comexp.experiment.objects",
    "comexp.simulator": "comexp.experiment.simulator",
    "comexp.reports": "comexp.results.reports",
}


class _AliasFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """`import comexp.estimator` gives the module `comexp.method.estimator` itself."""

    def find_spec(
        self, fullname: str, path: Any = None, target: ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        if fullname not in _ALIASES:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        module = importlib.import_module(_ALIASES[spec.name])
        spec.loader_state = module.__spec__  # the import system sets the alias' spec on it
        return module

    def exec_module(self, module: ModuleType) -> None:
        """Nothing to run: the real module ran when it was imported under its own name; it
        gets its own spec back."""
        own = module.__spec__.loader_state
        if isinstance(own, importlib.machinery.ModuleSpec):
            module.__spec__ = own


if not any(isinstance(f, _AliasFinder) for f in sys.meta_path):
    sys.meta_path.insert(0, _AliasFinder())


def __getattr__(name: str) -> Any:
    if name in __all__:
        from comexp.results import api

        return getattr(api, name)
    if f"comexp.{name}" in _ALIASES:
        return importlib.import_module(f"comexp.{name}")
    raise AttributeError(f"module 'comexp' has no attribute {name!r}")
