"""What an engine step costs inside a push, and how far an episode is from the engine's floor.

    .venv/bin/python bench/step_cost.py --backend pybullet [--episodes 16] [--speed 40]
    .venv/bin/python bench/step_cost.py --backend mujoco --speed 4 --floor aniso
    .venv/bin/python bench/step_cost.py --backend planar --speed 4 --floor aniso

Issue 16 asks for an episode within 1.5x of the engine's own floor: its steps plus its
renders, measured in the same run (issue 24: with the model's physics as well). This script
measures, on one in-process worker and the job's own episodes (`episode_profile.strided`
slice, vision and the default camera):

- **in-push cost per step**: `sim.push` time, minus the tracking frames rendered inside
  it and the tracker's work on them (its `on_frame` / `frame_wanted` callbacks: perception,
  counted with the rest outside physics), over the steps the engine took (an engine jumps
  the still ones, `Simulator._steps_still`: `PushOutcome.steps` counts those too);
- **the engine's step in pushes**: the engine's own step call alone, no Python of ours
  around it, in the states the pushes drive it through (`EngineStepsInPushes`: pybullet's
  compiled chunks, `push_steps`, timed one by one, the friction kernel's replay taken off:
  Bullet's step with the C commands that drive it (from Python, without the compiled steps:
  its `stepSimulation` calls); MuJoCo's chunks replayed from their saved states as
  `mj_step(m, d, n)`; planar's compiled calls (`_run`, `_run_chunks`) timed one by one: its
  friction solve is inside its step), in a second run of each episode right after its timed one
  (builds are full resets, so it takes the same steps). Beside it, the same call on each
  episode's built scene at rest (object resting, pusher parked): a pusher contact and a
  sliding object make a step dearer, so the resting step alone understates the floor;
- **the friction model's kernel**: every `FootprintFriction` input of that second run
  recorded and replayed through the compiled kernel alone, called as the engines call it
  (planar: none apart from its step);
- the rest of the step, **our Python around the engine** (pusher command, state reads, force
  application, contact query, the protocol's checks): in-push minus engine minus kernel.

Every time is CPU time (`time.process_time`; pybullet's per-call timer `time.thread_time`),
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
from collections.abc import Sequence
from typing import Any

import numpy as np
from episode_profile import (
    engine_stdout_silenced,
    job_backend_options,
    job_specs,
    source_digest,
    strided,
    use_one_cpu,
)

from comexp.backends import floor_friction as ff
from comexp.backends.numba_kernels import DirectCall
from comexp.experiment import episode as episode_mod
from comexp.experiment.episode import EpisodeSpec, run_episode
from comexp.experiment.simulator import Simulator, make_simulator


class Timers:
    """CPU time and calls of the wrapped methods, and the steps of the pushes. A push's
    `on_frame` and `frame_wanted` callbacks (the tracker following the push: masking,
    boundary, ICP) are timed as "track": they run inside the push but are perception."""

    def __init__(self) -> None:
        keys = ("push", "render", "frame", "track")
        self.s: dict[str, float] = dict.fromkeys(keys, 0.0)
        self.n: dict[str, int] = dict.fromkeys(keys, 0)
        self.steps = 0
        self.active = True  # off: the wrapped methods run untimed

    def _timed(self, fn: Any, key: str) -> Any:
        def timed(*a: Any, **k: Any) -> Any:
            if not self.active:
                return fn(*a, **k)
            t0 = time.process_time()
            out = fn(*a, **k)
            self.s[key] += time.process_time() - t0
            self.n[key] += 1
            if key == "push":
                self.steps += out.steps
            return out

        return timed

    def wrap(self, sim: Simulator, name: str, key: str) -> None:
        timed = self._timed(getattr(sim, name), key)
        if key != "push":
            setattr(sim, name, timed)
            return

        def push(*a: Any, **k: Any) -> Any:
            for cb in ("on_frame", "frame_wanted"):
                if self.active and k.get(cb) is not None:
                    k[cb] = self._timed(k[cb], "track")
            return timed(*a, **k)

        setattr(sim, name, push)


def raw_step_s(sim: Simulator, spec: EpisodeSpec, n: int) -> float:
    """Seconds per step of the engine's own step call on the episode's built scene (best of
    three runs of n steps). Reaches into the backend for its engine handle: this is the one
    number that must not include the backend's Python."""
    sim.build(episode_mod.build_scene(spec))
    best = float("inf")
    if sim.name == "pybullet":
        import pybullet as pb

        cid = sim._cid  # type: ignore[attr-defined]
        for _ in range(3):
            t0 = time.process_time()
            for _ in range(n):
                pb.stepSimulation(physicsClientId=cid)
            best = min(best, time.process_time() - t0)
    elif sim.name == "mujoco":
        import mujoco

        m, d = sim._require()  # type: ignore[attr-defined]
        for _ in range(3):
            t0 = time.process_time()
            mujoco.mj_step(m, d, n)
            best = min(best, time.process_time() - t0)
    elif sim.name == "planar":
        from comexp.backends import planar_sim

        m = sim._require()  # type: ignore[attr-defined]
        q = sim._pusher_xy()
        targets = np.repeat(q[None, :], n, axis=0)
        dt, mu_p = sim.settings.timestep_s, sim._scene.obj.mu_pusher  # type: ignore[attr-defined]
        for _ in range(3):
            t0 = time.process_time()
            m.run(q, targets, dt, mu_p, planar_sim._NO_TRACE, sim.slow_steps)  # type: ignore[attr-defined]
            best = min(best, time.process_time() - t0)
    else:
        raise SystemExit(f"no raw engine step for backend {sim.name}")
    return best / n


