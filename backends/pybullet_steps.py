"""pybullet's push steps compiled: Bullet's C API called from Numba, no Python between steps.

Why: with `floor_friction=model` every step needs the floor's friction from the state the last
step left, and pybullet's Python functions are the only way in: ~10 calls a step, each parsing
its arguments and building Python objects (`stepSimulation` alone builds a dict of analytics
per island), were 18 us of our Python and ~4 us of pybullet's around Bullet's ~8 us step and
the kernel's ~8 us (bench/step_cost.py). Here one Numba call runs a whole chunk of the
protocol: per step exactly the commands `PybulletSimulator._step_once` sends through pybullet's
Python functions, in the same order with the same numbers, so the results are the same to the
bit (tests/test_pybullet_backend.py).

How: the pybullet extension module is also Bullet's C client library (`b3*` functions, exported
by name, declared here as external functions and bound to the module's own addresses for the
compiled code alone: the library is not made global, so its bundled C++ runtime cannot
interpose on libraries loaded later). What those functions need is the client handle
pybullet keeps for a `physicsClientId`, in its module-private table `sPhysicsClients1`
(examples/pybullet/pybullet.c): `client_handle` reads it at the address the library's ELF
symbol table gives for that table, relative to an exported function's, once it has checked
that the file it read is the library loaded and the table has pybullet's size. Where that
cannot be found or checked (a stripped, replaced or another build, not Linux),
`client_handle` returns None and the backend steps from Python as before.

What is given up: a Bullet command that fails is reported by its status, as pybullet's Python
functions check it (the state and contact queries), and the chunk raises; Bullet's own fatal
errors end the process in either path.
"""

from __future__ import annotations

import ctypes
import math
import os
import struct
import sys
from functools import lru_cache

import numpy as np
import pybullet as pb
from numba import njit, types

from comexp.backends import floor_friction
from comexp.backends.floor_friction import impulse_kernel
from comexp.backends.numba_kernels import bind_library_functions, c_memcpy, stamp_with_sources

# pybullet's table of client handles (pybullet.c: `static b3PhysicsClientHandle
# sPhysicsClients1[MAX_PHYSICS_CLIENTS]`) and an exported function to locate it by
_CLIENTS_SYMBOL = "sPhysicsClients1"
_ANCHOR_SYMBOL = "b3CanSubmitCommand"
_MAX_PHYSICS_CLIENTS = 1024  # pybullet.c's MAX_PHYSICS_CLIENTS

# status types and flags (SharedMemoryPublic.h, Bullet 3.2.7 as pybullet 3.2.7 ships it): a
# wrong state status fails the handle's check, a wrong contact status every compiled push
# (tests/test_pybullet_backend.py); the frame flag is pybullet's WORLD_FRAME (tested)
CMD_ACTUAL_STATE_UPDATE_COMPLETED = 21
CMD_CONTACT_POINT_INFORMATION_COMPLETED = 39
EF_WORLD_FRAME = 2
# the C functions the compiled steps call, bound by address (`bind_library_functions`)
_C_FUNCTIONS = (
    "b3CanSubmitCommand", "b3SubmitClientCommandAndWaitStatus", "b3GetStatusType",
    "b3InitStepSimulationCommand", "b3RequestActualStateCommandInit", "b3GetStatusActualState",
    "b3CreatePoseCommandInit", "b3CreatePoseCommandSetBasePosition",
    "b3CreatePoseCommandSetBaseOrientation", "b3CreatePoseCommandSetBaseLinearVelocity",
    "b3CreatePoseCommandSetBaseAngularVelocity", "b3ApplyExternalForceCommandInit",
    "b3ApplyExternalForce", "b3ApplyExternalTorque", "b3InitRequestContactPointInformation",
    "b3SetContactFilterBodyA", "b3SetContactFilterBodyB", "b3GetContactPointInformation",
)  # fmt: skip

_ELF_MAGIC = b"\x7fELF"
_SHT_SYMTAB = 2


