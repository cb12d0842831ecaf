"""The protocol's stop rule for an engine that runs several chunks in one compiled call.

`ChunkStop` (comexp.sim.protocol) says where such an engine stops so that the protocol's own
check sees the chunk's state; this is that rule, compiled once for every engine's compiled
chunk loop (backends/planar_sim.py, backends/mujoco_steps.py), each of which reads its own
state into the rule's terms: whether the state is healthy (finite, flat enough, no failure of
the engine's own), where the object frame's origin is, and how fast it moves and turns.
"""

from __future__ import annotations

from numba import njit


@njit(cache=True)
def chunk_stops(healthy, x, y, rest, speed_l1, spin, rule):
    """Whether the chunk loop stops after a chunk: the state is not `healthy`, the origin
    (x, y) is outside the box `rule[0:4]` (x_lo, x_hi, y_lo, y_hi), or, where `rest` marks
    the chunk, the origin's |v_x| + |v_y| (`speed_l1`) is below `rule[4]` and the spin about
    world z below `rule[5]` (near rest: a superset of the settle rule's rest)."""
    if not healthy:
        return True
    if not (rule[0] <= x <= rule[1] and rule[2] <= y <= rule[3]):
        return True
    return rest and speed_l1 < rule[4] and abs(spin) < rule[5]
