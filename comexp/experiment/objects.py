"""The objects of the study: one YAML file per object (a footprint polygon in cm plus a height),
the one loader of those files, validation, the seeded CoM points and the one conversion to the
simulator's `ObjectSpec` (`ObjectDef.model`).

Loading: `load_objects(names, sources)` reads `object/<name>.yaml` from a job's config sources
(`comexp.experiment.sources`: the package's `conf/`, `--config-dir`, `hydra.searchpath`
entries), the first source that has the file winning as in Hydra's search path; without
`sources`, from the package's `conf/` alone (the built-in objects: tests, bench).

Object frame: the footprint is re-centred on its area centroid (as
`comexp.sim.bodies.prism_object` does) and put in counter-clockwise order; x/y keep the axes of
the config file. Every CoM the study samples, stores and estimates is in this frame, in cm.

CoM rule: the k-th CoM of an object depends only on (object name, k, base_seed), so every
condition (speed, friction, Izz, backend) sees the very same CoMs and asking for 3 CoMs gives
the first 3 of 10. See docs/objects.md.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from shapely.geometry import Point, Polygon

from comexp.episode.task import EpisodeSettings, object_model
from comexp.experiment.sources import PACKAGE_SOURCES, group_files, read_mapping
from comexp.method import geometry
from comexp.sim.scene import ObjectSpec

# Validation bounds (documented in docs/objects.md). The camera sees the floor at ~2.8 mm/px,
# so an object thinner than MIN_WIDTH_CM covers only a dozen pixels across and its rotation is
# hard to measure; objects larger than MAX_EXTENT_CM would leave the 0.6 m floor's view after a
# few pushes.
MIN_AREA_CM2 = 12.0
MIN_WIDTH_CM = 3.0
MAX_EXTENT_CM = 30.0
MAX_HEIGHT_CM = 6.0  # the pusher spans 0.2-6.2 cm above the floor: taller sides are not pushed
MIN_COM_MARGIN_CM = 0.5  # a CoM closer to the edge than this makes the object nearly unstable
DEFAULT_COM_MARGIN_CM = 1.0
_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
_KEYS = {"name", "outline_cm", "height_cm", "description"}


@dataclass(frozen=True)
class ObjectDef:
    """An object as the experiment layer sees it: footprint (cm, CCW, origin at its area
    centroid) and height (cm). Construct through `from_mapping` (or `load_objects`), which
    validate."""

    name: str
    outline_cm: tuple[tuple[float, float], ...]
    height_cm: float
    description: str = ""

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], default_name: str | None = None) -> ObjectDef:
        """Validate a mapping ({name, outline_cm, height_cm[, description]}) into an ObjectDef.

        The outline may be in any vertex order and any origin; a closing vertex equal to the
        first is dropped. Raises ValueError with one line naming the object and the problem.
        """
        if not isinstance(data, Mapping):
            raise ValueError(f"object {default_name!r}: expected a mapping, got {type(data)}")
        name = data.get("name", default_name)
        label = name if isinstance(name, str) else default_name
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise ValueError(f"object {label!r}: name must be a non-empty identifier, got {name!r}")
        unknown = set(data) - _KEYS
        if unknown:
            raise ValueError(f"object {name!r}: unknown keys {sorted(unknown)}; allowed {_KEYS}")
        if "outline_cm" not in data or "height_cm" not in data:
            raise ValueError(f"object {name!r}: needs outline_cm and height_cm")
        outline = _parse_outline(name, data["outline_cm"])
        height = _parse_number(name, "height_cm", data["height_cm"])
        description = str(data.get("description", "") or "")
        _validate(name, outline, height)
        p = geometry.ccw(outline)
        p = p - geometry.centroid(p, compiled=False)  # (the same bits, no kernel to load)
        return cls(
            name=name,
            outline_cm=tuple((float(x), float(y)) for x, y in p),
            height_cm=height,
            description=description,
        )

    @property
    def polygon(self) -> Polygon:
        return Polygon(self.outline_cm)

    @property
    def area_cm2(self) -> float:
        return geometry.signed_area(self.outline_cm)

    @property
    def convex(self) -> bool:
        return geometry.is_convex(self.outline_cm)

    @property
    def size_cm(self) -> tuple[float, float]:
        """Axis-aligned extent (x, y) of the footprint."""
        a = np.asarray(self.outline_cm)
        return float(np.ptp(a[:, 0])), float(np.ptp(a[:, 1]))

    @property
    def min_width_cm(self) -> float:
        return geometry.min_width(self.outline_cm)

    def convex_parts_cm(self) -> list[np.ndarray]:
        return geometry.convex_decomposition(self.outline_cm)

    def model(
        self,
        com_cm: Sequence[float],
        *,
        izz_scale: float,
        mu_pusher: float,
        mass_kg: float = EpisodeSettings.mass_kg,
    ) -> ObjectSpec:
        """The simulator's rigid body of this object with its CoM at `com_cm`
        (`comexp.episode.task.object_model`, the one conversion)."""
        return object_model(
            self.name,
            self.outline_cm,
            self.height_cm,
            com_cm,
            izz_scale=izz_scale,
            mu_pusher=mu_pusher,
            mass_kg=mass_kg,
        )


def _parse_number(name: str, what: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"object {name!r}: {what} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"object {name!r}: {what} must be finite, got {value!r}")
    return v


def _parse_outline(name: str, value: Any) -> np.ndarray:
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise ValueError(f"object {name!r}: outline_cm must be a list of [x, y] pairs")
    pts = []
    for k, v in enumerate(value):
        if isinstance(v, str) or not isinstance(v, Sequence) or len(v) != 2:
            raise ValueError(f"object {name!r}: outline_cm[{k}] must be [x, y], got {v!r}")
        pts.append(
            (
                _parse_number(name, f"outline_cm[{k}]", v[0]),
                _parse_number(name, f"outline_cm[{k}]", v[1]),
            )
        )
    if len(pts) >= 2 and pts[0] == pts[-1]:
        pts = pts[:-1]  # a closed ring
    if len(pts) < 3:
        raise ValueError(f"object {name!r}: outline_cm needs at least 3 vertices, got {len(pts)}")
    return np.asarray(pts, dtype=float)


def _validate(name: str, outline: np.ndarray, height_cm: float) -> None:
    poly = Polygon(outline)
    if not poly.is_valid:
        reason = shapely.is_valid_reason(poly)
        raise ValueError(f"object {name!r}: outline is not a simple polygon ({reason})")
    area = poly.area
    if area < MIN_AREA_CM2:
        raise ValueError(
            f"object {name!r}: footprint area {area:.2f} cm^2 is below {MIN_AREA_CM2} cm^2"
        )
    width = geometry.min_width(outline)
    if width < MIN_WIDTH_CM:
        raise ValueError(
            f"object {name!r}: minimum width {width:.2f} cm is below {MIN_WIDTH_CM} cm"
        )
    extent = max(np.ptp(outline[:, 0]), np.ptp(outline[:, 1]))
    if extent > MAX_EXTENT_CM:
        raise ValueError(f"object {name!r}: extent {extent:.1f} cm is above {MAX_EXTENT_CM} cm")
    if not 0.0 < height_cm <= MAX_HEIGHT_CM:
        raise ValueError(
            f"object {name!r}: height_cm must be in (0, {MAX_HEIGHT_CM}], got {height_cm}"
        )
    if poly.buffer(-MIN_COM_MARGIN_CM).is_empty:
        raise ValueError(
            f"object {name!r}: no point lies {MIN_COM_MARGIN_CM} cm inside the footprint"
        )


def _name_key(name: str) -> list[int]:
    """Stable 128-bit key of the name (Python's hash() is randomised per process)."""
    digest = hashlib.sha256(name.encode("utf-8")).digest()
    return [int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4)]