def _elf_symbol_values(path: str, names: set[str]) -> dict[str, tuple[int, int]]:
    """(st_value, st_size) of each of `names` defined in a 64-bit little-endian ELF file's full
    symbol table (.symtab, local symbols included; the dynamic table lists exported ones
    only). Reads the section headers, the symbol table and its string table, nothing else."""
    found: dict[str, tuple[int, int]] = {}
    with open(path, "rb") as f:
        head = f.read(64)
        if head[:4] != _ELF_MAGIC or head[4] != 2 or head[5] != 1:  # ELFCLASS64, LSB
            return found
        (shoff,) = struct.unpack_from("<Q", head, 0x28)
        shentsize, shnum = struct.unpack_from("<HH", head, 0x3A)
        f.seek(shoff)
        raw = f.read(shentsize * shnum)
        sections = [struct.unpack_from("<IIQQQQIIQQ", raw, i * shentsize) for i in range(shnum)]
        for sh in sections:
            if sh[1] != _SHT_SYMTAB:
                continue
            _, _, _, _, sym_off, sym_size, link, _, _, entsize = sh
            str_off, str_size = sections[link][4], sections[link][5]
            f.seek(str_off)
            strtab = f.read(str_size)
            f.seek(sym_off)
            syms = f.read(sym_size)
            for i in range(0, sym_size, entsize):
                st_name, _, _, st_shndx, st_value, st_size = struct.unpack_from("<IBBHQQ", syms, i)
                end = strtab.find(b"\0", st_name)
                name = strtab[st_name:end].decode("ascii", "replace")
                if name in names and st_shndx != 0:  # defined here, not an import
                    found[name] = (st_value, st_size)
    return found


@lru_cache(maxsize=1)
def _clients_table_address() -> int | None:
    """The run-time address of pybullet's client table, or None where it cannot be found:
    the load bias (an exported function's address less its symbol value) plus the table's
    symbol value."""
    if not sys.platform.startswith("linux"):
        return None
    path = pb.__file__
    try:
        values = _elf_symbol_values(path, {_CLIENTS_SYMBOL, _ANCHOR_SYMBOL})
        if len(values) != 2 or values[_CLIENTS_SYMBOL][1] != 8 * _MAX_PHYSICS_CLIENTS:
            return None
        lib = ctypes.CDLL(path)  # the module's own library: already loaded, the same handle
        anchor = ctypes.cast(getattr(lib, _ANCHOR_SYMBOL), ctypes.c_void_p).value
        if anchor is None or not _mapped_from(path, anchor):
            return None  # the file read is not the library loaded (replaced since?)
    except (OSError, AttributeError, struct.error, ValueError):
        return None
    return anchor - values[_ANCHOR_SYMBOL][0] + values[_CLIENTS_SYMBOL][0]


def _mapped_from(path: str, address: int) -> bool:
    """Whether `address` lies in a mapping of the file at `path` as it is on disk now
    (/proc/self/maps names a mapped file that was deleted or replaced since "... (deleted)")."""
    want = os.path.realpath(path)
    with open("/proc/self/maps") as maps:
        for line in maps:
            fields = line.split(maxsplit=5)
            start, end = (int(x, 16) for x in fields[0].split("-"))
            if start <= address < end:
                return len(fields) == 6 and fields[5].rstrip("\n") == want
    return False


def client_handle(cid: int, probe_body: int) -> int | None:
    """Bullet's client handle behind pybullet's `physicsClientId` `cid`, checked: the handle
    accepts commands and reports `probe_body`'s base state as pybullet does. None where it
    cannot be found or does not check out (then the caller steps through pybullet)."""
    table = _clients_table_address()
    if table is None or not _BOUND or not 0 <= cid < _MAX_PHYSICS_CLIENTS:
        return None
    handle = ctypes.c_void_p.from_address(table + 8 * cid).value
    if not handle or not _can_submit(handle):
        return None
    state = np.zeros(13)
    if not _base_state(handle, probe_body, state):
        return None
    pos, quat = pb.getBasePositionAndOrientation(probe_body, physicsClientId=cid)
    v, w = pb.getBaseVelocity(probe_body, physicsClientId=cid)
    return handle if state.tolist() == [*pos, *quat, *v, *w] else None


