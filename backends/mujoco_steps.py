"""MuJoCo's push steps compiled: the engine's step and the footprint friction, no Python between.

Why: with `floor_friction=model` every step needs the floor's friction from the state the last
step left (backends/floor_friction.py), so MuJoCo cannot run a chunk of steps in one call of
its own. Stepped from Python, a step cost ~40 - 54 us of our Python around MuJoCo's ~20 us
and the kernel's ~18 us (bench/step_cost.py, 8176422). Here one Numba call runs a whole chunk
of the protocol: per step it puts the pusher on its path, computes the floor's friction force
(`impulse_kernel`, the same kernel), calls libmujoco's `mj_step` by its C symbol, and reads
whether the pusher touches the object from a contact sensor (`PUSHER_SENSOR`).

What is given up: the Python bindings turn MuJoCo's fatal errors (`mju_error`) into Python
exceptions; called from here such an error ends the process, as MuJoCo's default handler
does. `mj_step` raises none for these scenes; its warnings (a full contact buffer, a bad
acceleration) are still counted after every chunk (`MujocoSimulator.engine_failure`).
"""

from __future__ import annotations

import glob
import math
import os
import sys

import mujoco
import numpy as np
from numba import njit, types

from comexp.backends import floor_friction
from comexp.backends.floor_friction import impulse_kernel
from comexp.backends.numba_kernels import bind_library_functions, stamp_with_sources
from comexp.sim import stop_rule
from comexp.sim.stop_rule import chunk_stops


def _libmujoco() -> str:
    """The libmujoco the Python bindings load (the wheel ships it beside them; Linux only:
    the backend's `linux_only` in conf/backend/mujoco.yaml)."""
    if not sys.platform.startswith("linux"):
        msg = f"the compiled MuJoCo loop loads libmujoco.so: Linux only, not {sys.platform}"
        raise ImportError(msg)
    pkg = os.path.dirname(mujoco.__file__)
    found = sorted(glob.glob(os.path.join(pkg, f"libmujoco.so.{mujoco.__version__}")))
    found = found or sorted(glob.glob(os.path.join(pkg, "libmujoco.so*")))
    if not found:
        raise ImportError(f"no libmujoco.so* beside the mujoco package in {pkg}")
    return found[0]


# Declared by name (resolved when the compiled code is loaded), which keeps the compiled loop
# cacheable, and bound to the functions `mujoco.mj_step` calls (libmujoco is not made
# global). Pointers are passed as integers: the same registers in the x86-64 and AArch64 C
# ABIs.
_C_FUNCTIONS = ("mj_step", "mju_quat2Mat")
if not bind_library_functions(_libmujoco(), _C_FUNCTIONS):
    raise ImportError(f"cannot bind {', '.join(_C_FUNCTIONS)} in {_libmujoco()}")
_mj_step = types.ExternalFunction("mj_step", types.void(types.intp, types.intp))
_mju_quat2mat = types.ExternalFunction("mju_quat2Mat", types.void(types.intp, types.intp))

# The MJCF sensor whose reading says whether the pusher touches the object: every contact of
# the pusher geom, reduced to the deepest one (sensordata = [count, its distance]). It is
# evaluated inside mj_step from the same contact list the step used.
PUSHER_SENSOR = "pusher_touch"
PUSHER_SENSOR_MJCF = (
    f'<sensor><contact name="{PUSHER_SENSOR}" geom1="pusher" data="found dist" '
    f'reduce="mindist" num="1"/></sensor>'
)


@njit(cache=True)
def pusher_touching(sensordata, adr):
    """The pusher penetrates the object (a contact of the pusher geom at negative distance)."""
    return sensordata[adr] > 0.0 and sensordata[adr + 1] < 0.0


@njit(cache=True)
def cos_tilt(qx, qy):
    """Cosine of the angle between the body's z axis and world z, from the x and y parts of
    its (w, x, y, z) quaternion: the largest tilt is that of the least cosine."""
    return 1.0 - 2.0 * (qx * qx + qy * qy)


