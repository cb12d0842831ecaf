"""Episode identity: `episode_key`, a hash of the whole spec, so that a resumed or raced sweep
never stores an episode twice (the database's UNIQUE ``episode_key`` with ``ON CONFLICT DO
NOTHING``), the canonical JSON the key and the stored `spec` / `estimator` columns share, and
that JSON read back (`spec_from_json`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import numbers
import typing
from typing import Any

from comexp.episode.task import EpisodeSpec

KEY_VERSION = "v1"  # bump if the key's canonical form changes (old keys then no longer match)


def _canonical(value: Any) -> Any:
    """JSON-ready form whose text does not depend on int-vs-float spelling or container type.

    40 and 40.0 (Hydra may give either) both become 40; other floats keep Python's shortest
    round-trip repr, which is stable across platforms; tuples become lists.
    """
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        x = float(value)
        if math.isfinite(x) and x.is_integer() and abs(x) < 2**53:
            return int(x)
        return x
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_canonical(v) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        # a field marked key_omit_default counts only when set: adding one leaves the keys of
        # the episodes that do not set it as they were
        return {
            f.name: _canonical(getattr(value, f.name))
            for f in dataclasses.fields(value)
            if not (f.metadata.get("key_omit_default") and getattr(value, f.name) == f.default)
        }
    if hasattr(value, "tolist"):  # numpy scalars and arrays
        return _canonical(value.tolist())
    raise TypeError(f"cannot build an episode key from a {type(value).__name__}: {value!r}")


def canonical_json(value: Any) -> str:
    """Sorted-key compact JSON of `_canonical(value)`."""
    return json.dumps(_canonical(value), sort_keys=True, separators=(",", ":"), allow_nan=True)


def episode_key(spec: EpisodeSpec) -> str:
    """Identity of an episode: sha256 of every spec field, so fields added later count too."""
    text = KEY_VERSION + ":" + canonical_json(spec)
    return hashlib.sha256(text.encode()).hexdigest()


def from_json(tp: Any, value: Any) -> Any:
    """Rebuild a (nested, frozen) dataclass from its canonical JSON: lists become tuples."""
    if dataclasses.is_dataclass(tp) and isinstance(value, dict):
        hints = typing.get_type_hints(tp)
        names = {f.name for f in dataclasses.fields(tp)}
        unknown = sorted(set(value) - names)
        if unknown:
            raise ValueError(
                f"stored {tp.__name__} has fields this comexp does not know: {', '.join(unknown)}"
            )
        return tp(**{k: from_json(hints[k], v) for k, v in value.items()})
    if isinstance(value, list):
        return tuple(from_json(None, v) for v in value)
    if isinstance(value, dict):
        return {k: from_json(None, v) for k, v in value.items()}
    if tp is float and isinstance(value, int):
        return float(value)
    return value


def spec_from_json(text: str) -> EpisodeSpec:
    """The stored `spec` column back as the `EpisodeSpec` that ran (estimator included)."""
    return from_json(EpisodeSpec, json.loads(text))