# --- Bullet's C API (PhysicsClientC_API.h), pointers as integers ---------------------------
# the compiled code's C functions are pybullet's own, the library not made global
_BOUND = sys.platform.startswith("linux") and bind_library_functions(pb.__file__, _C_FUNCTIONS)
_p, _i, _d = types.intp, types.intc, types.float64
_can_submit_c = types.ExternalFunction("b3CanSubmitCommand", _i(_p))
_submit = types.ExternalFunction("b3SubmitClientCommandAndWaitStatus", _p(_p, _p))
_status_type = types.ExternalFunction("b3GetStatusType", _i(_p))
_step_init = types.ExternalFunction("b3InitStepSimulationCommand", _p(_p))
_state_init = types.ExternalFunction("b3RequestActualStateCommandInit", _p(_p, _i))
_state_get = types.ExternalFunction("b3GetStatusActualState", _i(_p, _p, _p, _p, _p, _p, _p, _p))
_pose_init = types.ExternalFunction("b3CreatePoseCommandInit", _p(_p, _i))
_pose_position = types.ExternalFunction("b3CreatePoseCommandSetBasePosition", _i(_p, _d, _d, _d))
_pose_orientation = types.ExternalFunction(
    "b3CreatePoseCommandSetBaseOrientation", _i(_p, _d, _d, _d, _d)
)
_pose_linear_velocity = types.ExternalFunction(
    "b3CreatePoseCommandSetBaseLinearVelocity", _i(_p, _p)
)
_pose_angular_velocity = types.ExternalFunction(
    "b3CreatePoseCommandSetBaseAngularVelocity", _i(_p, _p)
)
_force_init = types.ExternalFunction("b3ApplyExternalForceCommandInit", _p(_p))
_force = types.ExternalFunction("b3ApplyExternalForce", types.void(_p, _i, _i, _p, _p, _i))
_torque = types.ExternalFunction("b3ApplyExternalTorque", types.void(_p, _i, _i, _p, _i))
_contacts_init = types.ExternalFunction("b3InitRequestContactPointInformation", _p(_p))
_contacts_body_a = types.ExternalFunction("b3SetContactFilterBodyA", types.void(_p, _i))
_contacts_body_b = types.ExternalFunction("b3SetContactFilterBodyB", types.void(_p, _i))
_contacts_get = types.ExternalFunction("b3GetContactPointInformation", types.void(_p, _p))


@njit(cache=True)
def _base_state_kernel(h, body, out, slots):
    """out[:7] = the body's base position and orientation (x, y, z, w), out[7:13] its linear
    and angular velocity, from one actual-state request (what pybullet's
    getBasePositionAndOrientation and getBaseVelocity each read of theirs), copied from the
    arrays Bullet hands out into `out`, a contiguous float64 array of 13. False when the
    request fails."""
    status = _submit(h, _state_init(h, body))
    if _status_type(status) != CMD_ACTUAL_STATE_UPDATE_COMPLETED:
        return False
    _state_get(status, 0, 0, 0, 0, slots.ctypes.data, slots.ctypes.data + 8, 0)
    c_memcpy(out.ctypes.data, slots[0], 56)  # q: 7 doubles
    c_memcpy(out.ctypes.data + 56, slots[1], 48)  # q dot: 6 doubles
    return True


def _can_submit(handle: int) -> bool:
    return bool(_can_submit_kernel(handle))


@njit(cache=True)
def _can_submit_kernel(h):
    return _can_submit_c(h)


def _base_state(handle: int, body: int, out: np.ndarray) -> bool:
    return bool(_base_state_kernel(handle, body, out, np.zeros(2, dtype=np.int64)))


@njit(cache=True)
def yaw_of_quaternion(x, y, z, w):
    """The yaw of pybullet's getEulerFromQuaternion (pybullet.c), its operations in its order:
    the same bits."""
    sarg = -2 * (x * z - w * y)
    if sarg <= -0.99999:
        return 2 * math.atan2(x, -y)
    if sarg >= 0.99999:
        return 2 * math.atan2(-x, y)
    sqx, sqy, sqz, squ = x * x, y * y, z * z, w * w
    return math.atan2(2 * (x * y + w * z), squ + sqx - sqy - sqz)