class ImpulseRecorder:
    """Patches FootprintFriction to keep every step's friction input, per friction object
    (`FootprintFriction.inputs`: filled by `impulse` and by MuJoCo's compiled loop alike)."""

    def __init__(self) -> None:
        self.objects: list[tuple[tuple, dict, list]] = []
        self._init = ff.FootprintFriction.__init__

    def __enter__(self) -> ImpulseRecorder:
        rec, init = self.objects, self._init

        def patched_init(fr: Any, *a: Any, **k: Any) -> None:
            init(fr, *a, **k)
            fr.inputs = []
            rec.append((a, k, fr.inputs))

        ff.FootprintFriction.__init__ = patched_init  # type: ignore[method-assign]
        return self

    def __exit__(self, *exc: object) -> None:
        ff.FootprintFriction.__init__ = self._init  # type: ignore[method-assign]

    def replay_s(self, dt: float) -> tuple[float, int]:
        """Seconds in the compiled kernel alone over every recorded input (steps of `dt`),
        and the count."""
        total, count = 0.0, 0
        for a, k, inputs in self.objects:
            fr = ff.FootprintFriction(*a, **k)
            g, fs, nrm, dxw, dyw = fr.geo, fr.fs, fr.normal, fr.dxw, fr.dyw
            steps = [(np.array((x, y, w)), yaw, pushed) for x, y, w, yaw, pushed in inputs]
            if not steps:
                continue
            call = DirectCall(ff.impulse_kernel)  # as the engines call it: no type dispatch
            x0, yaw0, p0 = steps[0]
            call(g, fs.copy(), nrm.copy(), dxw.copy(), dyw.copy(), x0, yaw0, dt, p0)  # resolve
            t0 = time.process_time()
            for xi_hat, yaw, pushed in steps:
                call(g, fs, nrm, dxw, dyw, xi_hat, yaw, dt, pushed)
            total += time.process_time() - t0
            count += len(inputs)
        return total, count