def com_point(
    obj: ObjectDef, k: int, base_seed: int = 0, margin_cm: float = DEFAULT_COM_MARGIN_CM
) -> tuple[float, float]:
    """The k-th CoM of `obj` (cm, object frame): uniform over the footprint shrunk inward by
    `margin_cm`, drawn by rejection sampling from a generator seeded by (name, k, base_seed)."""
    if k < 0 or base_seed < 0:
        raise ValueError(f"object {obj.name!r}: CoM index and base_seed must be >= 0")
    if not margin_cm >= 0:
        raise ValueError(f"object {obj.name!r}: CoM margin must be >= 0, got {margin_cm}")
    poly = obj.polygon
    inner = poly.buffer(-margin_cm) if margin_cm > 0 else poly
    if inner.is_empty:
        raise ValueError(
            f"object {obj.name!r}: no point lies {margin_cm} cm inside the footprint; "
            "use a smaller CoM margin"
        )
    x0, y0, x1, y1 = poly.bounds
    rng = np.random.default_rng(np.random.SeedSequence([*_name_key(obj.name), k, base_seed]))
    boundary = poly.exterior
    for _ in range(100_000):
        x, y = rng.uniform(x0, x1), rng.uniform(y0, y1)
        pt = Point(x, y)
        # exact test (the buffered polygon only approximates the rounded inner corners)
        if poly.contains(pt) and boundary.distance(pt) >= margin_cm:
            return float(x), float(y)
    raise ValueError(f"object {obj.name!r}: CoM sampling found no point {margin_cm} cm inside")


