"""What an engine step costs inside a push, and how far an episode is from the engine's floor.

    .venv/bin/python bench/step_cost.py --backend pybullet [--episodes 16] [--speed 40]
    .venv/bin/python bench/step_cost.py --backend mujoco --speed 4 --floor aniso
    .venv/bin/python bench/step_cost.py --backend planar --speed 4 --floor aniso

Issue 16 asks for an episode within 1.5x of the engine's own floor: its steps plus its
renders, measured in the same run (issue 24: with the model's physics as well). This script
measures, on one in-process worker and the job's own episodes (`common.strided` slice, the
job's simulator, vision and the default camera), with a subclass of the backend's class that
times and records its calls (`TimedRenders`, `RecordsFriction` and the backend's
`PlanarSteps` / `PybulletSteps` / `MujocoSteps`) and the push protocol handed to
`run_episode` as its `push` (`StepClock.push`, `EngineClock.push`): nothing of the package is
patched.

- **in-push cost per step**: the push's time (`comexp.sim.protocol.push`), minus the tracking
  frames rendered inside it and the tracker's work on them (its `on_frame` / `frame_wanted`
  callbacks: perception, counted with the rest outside physics), over the steps the engine
  took (an engine jumps the still ones, `steps_still`: `PushOutcome.steps` counts those too);
- **the engine's step in pushes**: the engine's own step call, in the states the pushes
  drive it through, in a second run of each episode right after its timed one (builds are
  full resets, so it takes the same steps): pybullet's compiled chunks (`_compiled_steps`,
  `push_steps` and its few lines of argument handling) timed one by one, the friction
  kernel's replay taken off (stepped from Python, without the compiled steps: each
  `_step_once`, Bullet's step with the pusher command and the friction call around it);
  MuJoCo's chunks replayed from their saved states as `mj_step(m, d, n)`; planar's compiled
  calls (`advance`, `advance_chunks`) timed one by one: its friction solve is inside its
  step. Beside it, the same call on each episode's built scene at rest (object resting,
  pusher parked): a pusher contact and a sliding object make a step dearer, so the resting
  step alone understates the floor;
- **the friction model's kernel**: every `FootprintFriction` input of that run
  (`FootprintFriction.inputs`; pybullet: in a third run, so that its timed chunks do not
  hold the recording) replayed through the compiled kernel alone, called as the engines call
  it (planar: none apart from its step);
- the rest of the step, **our Python around the engine** (pusher command, state reads, force
  application, contact query, the protocol's checks): in-push minus engine minus kernel.

Every time is CPU time (`time.process_time`; the engine's per-call timer `time.thread_time`),
not wall time: these machines are shared, and a bench beside a study would otherwise count
the study's turns as its own.

It prints the floors: the engine's (its steps in pushes + renders) and the model's (+ the
friction kernel, the physics the contract asks of an engine), the episode's ratio to each,
and what a step loop compiled whole (no Python between steps) would leave: the model's floor
plus everything outside physics (perception, estimator, builds), as a projection, labelled so.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from typing import Any

import numpy as np
from common import (
    bench_simulator,
    engine_stdout_silenced,
    job_simulator,
    job_specs,
    source_digest,
    strided,
    use_one_cpu,
    warm_up,
)

from comexp.backends import floor_friction as ff
from comexp.backends.numba_kernels import DirectCall
from comexp.episode.loop import run_episode
from comexp.episode.task import EpisodeSpec, build_scene
from comexp.sim.protocol import push
from comexp.sim.simulator import Simulator


class StepClock:
    """CPU time and calls of the pushes (the push protocol, handed to `run_episode` as its
    `push`), of the renders (`TimedRenders`) and of the tracker's work inside the pushes (the
    push's `on_frame` / `frame_wanted` callbacks: masking, boundary, ICP; perception, timed
    as "track"), and the pushes' steps. Times only while `active`."""

    def __init__(self) -> None:
        keys = ("push", "render", "frame", "track")
        self.s: dict[str, float] = dict.fromkeys(keys, 0.0)
        self.n: dict[str, int] = dict.fromkeys(keys, 0)
        self.steps = 0
        self.active = False

    @contextmanager
    def timing(self, key: str) -> Iterator[None]:
        if not self.active:
            yield
            return
        t0 = time.process_time()
        try:
            yield
        finally:
            self.s[key] += time.process_time() - t0
            self.n[key] += 1

    def _tracked(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*a: Any, **k: Any) -> Any:
            t0 = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                self.s["track"] += time.process_time() - t0
                self.n["track"] += 1

        return timed

    def push(self, sim: Simulator, cmd: Any, **kwargs: Any) -> Any:
        """`run_episode`'s push: the protocol's, timed, its tracking callbacks timed apart."""
        if self.active:
            for cb in ("on_frame", "frame_wanted"):
                if kwargs.get(cb) is not None:
                    kwargs[cb] = self._tracked(kwargs[cb])
        with self.timing("push"):
            out = push(sim, cmd, **kwargs)
        if self.active:
            self.steps += out.steps
        return out