class EngineStepsInPushes:
    """The engine's own step as the pushes drive it (contacts with the pusher, a sliding
    object), not only on a resting scene: what `raw_step_s` cannot see.

    pybullet: every compiled chunk (`push_steps`) of a pass is timed on the thread's CPU
    clock (the clock's own cost, calibrated, is taken off each call); the friction kernel
    runs inside it (`kernel_inside`: the caller takes the kernel's replay off); stepped
    from Python (no client handle), every `stepSimulation` call. MuJoCo's steps run inside the
    compiled loop, where no timer reaches: before every chunk of the pass the engine's
    integration state is saved (`mj_getState`), and after each episode, while its model is
    still built, every chunk is replayed from its state as one `mj_step(m, d, n)` (the pusher
    coasting at its velocity, the floor's friction force of the chunk's first step held); in
    that pass MuJoCo runs one chunk per call (`batches_chunks` off: the same steps)."""

    def __init__(self, sim: Simulator) -> None:
        self.sim = sim
        self.s = 0.0
        self.steps = 0
        self._snaps: list[tuple[np.ndarray, int]] = []
        self._in_push = False
        self.kernel_inside = False  # the timed calls run the friction kernel too

    def _timed_in_pushes(self, step: Any, steps_of: Any) -> Any:
        """`step` timed call by call on the thread's CPU clock (its own cost, calibrated,
        taken off) while a push is under way; `steps_of(args, result)`: the steps one call
        ran."""
        clock = time.thread_time
        t0 = clock()
        for _ in range(1000):
            clock()
        own = (clock() - t0) / 1001  # one clock read

        def timed(*a: Any, **k: Any) -> Any:
            if not self._in_push:
                return step(*a, **k)
            t0 = clock()
            out = step(*a, **k)
            self.s += clock() - t0 - own
            self.steps += steps_of(a, out)
            return out

        push = self.sim.push
        self._own_push = self.sim.__dict__.get("push")  # a wrapper already set, or None

        def pushing(*a: Any, **k: Any) -> Any:
            self._in_push = True
            try:
                return push(*a, **k)
            finally:
                self._in_push = False

        self.sim.push = pushing  # type: ignore[method-assign]
        return timed

    def __enter__(self) -> EngineStepsInPushes:
        sim = self.sim
        if sim.name == "pybullet" and getattr(sim, "_handle", None) is not None:
            from comexp.backends import pybullet_sim

            # push_steps(handle, pusher, object, z, targets, ...): a step per target
            self._pbsim, self._step = pybullet_sim, pybullet_sim._push_steps_call
            pybullet_sim._push_steps_call = self._timed_in_pushes(
                self._step, lambda a, out: len(a[4])
            )
            self.kernel_inside = True
        elif sim.name == "pybullet":
            import pybullet as pb

            self._pb, self._step = pb, pb.stepSimulation
            pb.stepSimulation = self._timed_in_pushes(self._step, lambda a, out: 1)
        elif sim.name == "planar":
            from comexp.backends import planar_sim

            # the protocol's steps of a chunk (its model takes fewer where `SlowSteps` groups),
            # and of the chunks run in one call (`_run_chunks`: how many ran x the chunk)
            self._planar = planar_sim
            self._step = planar_sim._run_call, planar_sim._run_chunks_call
            planar_sim._run_call = self._timed_in_pushes(self._step[0], lambda a, out: len(a[8]))
            planar_sim._run_chunks_call = self._timed_in_pushes(
                self._step[1], lambda a, out: out * a[9]
            )
        elif sim.name == "mujoco":
            import mujoco

            self._mj = mujoco
            fn = sim._friction_steps  # type: ignore[attr-defined]
            spec = mujoco.mjtState.mjSTATE_INTEGRATION

            def snapped(m: Any, d: Any, starts: np.ndarray, vels: np.ndarray) -> Any:
                state = np.empty(mujoco.mj_stateSize(m, spec))
                mujoco.mj_getState(m, d, state, spec)
                self._snaps.append((state, len(starts)))
                return fn(m, d, starts, vels)

            sim._friction_steps = snapped  # type: ignore[attr-defined]
            # this pass runs one chunk per call (the same steps: `_advance_chunks` runs
            # `_advance`'s), so that every chunk has its state saved
            self._batches = sim.batches_chunks
            sim.batches_chunks = False
        return self

    def replay(self) -> None:
        """MuJoCo: time the chunks saved since the last call on the model now built."""
        if not self._snaps:
            return
        mujoco = self._mj
        m, d = self.sim._require()  # type: ignore[attr-defined]
        sub = self.sim.contact.substeps  # type: ignore[attr-defined]
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        for state, n in self._snaps:
            mujoco.mj_setState(m, d, state, spec)
            t0 = time.process_time()
            mujoco.mj_step(m, d, n * sub)
            self.s += time.process_time() - t0
            self.steps += n
        self._snaps.clear()

    def _restore_push(self) -> None:
        if self._own_push is None:
            del self.sim.push  # back to the class's method
        else:
            self.sim.push = self._own_push  # type: ignore[method-assign]

    def __exit__(self, *exc: object) -> None:
        if self.sim.name == "pybullet" and self.kernel_inside:
            self._pbsim._push_steps_call = self._step
            self._restore_push()
        elif self.sim.name == "pybullet":
            self._pb.stepSimulation = self._step
            self._restore_push()
        elif self.sim.name == "planar":
            self._planar._run_call, self._planar._run_chunks_call = self._step
            self._restore_push()
        elif self.sim.name == "mujoco":
            del self.sim._friction_steps  # back to the class's method
            self.sim.batches_chunks = self._batches