@njit(cache=True)
def push_steps(
    h, pusher, obj, pusher_z, targets, dt, geo, fs, normal, dxw, dyw, pushed, record, slots
):  # fmt: skip
    """One step per row of `targets` (the pusher's position at the end of each step), each
    as `PybulletSimulator._step_once` with `floor_friction=model`: the pusher put back at its
    height when it fell, its velocity set to reach the target, the floor's friction of the
    object's twist (`impulse_kernel`) applied at the floor under the CoM, Bullet's step, the
    contact query. `pushed`: the pusher touched the object in the step before.

    `record` (n x 5, or 0 rows: off) receives every step's friction input
    (`FootprintFriction.inputs`). Returns (status: 0, or the step at which a query failed,
    1-based, negated; touched at any step; touching after the last)."""
    inv_dt = 1.0 / dt
    st = np.empty(13)
    vel = np.zeros(3)
    zero = np.zeros(3)
    force = np.zeros(3)
    at = np.zeros(3)
    torque = np.zeros(3)
    info = np.zeros(2, dtype=np.int64)  # struct b3ContactInformation (count, pointer)
    twist = np.empty(3)
    touched = False
    for i in range(targets.shape[0]):
        # the pusher: back at its height, moving to reach its target at the step's end
        if not _base_state_kernel(h, pusher, st, slots):
            return -(i + 1), touched, pushed
        px, py = st[0], st[1]
        if st[2] != pusher_z:
            cmd = _pose_init(h, pusher)
            _pose_position(cmd, px, py, pusher_z)
            _pose_orientation(cmd, st[3], st[4], st[5], st[6])
            _submit(h, cmd)
        vel[0] = (targets[i, 0] - px) * inv_dt
        vel[1] = (targets[i, 1] - py) * inv_dt
        cmd = _pose_init(h, pusher)
        _pose_linear_velocity(cmd, vel.ctypes.data)
        _pose_angular_velocity(cmd, zero.ctypes.data)
        _submit(h, cmd)
        # the floor's friction (PybulletSimulator._apply_floor_friction)
        if not _base_state_kernel(h, obj, st, slots):
            return -(i + 1), touched, pushed
        yaw = yaw_of_quaternion(st[3], st[4], st[5], st[6])
        if record.shape[0]:
            record[i, 0], record[i, 1], record[i, 2] = st[7], st[8], st[12]
            record[i, 3], record[i, 4] = yaw, 1.0 if pushed else 0.0
        twist[0], twist[1], twist[2] = st[7], st[8], st[12]
        imp = impulse_kernel(geo, fs, normal, dxw, dyw, twist, yaw, dt, pushed)
        if imp[0] != 0.0 or imp[1] != 0.0 or imp[2] != 0.0:
            force[0], force[1] = imp[0] / dt, imp[1] / dt
            at[0], at[1] = st[0], st[1]
            cmd = _force_init(h)
            _force(cmd, obj, -1, force.ctypes.data, at.ctypes.data, EF_WORLD_FRAME)
            _submit(h, cmd)
            torque[2] = imp[2] / dt
            cmd = _force_init(h)
            _torque(cmd, obj, -1, torque.ctypes.data, EF_WORLD_FRAME)
            _submit(h, cmd)
        _submit(h, _step_init(h))
        # pushed = bool(getContactPoints(pusher, obj))
        cmd = _contacts_init(h)
        _contacts_body_a(cmd, pusher)
        _contacts_body_b(cmd, obj)
        if _status_type(_submit(h, cmd)) != CMD_CONTACT_POINT_INFORMATION_COMPLETED:
            return -(i + 1), touched, pushed
        _contacts_get(h, info.ctypes.data)
        pushed = (info[0] & 0xFFFFFFFF) != 0  # the struct's leading int
        touched = touched or pushed
    return 0, touched, pushed


# the steps above compile the friction kernel into their own machine code
stamp_with_sources(globals(), floor_friction)
