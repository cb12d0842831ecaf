"""The paper's reported numbers and the condition they were measured under (Gao et al.).

Tables II (isotropic floor) and III (anisotropic floor) give, per object, mean / std / max / min
of the CoM error in cm at 40 cm/s ("high speed") and 4 cm/s ("low speed"). Our 20 objects are
not the paper's (its Fig. 2 is not available), so only the all-objects mean is comparable; it
is the mean of the 20 per-object means (every object has the same number of episodes).
"""

from __future__ import annotations

from statistics import fmean

# Per-object means, obj1 .. obj20, copied from Tables II and III.
TABLE_MEANS_CM: dict[tuple[str, float], tuple[float, ...]] = {
    ("iso", 40.0): (
        0.489, 0.476, 0.423, 0.631, 0.481, 0.605, 0.713, 0.651, 0.742, 0.66,
        0.619, 0.619, 0.598, 0.53, 0.521, 0.689, 0.645, 0.8, 0.87, 0.812,
    ),
    ("iso", 4.0): (
        0.949, 0.915, 0.591, 2.06, 1.071, 1.297, 1.3, 1.936, 2.2, 2.067,
        1.805, 1.423, 1.004, 1.253, 0.678, 1.103, 0.919, 1.735, 1.811, 1.862,
    ),
    ("aniso", 40.0): (
        0.597, 0.595, 0.607, 0.598, 0.51, 0.649, 0.742, 0.631, 0.832, 0.667,
        0.606, 0.655, 0.556, 0.596, 0.771, 0.764, 0.599, 0.832, 0.822, 1.15,
    ),
    ("aniso", 4.0): (
        1.408, 1.744, 1.602, 3.651, 2.039, 2.006, 2.098, 3.22, 3.789, 2.073,
        2.513, 1.76, 1.938, 1.83, 1.347, 2.525, 2.428, 2.863, 3.026, 3.319,
    ),
}  # fmt: skip

# All-objects mean per (floor, speed), computed from the tables above.
ALL_OBJECTS_MEAN_CM: dict[tuple[str, float], float] = {
    key: fmean(means) for key, means in TABLE_MEANS_CM.items()
}

# The paper's grid (Table I, Sec. III): floor (mu_x, mu_y) pairs, pusher mu, Izz scales.
FLOOR_PAIRS: dict[str, frozenset[tuple[float, float]]] = {
    "iso": frozenset({(0.1, 0.1), (1.0, 1.0)}),
    "aniso": frozenset({(0.1, 1.0), (1.0, 0.1)}),
}
PUSHER_MU: dict[str, frozenset[float]] = {
    "iso": frozenset({0.1, 1.0}),
    "aniso": frozenset({0.5}),
}
IZZ_SCALES = frozenset({1.0, 10.0})
MASS_KG = 0.2
PUSH_LENGTH_CM = 3.0
# Estimator values the paper states (Sec. III); the rotation is measured by vision.
ESTIMATOR = {"w": [1, 0.5], "theta_T_deg": 1, "C_bw_px": 10, "n_push": 5}
ROTATION_SOURCE = "vision"