@njit(cache=True)
def push_steps(
    m_ptr, d_ptr, substeps, qpos, qvel, xipos, xfrc, sensordata, sensor_adr,
    obj_q, obj_v, pusher_q, pusher_v, body, com_local, starts, vels,
    geo, fs, normal, dxw, dyw, dt, pushed, record,
):  # fmt: skip
    """Runs one step per row of `starts` / `vels`: the pusher set at `starts[i]` moving at
    `vels[i]` (kinematic, as `MujocoSimulator._set_pusher`), the floor's friction for the step
    as a force at the floor under the CoM in `xfrc_applied` (`impulse_kernel` on the twist the
    object has before it: `floor_friction=model`), then `substeps` calls of mj_step.

    The arrays are MjData's own buffers (numpy views of it): MuJoCo's writes are seen here and
    ours by MuJoCo. `record` (n x 5, or 0 rows: off) receives every step's friction input
    (`FootprintFriction.inputs`). Returns (touched at any step, touching after the last, the
    least cosine of the tilt seen after a step: the tilt is monotone in it)."""
    rot = np.empty(9)
    quat_adr = qpos.ctypes.data + 8 * (obj_q + 3)
    xi_hat = np.empty(3)
    touched = False
    min_cos_tilt = 1.0
    for i in range(starts.shape[0]):
        qpos[pusher_q] = starts[i, 0]
        qpos[pusher_q + 1] = starts[i, 1]
        qvel[pusher_v] = vels[i, 0]
        qvel[pusher_v + 1] = vels[i, 1]
        # the object's twist at its CoM: the free joint's angular velocity is in the body
        # frame, its linear velocity the body origin's in the world frame
        _mju_quat2mat(rot.ctypes.data, quat_adr)
        b0, b1, b2 = qvel[obj_v + 3], qvel[obj_v + 4], qvel[obj_v + 5]
        w0 = rot[0] * b0 + rot[1] * b1 + rot[2] * b2
        w1 = rot[3] * b0 + rot[4] * b1 + rot[5] * b2
        w2 = rot[6] * b0 + rot[7] * b1 + rot[8] * b2
        c0, c1, c2 = com_local[0], com_local[1], com_local[2]
        r0 = rot[0] * c0 + rot[1] * c1 + rot[2] * c2
        r1 = rot[3] * c0 + rot[4] * c1 + rot[5] * c2
        r2 = rot[6] * c0 + rot[7] * c1 + rot[8] * c2
        xi_hat[0] = qvel[obj_v] + (w1 * r2 - w2 * r1)
        xi_hat[1] = qvel[obj_v + 1] + (w2 * r0 - w0 * r2)
        xi_hat[2] = w2
        yaw = math.atan2(rot[3], rot[0])
        if record.shape[0]:
            record[i, 0], record[i, 1], record[i, 2] = xi_hat[0], xi_hat[1], xi_hat[2]
            record[i, 3], record[i, 4] = yaw, 1.0 if pushed else 0.0
        imp = impulse_kernel(geo, fs, normal, dxw, dyw, xi_hat, yaw, dt, pushed)
        fx, fy, tz = imp[0] / dt, imp[1] / dt, imp[2] / dt
        z = xipos[body, 2]  # the CoM's height above the floor: the floor point's lever
        xfrc[body, 0] = fx
        xfrc[body, 1] = fy
        xfrc[body, 2] = 0.0
        xfrc[body, 3] = z * fy
        xfrc[body, 4] = -z * fx
        xfrc[body, 5] = tz
        for _ in range(substeps):
            _mj_step(m_ptr, d_ptr)
        pushed = pusher_touching(sensordata, sensor_adr)
        touched = touched or pushed
        min_cos_tilt = min(min_cos_tilt, cos_tilt(qpos[obj_q + 4], qpos[obj_q + 5]))
    return touched, pushed, min_cos_tilt


@njit(cache=True)
def push_chunks(
    m_ptr, d_ptr, substeps, qpos, qvel, xipos, xfrc, sensordata, sensor_adr,
    obj_q, obj_v, pusher_q, pusher_v, body, com_local, starts, vels,
    geo, fs, normal, dxw, dyw, dt, pushed, record,
    chunk, rule, min_cos_tilt, rest_after, warnings, warning_index, warnings0, out,
):  # fmt: skip
    """`push_steps` over each whole chunk of `chunk` rows in turn (the protocol's `advance`
    calls, one compiled call), stopping after the first chunk whose state `chunk_stops`
    names (the rest rule after those `rest_after` marks). Per chunk run, `out` gets (touched,
    the least cosine of its tilt, touching after it, the object's quaternion after it).
    `record` as `push_steps`' (one row per step, or 0 rows). Returns how many chunks ran."""
    n = starts.shape[0] // chunk
    rot = np.empty(9)
    for c in range(n):
        a, b = c * chunk, (c + 1) * chunk
        rec = record[a:b] if record.shape[0] else record
        touched, pushed, min_cos = push_steps(
            m_ptr, d_ptr, substeps, qpos, qvel, xipos, xfrc, sensordata, sensor_adr,
            obj_q, obj_v, pusher_q, pusher_v, body, com_local, starts[a:b], vels[a:b],
            geo, fs, normal, dxw, dyw, dt, pushed, rec,
        )  # fmt: skip
        out[c, 0] = 1.0 if touched else 0.0
        out[c, 1] = min_cos
        out[c, 2] = 1.0 if pushed else 0.0
        for k in range(4):
            out[c, 3 + k] = qpos[obj_q + 3 + k]
        if _stops(
            qpos, qvel, obj_q, obj_v, min_cos, min_cos_tilt, rule, rest_after[c], warnings,
            warning_index, warnings0, rot,
        ):  # fmt: skip
            return c + 1
    return n


@njit(cache=True)
def _stops(
    qpos, qvel, obj_q, obj_v, min_cos, min_cos_tilt, rule, rest, warnings, warning_index,
    warnings0, rot,
):  # fmt: skip
    """`ChunkStop`'s rule (`stop_rule.chunk_stops`) on MuJoCo's state: healthy is every
    coordinate finite, no more of the engine's unstable warnings than `warnings0`
    (`MujocoSimulator.engine_failure`) and the chunk's tilt within the cosine
    `min_cos_tilt` (half way to the tip limit: an engine's object is never exactly flat);
    the object frame's origin, its |v_x| + |v_y| and the spin about world z."""
    healthy = True
    for i in range(7):
        if not math.isfinite(qpos[obj_q + i]):
            healthy = False
    for i in range(6):
        if not math.isfinite(qvel[obj_v + i]):
            healthy = False
    count = 0
    for k in warning_index:
        count += warnings[k]
    if count > warnings0 or min_cos < min_cos_tilt:
        healthy = False
    _mju_quat2mat(rot.ctypes.data, qpos.ctypes.data + 8 * (obj_q + 3))
    # the free joint's angular velocity is in the body frame: world z is the matrix's last row
    wz = rot[6] * qvel[obj_v + 3] + rot[7] * qvel[obj_v + 4] + rot[8] * qvel[obj_v + 5]
    speed = abs(qvel[obj_v]) + abs(qvel[obj_v + 1])
    return chunk_stops(healthy, qpos[obj_q], qpos[obj_q + 1], rest, speed, wz, rule)


# the chunk above compiles the friction kernel into its own machine code
stamp_with_sources(globals(), floor_friction, stop_rule)