def measure(backend: str, n: int, speed: float, floor: str, raw_n: int) -> dict[str, Any]:
    specs = strided(job_specs(backend, floor, speed), n)
    sim = make_simulator(backend, **job_backend_options(backend, floor, speed))  # the job's physics
    out: dict[str, Any] = {"backend": backend, "episodes": len(specs), "speed": speed,
                           "floor": floor, "source": source_digest(backend)}  # fmt: skip
    try:
        first: dict[str, EpisodeSpec] = {}
        for s in specs:
            first.setdefault(s.object, s)
        for s in first.values():  # warm-up: one-offs per object (renderers, JIT)
            run_episode(s, sim)
        t = Timers()
        t.wrap(sim, "push", "push")
        t.wrap(sim, "render_depth", "render")
        t.wrap(sim, "render_tracking_depth", "frame")
        walls = []
        kernel_s, kernel_n = 0.0, 0
        engine_s, engine_steps = 0.0, 0
        # Each episode timed, then at once run again (builds are full resets: the same
        # steps) with its friction inputs recorded and its engine steps timed, and both
        # replayed: the episode and its floor seconds apart, not passes minutes apart on a
        # host whose speed drifts.
        for s in specs:
            t.active = True
            t0 = time.process_time()
            run_episode(s, sim)
            walls.append(time.process_time() - t0)
            t.active = False
            with ImpulseRecorder() as rec, EngineStepsInPushes(sim) as engine:
                run_episode(s, sim)
                engine.replay()
            ks, kn = rec.replay_s(sim.settings.timestep_s)
            kernel_s, kernel_n = kernel_s + ks, kernel_n + kn
            inside = ks if engine.kernel_inside else 0.0  # timed with the engine's steps
            engine_s, engine_steps = engine_s + engine.s - inside, engine_steps + engine.steps
        for name in ("push", "render_depth", "render_tracking_depth"):
            delattr(sim, name)  # back to the class's methods
        raws = [raw_step_s(sim, s, raw_n) for s in strided(specs, min(4, len(specs)))]
    finally:
        sim.close()
    ne = len(specs)
    physics_s = t.s["push"] - t.s["frame"] - t.s["track"]
    out.update(
        episode_ms=1e3 * sum(walls) / ne,
        median_ms=1e3 * statistics.median(walls),
        steps_per_ep=t.steps / ne,
        # the engine's own steps: an engine jumps the still ones (`Simulator._steps_still`)
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