class EngineClock:
    """The engine's own step calls, on the thread's CPU clock (its own cost, calibrated,
    taken off each call), while a push of the engine pass is under way (`push`, handed to
    `run_episode`): the backends' mixins below report to it."""

    def __init__(self) -> None:
        self.s = 0.0
        self.steps = 0
        self.in_push = False
        self.clock = time.thread_time
        t0 = self.clock()
        for _ in range(1000):
            self.clock()
        self.own = (self.clock() - t0) / 1001  # one clock read

    def push(self, sim: Simulator, cmd: Any, **kwargs: Any) -> Any:
        self.in_push = True
        try:
            return push(sim, cmd, **kwargs)
        finally:
            self.in_push = False

    def call(self, fn: Callable[[], Any], steps: Callable[[Any], int]) -> Any:
        """`fn()`, timed when in a push; `steps(result)`: the steps it ran."""
        if not self.in_push:
            return fn()
        t0 = self.clock()
        out = fn()
        self.s += self.clock() - t0 - self.own
        self.steps += steps(out)
        return out


# --- a bench subclass of the backend's class: its calls timed and recorded -----------------


class TimedRenders:
    """The images (`render_depth`) and tracking frames (`render_tracking_depth`), timed on
    the `StepClock`; the mixin every backend's bench class starts with (it makes the clocks:
    `clock`, `engine`, and `friction_log`, None or the list `RecordsFriction` fills)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.clock = StepClock()
        self.engine = EngineClock()
        self.friction_log: list[tuple[tuple, list]] | None = None
        super().__init__(*args, **kwargs)

    def render_depth(self) -> Any:
        with self.clock.timing("render"):
            return super().render_depth()

    def render_tracking_depth(self) -> Any:
        with self.clock.timing("frame"):
            return super().render_tracking_depth()


class RecordsFriction:
    """Every step's footprint friction input (`FootprintFriction.inputs`, which the engines
    fill), per friction object the builds make, into `friction_log` while it is a list:
    (the friction's constructor arguments, its inputs)."""

    def build(self, scene: Any) -> None:
        super().build(scene)
        fr = getattr(self, "_fric", None)  # the engines' footprint friction (model)
        log = self.friction_log
        if log is not None and fr is not None:
            fr.inputs = []
            args = (scene.obj, scene.floor.mu_x, scene.floor.mu_y, scene.pusher)
            log.append((args, fr.inputs))


class PlanarSteps:
    """planar's step is its compiled call (`advance`: a chunk; `advance_chunks`: chunks of
    it), the friction solve inside it: each call timed, with the few lines of argument
    handling around the compiled call; the protocol's steps it ran (its model takes fewer
    where `SlowSteps` groups them)."""

    def advance(self, targets: np.ndarray) -> tuple[bool, float]:
        call = super().advance
        return self.engine.call(lambda: call(targets), lambda out: len(targets))

    def advance_chunks(self, targets: np.ndarray, chunk: int, stop: Any) -> list:
        call = super().advance_chunks
        return self.engine.call(lambda: call(targets, chunk, stop), lambda out: len(out) * chunk)


class PybulletSteps:
    """pybullet's step: every compiled chunk (`push_steps`, in `_compiled_steps`) timed, the
    friction kernel inside it (`kernel_inside`: its replay is taken off); stepped from Python
    (no client handle), every `_step_once`: Bullet's step with its pusher command and the
    friction's call around it."""

    kernel_inside = True

    def _compiled_steps(self, targets: np.ndarray) -> bool:
        call = super()._compiled_steps
        return self.engine.call(lambda: call(targets), lambda out: len(targets))

    def _step_once(self) -> None:
        call = super()._step_once
        self.engine.call(call, lambda out: 1)


class MujocoSteps:
    """MuJoCo's steps run inside its compiled loop, where no timer reaches: in a push of the
    engine pass, before every chunk (`_friction_steps`) the engine's integration state is
    saved (`mj_getState`), one chunk per call (`runs_chunks` off: the same steps, as
    `advance_chunks` runs `advance`'s); after each episode, while its model is still built,
    every chunk is replayed from its state as one `mj_step(m, d, n)` (`replay_steps`: the
    pusher coasting at its velocity, the floor's friction force of the chunk's first step
    held)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._snaps: list[tuple[np.ndarray, int]] = []
        super().__init__(*args, **kwargs)

    def runs_chunks(self) -> bool:
        return not self.engine.in_push and super().runs_chunks()

    def _friction_steps(self, m: Any, d: Any, starts: np.ndarray, vels: np.ndarray) -> Any:
        if self.engine.in_push:
            import mujoco

            spec = mujoco.mjtState.mjSTATE_INTEGRATION
            state = np.empty(mujoco.mj_stateSize(m, spec))
            mujoco.mj_getState(m, d, state, spec)
            self._snaps.append((state, len(starts)))
        return super()._friction_steps(m, d, starts, vels)

    def replay_steps(self) -> None:
        """Time the chunks saved since the last call on the model now built."""
        import mujoco

        m, d = self._require()
        sub = self.contact.substeps
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        for state, n in self._snaps:
            mujoco.mj_setState(m, d, state, spec)
            t0 = time.process_time()
            mujoco.mj_step(m, d, n * sub)
            self.engine.s += time.process_time() - t0
            self.engine.steps += n
        self._snaps.clear()


ENGINE_STEPS = {"planar": PlanarSteps, "pybullet": PybulletSteps, "mujoco": MujocoSteps}


def step_cost_simulator(backend: str, floor: str, speed: float) -> Any:
    """The job's simulator (its physics), of a bench subclass of the backend's class whose
    renders, friction inputs and engine steps are timed or recorded on demand."""
    if backend not in ENGINE_STEPS:
        raise SystemExit(f"no engine step timing for backend {backend}")
    mixins = (TimedRenders, RecordsFriction, ENGINE_STEPS[backend])
    return bench_simulator(job_simulator(backend, floor, speed), *mixins)


def raw_step_s(sim: Simulator, spec: EpisodeSpec, n: int) -> float:
    """Seconds per step of the engine's own step call on the episode's built scene (best of
    three runs of n steps). Reaches into the backend for its engine handle: this is the one
    number that must not include the backend's Python."""
    sim.build(build_scene(spec))
    if sim.name == "pybullet":
        import pybullet as pb

        cid = sim._cid

        def run() -> None:
            for _ in range(n):
                pb.stepSimulation(physicsClientId=cid)
    elif sim.name == "mujoco":
        import mujoco

        m, d = sim._require()

        def run() -> None:
            mujoco.mj_step(m, d, n)
    elif sim.name == "planar":
        from comexp.backends import planar_sim

        model = sim._require()
        q = sim.pusher_xy()
        targets = np.repeat(q[None, :], n, axis=0)
        dt, mu_p = sim.settings.timestep_s, sim.scene.obj.mu_pusher
        slow = sim.slow_steps

        def run() -> None:
            model.run(q, targets, dt, mu_p, planar_sim._NO_TRACE, slow)
    else:
        raise SystemExit(f"no raw engine step for backend {sim.name}")
    best = float("inf")
    for _ in range(3):
        t0 = time.process_time()
        run()
        best = min(best, time.process_time() - t0)
    return best / n


def replay_s(log: list[tuple[tuple, list]], dt: float) -> tuple[float, int]:
    """Seconds in the compiled friction kernel alone over every recorded input (steps of
    `dt`, a friction object made anew from each one's arguments), and the count."""
    total, count = 0.0, 0
    for args, inputs in log:
        if not inputs:
            continue
        fr = ff.FootprintFriction(*args)
        g, fs, nrm, dxw, dyw = fr.geo, fr.fs, fr.normal, fr.dxw, fr.dyw
        steps = [(np.array((x, y, w)), yaw, pushed) for x, y, w, yaw, pushed in inputs]
        call = DirectCall(ff.impulse_kernel)  # as the engines call it: no type dispatch
        x0, yaw0, p0 = steps[0]
        call(g, fs.copy(), nrm.copy(), dxw.copy(), dyw.copy(), x0, yaw0, dt, p0)  # resolve
        t0 = time.process_time()
        for xi_hat, yaw, pushed in steps:
            call(g, fs, nrm, dxw, dyw, xi_hat, yaw, dt, pushed)
        total += time.process_time() - t0
        count += len(inputs)
    return total, count


@contextmanager
def recording(sim: Any) -> Iterator[list[tuple[tuple, list]]]:
    """The friction inputs of the builds and steps within, recorded (`RecordsFriction`)."""
    sim.friction_log = log = []
    try:
        yield log
    finally:
        sim.friction_log = None


def floor_pass(sim: Any, spec: EpisodeSpec) -> tuple[float, int, float, int]:
    """The episode once more (builds are full resets: the same steps) with its engine steps
    timed (`EngineClock`; MuJoCo's replayed) and its friction inputs recorded, in a pass of
    their own where the timed call would hold the recording (pybullet), and the kernel
    replayed: (kernel s, kernel steps, engine s without the kernel, engine steps)."""
    engine = sim.engine
    s0, n0 = engine.s, engine.steps
    inside = getattr(sim, "kernel_inside", False)  # the timed calls run the kernel too
    with nullcontext([]) if inside else recording(sim) as log:
        run_episode(spec, sim, push=engine.push)
        if hasattr(sim, "replay_steps"):
            sim.replay_steps()
    if inside:
        with recording(sim) as log:
            run_episode(spec, sim)
    ks, kn = replay_s(log, sim.settings.timestep_s)
    return ks, kn, engine.s - s0 - (ks if inside else 0.0), engine.steps - n0


def measure(backend: str, n: int, speed: float, floor: str, raw_n: int) -> dict[str, Any]:
    specs = strided(job_specs(backend, floor, speed), n)
    sim = step_cost_simulator(backend, floor, speed)  # the job's physics
    out: dict[str, Any] = {"backend": backend, "episodes": len(specs), "speed": speed,
                           "floor": floor, "source": source_digest(backend)}  # fmt: skip
    clock = sim.clock
    walls = []
    kernel_s = kernel_n = engine_s = engine_steps = 0
    try:
        warm_up(specs, sim)  # one-offs per object (renderers, JIT)
        # Each episode timed, then at once run again for its floor (`floor_pass`): the
        # episode and its floor seconds apart, not passes minutes apart on a host whose
        # speed drifts.
        for s in specs:
            clock.active = True
            t0 = time.process_time()
            run_episode(s, sim, push=clock.push)
            walls.append(time.process_time() - t0)
            clock.active = False
            ks, kn, es, en = floor_pass(sim, s)
            kernel_s, kernel_n = kernel_s + ks, kernel_n + kn
            engine_s, engine_steps = engine_s + es, engine_steps + en
        raws = [raw_step_s(sim, s, raw_n) for s in strided(specs, min(4, len(specs)))]
    finally:
        sim.close()
    return out | summary(clock, walls, (kernel_s, kernel_n, engine_s, engine_steps), raws)


def summary(
    t: StepClock, walls: list[float], floor: tuple[float, int, float, int], raws: list[float]
) -> dict[str, Any]:
    """The figures of the timed episodes (`t`, `walls`), their floor passes (the kernel's
    and the engine's seconds and steps) and the raw steps."""
    kernel_s, kernel_n, engine_s, engine_steps = floor
    ne = len(walls)
    physics_s = t.s["push"] - t.s["frame"] - t.s["track"]
    out: dict[str, Any] = dict(
        episode_ms=1e3 * sum(walls) / ne,
        median_ms=1e3 * statistics.median(walls),
        steps_per_ep=t.steps / ne,
        # the engine's own steps: an engine jumps the still ones (`Simulator.steps_still`)
        stepped_per_ep=engine_steps / ne,
        step_us=1e6 * physics_s / max(engine_steps, 1),
        raw_us=1e6 * statistics.median(raws),
        engine_us=1e6 * engine_s / max(engine_steps, 1),
        kernel_us=1e6 * kernel_s / max(engine_steps, 1),
        kernel_steps=kernel_n,
        render_ms=1e3 * (t.s["render"] + t.s["frame"]) / ne,
        track_ms=1e3 * t.s["track"] / ne,
        renders_per_ep=t.n["render"] / ne,
        frames_per_ep=t.n["frame"] / ne,
    )
    # the engine's step as the pushes drive it; the one on a resting scene beside it
    out["python_us"] = out["step_us"] - out["engine_us"] - out["kernel_us"]
    out["physics_ms"] = 1e3 * physics_s / ne
    # perception (the tracking inside pushes too), estimator, builds
    out["other_ms"] = out["episode_ms"] - out["physics_ms"] - out["render_ms"]
    steps = out["stepped_per_ep"]
    out["floor_ms"] = steps * out["engine_us"] / 1e3 + out["render_ms"]
    out["model_floor_ms"] = out["floor_ms"] + steps * out["kernel_us"] / 1e3
    out["compiled_ms"] = out["model_floor_ms"] + out["other_ms"]
    return out


def report(o: dict[str, Any]) -> None:
    print(
        f"== {o['backend']} (source {o['source']}), floor {o['floor']}, {o['speed']:g} cm/s: "
        f"{o['episodes']} episodes, one worker; load {os.getloadavg()[0]:.2f}"
    )
    print(
        f"episode             {o['episode_ms']:.0f} ms mean, {o['median_ms']:.0f} median; "
        f"{o['steps_per_ep']:.0f} steps ({o['stepped_per_ep']:.0f} stepped, the rest "
        f"jumped still), {o['renders_per_ep']:.1f} images + "
        f"{o['frames_per_ep']:.1f} tracking frames"
    )
    st = o["step_us"]
    print(
        f"step inside a push  {st:.1f} us  (push CPU time minus its frames' renders and "
        f"tracking, per stepped step)"
    )
    planar = o["backend"] == "planar"
    for label, key in (
        ("  engine's step", "engine_us"),
        ("  friction kernel", "kernel_us"),
        ("  our Python", "python_us"),
    ):
        note = "; planar's is inside its step" if planar and key == "kernel_us" else ""
        print(f"{label:<20}{o[key]:.1f} us  ({100 * o[key] / st:.0f}%{note})")
    print(
        f"  (the engine's step on the resting scene: {o['raw_us']:.3f} us; in pushes it "
        f"costs {o['engine_us'] / o['raw_us']:.2f}x that"
        + ("; at rest planar solves nothing)" if planar else ")")
    )
    print(
        f"episode split       physics {o['physics_ms']:.0f} ms, renders {o['render_ms']:.0f} "
        f"ms, the rest (perception, estimator, builds) {o['other_ms']:.0f} ms, of it "
        f"tracking in pushes {o['track_ms']:.1f} ms"
    )
    print(
        f"engine floor        {o['floor_ms']:.0f} ms (the engine's steps in pushes + renders): "
        f"episode {o['episode_ms'] / o['floor_ms']:.2f}x it"
    )
    print(
        f"with the model      {o['model_floor_ms']:.0f} ms (+ the friction kernel): episode "
        f"{o['episode_ms'] / o['model_floor_ms']:.2f}x it (target <= 1.5)"
    )
    print(
        f"no Python between   {o['compiled_ms']:.0f} ms (that floor + perception, estimator, "
        f"builds; a projection): episode {o['episode_ms'] / o['compiled_ms']:.2f}x it"
    )


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", choices=("pybullet", "mujoco", "planar"), default="pybullet")
    ap.add_argument("--episodes", type=int, default=16)
    ap.add_argument("--speed", type=float, default=40.0, help="cm/s")
    ap.add_argument("--floor", choices=("iso", "aniso"), default="iso")
    ap.add_argument("--raw-steps", type=int, default=2000, help="steps per raw-rate run")
    a = ap.parse_args(argv)
    use_one_cpu()
    with engine_stdout_silenced():
        o = measure(a.backend, a.episodes, a.speed, a.floor, a.raw_steps)
    report(o)
    return 0


if __name__ == "__main__":
    sys.exit(main())