def com_points(
    obj: ObjectDef, n: int, base_seed: int = 0, margin_cm: float = DEFAULT_COM_MARGIN_CM
) -> list[tuple[float, float]]:
    """The first n CoMs of `obj` (see `com_point`): every condition sees the same ones."""
    if n < 0:
        raise ValueError(f"object {obj.name!r}: number of CoMs must be >= 0, got {n}")
    return [com_point(obj, k, base_seed, margin_cm) for k in range(n)]


# --- the one loader: object/<name>.yaml from a job's config sources ---------------------------

OBJECT_GROUP = "object"


def object_names(sources: Sequence[Mapping[str, Any]] = PACKAGE_SOURCES) -> list[str]:
    """Names of the objects the sources hold, sorted (the built-in ones by default)."""
    return sorted(group_files(OBJECT_GROUP, sources))


def load_objects(
    names: Sequence[str] | None = None, sources: Sequence[Mapping[str, Any]] = PACKAGE_SOURCES
) -> dict[str, ObjectDef]:
    """`ObjectDef` per name, in the order asked (every object of the sources, sorted, when
    `names` is None). Raises ValueError, one line naming the object and the problem."""
    files = group_files(OBJECT_GROUP, sources)
    available = sorted(files)
    if names is None:
        if not available:
            raise ValueError(f"no objects found in the config group {OBJECT_GROUP!r}")
        names = available
    missing = [n for n in names if n not in files]
    if missing:
        shown = ", ".join(available[:30]) + (" ..." if len(available) > 30 else "")
        raise ValueError(f"unknown object {missing[0]!r} (available: {shown or 'none'})")
    out = {}
    for n in names:
        data = read_mapping(f"object {n!r}", files[n])
        try:
            obj = ObjectDef.from_mapping(data, default_name=n)
        except (TypeError, ValueError, KeyError) as e:
            msg = str(e).splitlines()[0]
            raise ValueError(msg if msg.startswith("object ") else f"object {n!r}: {msg}") from None
        if obj.name != n:
            # users select objects by file name: a different `name` inside would be ambiguous
            raise ValueError(f"object {n!r}: its config says name {obj.name!r}")
        out[n] = obj
    return out
