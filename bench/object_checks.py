"""Tipping and out-of-view risk of the objects, measured in a simulator.

Two checks per object, printed as one table row:

1. Tipping (floor mu = 1, pusher mu = 1, 40 cm/s, the harshest condition of the grid): for the
   object's study CoMs (`com_points`, k < --coms) and for adversarial CoMs (the corners of the
   footprint shrunk by the 1 cm CoM margin, i.e. CoMs as close to two edges as the study
   allows), push at every edge whose line of action can pass through the CoM, straight
   through it and offset by +-1.5 cm along the edge. Report the worst tilt (deg) and the
   number of pushes that were not `ok`.
2. Sliding (floor mu = 0.1, 40 cm/s): 5 pushes in a row, all along the same direction through
   the CoM (the worst case for drifting out of the 0.6 m floor), starting at the floor's
   centre: longest single slide and the distance travelled, and whether the object stayed in
   view.

Usage:  .venv/bin/python bench/object_checks.py [--backend pybullet] [--objects a b] [--coms 3]
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, replace

import numpy as np
from shapely.geometry import LineString, Point

from comexp.experiment.objects import (
    ObjectDef,
    _name_key,
    com_points,
    load_objects,
)
from comexp.experiment.simulator import PushStatus, Simulator, contact_push, make_simulator
from comexp.method.scene import FloorSpec, PusherSpec, SceneSpec

SPEED_M_S = 0.4
PUSH_LENGTH_M = 0.03
OFFSET_CM = 1.5
MARGIN_CM = 1.0


@dataclass
class Push:
    contact_cm: tuple[float, float]  # object frame
    normal: tuple[float, float]  # inward unit normal, object frame


def _edge_pushes(obj: ObjectDef, com: tuple[float, float], pusher_r_cm: float) -> list[Push]:
    """Pushes along edge normals whose line passes through the CoM (and +-OFFSET_CM beside it),
    kept only if the pusher can get there from outside without touching another edge first."""
    poly = obj.polygon
    pts = np.asarray(obj.outline_cm)
    out = []
    for k in range(len(pts)):
        a, b = pts[k], pts[(k + 1) % len(pts)]
        e = b - a
        length = float(np.hypot(*e))
        t_hat = e / length
        n = np.array([-t_hat[1], t_hat[0]])  # CCW outline: left normal points inward
        s_com = float((np.asarray(com) - a) @ t_hat)
        for ds in (0.0, -OFFSET_CM, OFFSET_CM):
            s = s_com + ds
            if not 0.0 <= s <= length:
                continue
            c = a + s * t_hat
            start = c - n * (pusher_r_cm + 1.0)
            # the pusher's approach path must stay clear of the object until the contact
            approach = LineString([start, c - n * pusher_r_cm * 1.05])
            if approach.distance(poly) < pusher_r_cm * 1.02:
                continue
            # the line of action must enter the object at this edge
            if not poly.contains(Point(c + n * 0.05)):
                continue
            out.append(Push((float(c[0]), float(c[1])), (float(n[0]), float(n[1]))))
    return out


def _adversarial_coms(obj: ObjectDef) -> list[tuple[float, float]]:
    inner = obj.polygon.buffer(-MARGIN_CM, join_style="mitre")
    geoms = getattr(inner, "geoms", [inner])
    return [(float(x), float(y)) for g in geoms for x, y in list(g.exterior.coords)[:-1]]


def _do_push(sim: Simulator, scene: SceneSpec, push: Push):
    pose = sim.true_pose()
    c_world = pose.to_world(np.asarray(push.contact_cm) / 100.0)
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    nx, ny = push.normal
    n_world = (c * nx - s * ny, s * nx + c * ny)
    cmd = contact_push(c_world, n_world, PUSH_LENGTH_M, SPEED_M_S, scene.pusher.radius_m)
    return sim.push(cmd)


def tipping_check(sim: Simulator, obj: ObjectDef, n_coms: int) -> dict:
    r_cm = PusherSpec().radius_m * 100
    max_tilt, n_push, bad, worst = 0.0, 0, {}, ""
    coms = [("com", c) for c in com_points(obj, n_coms)] + [
        ("adv", c) for c in _adversarial_coms(obj)
    ]
    for kind, com in coms:
        for push in _edge_pushes(obj, com, r_cm):
            scene = SceneSpec(FloorSpec(1.0, 1.0), obj.model(com, izz_scale=1.0, mu_pusher=1.0))
            sim.build(scene)
            out = _do_push(sim, scene, push)
            n_push += 1
            if out.max_tilt_deg > max_tilt:
                max_tilt = out.max_tilt_deg
                worst = f"{kind} ({com[0]:.1f},{com[1]:.1f})"
            if out.status is not PushStatus.OK:
                bad[out.status.value] = bad.get(out.status.value, 0) + 1
    return {"pushes": n_push, "max_tilt_deg": max_tilt, "not_ok": bad, "worst": worst}


def slide_check(sim: Simulator, obj: ObjectDef) -> dict:
    com = com_points(obj, 1)[0]
    r_cm = PusherSpec().radius_m * 100
    # the push through the CoM along the longest-travel edge normal: pick the first one found
    push = _edge_pushes(obj, com, r_cm)[0]
    scene = SceneSpec(FloorSpec(0.1, 0.1), obj.model(com, izz_scale=1.0, mu_pusher=1.0))
    sim.build(scene)
    start = sim.true_pose()
    slides, status = [], "ok"
    for _ in range(5):
        out = _do_push(sim, scene, push)
        slides.append(
            math.hypot(
                out.pose_after.x_m - out.pose_before.x_m, out.pose_after.y_m - out.pose_before.y_m
            )
        )
        if out.status is not PushStatus.OK:
            status = out.status.value
            break
    end = sim.true_pose()
    return {
        "max_slide_cm": 100 * max(slides),
        "travel_cm": 100 * math.hypot(end.x_m - start.x_m, end.y_m - start.y_m),
        "status": status,
    }


def _counts(counts: dict[str, int]) -> str:
    return ",".join(f"{k}:{v}" for k, v in sorted(counts.items())) or "-"


def object_table(objs: list[ObjectDef]) -> str:
    """Markdown table of the objects (the one in docs/objects.md)."""
    rows = [
        "| name | kind | size x*y (cm) | min width (cm) | height (cm) | area (cm^2) | parts |",
        "|---|---|---|---|---|---|---|",
    ]
    for o in objs:
        sx, sy = o.size_cm
        parts = "convex" if o.convex else f"{len(o.convex_parts_cm())} convex parts"
        rows.append(
            f"| {o.name} | {o.description} | {sx:.1f} x {sy:.1f} | {o.min_width_cm:.1f} | "
            f"{o.height_cm:.1f} | {o.area_cm2:.1f} | {parts} |"
        )
    return "\n".join(rows)


def _random_push(obj: ObjectDef, rng: np.random.Generator, pusher_r_cm: float) -> Push:
    """A push along the inward normal at a uniformly random reachable point of the outline."""
    pts = np.asarray(obj.outline_cm)
    edges = [(pts[k], pts[(k + 1) % len(pts)]) for k in range(len(pts))]
    lengths = np.array([np.hypot(*(b - a)) for a, b in edges])
    for _ in range(1000):
        a, b = edges[rng.choice(len(edges), p=lengths / lengths.sum())]
        t_hat = (b - a) / np.hypot(*(b - a))
        c = a + rng.uniform(0, 1) * (b - a)
        n = np.array([-t_hat[1], t_hat[0]])
        approach = LineString([c - n * (pusher_r_cm + 1.0), c - n * pusher_r_cm * 1.05])
        if approach.distance(obj.polygon) >= pusher_r_cm * 1.02:
            return Push((float(c[0]), float(c[1])), (float(n[0]), float(n[1])))
    raise RuntimeError(f"{obj.name}: no reachable contact found")


def random_walk_check(sim: Simulator, obj: ObjectDef, trials: int, mu: float) -> dict:
    """5 pushes at random reachable contacts along the inward normal, from the floor centre:
    how often the object leaves the view (the estimator's choices are not random, but this
    gives the scale of the risk)."""
    r_cm = PusherSpec().radius_m * 100
    rng = np.random.default_rng([*_name_key(obj.name), 1234])
    statuses: dict[str, int] = {}
    travel = []
    for t in range(trials):
        com = com_points(obj, trials)[t]
        scene = SceneSpec(FloorSpec(mu, mu), obj.model(com, izz_scale=1.0, mu_pusher=1.0))
        sim.build(scene)
        status = "ok"
        for _ in range(5):
            out = _do_push(sim, scene, _random_push(obj, rng, r_cm))
            if out.status is not PushStatus.OK:
                status = out.status.value
                break
        statuses[status] = statuses.get(status, 0) + 1
        end = sim.true_pose()
        travel.append(100 * math.hypot(end.x_m, end.y_m))
    return {"statuses": statuses, "max_travel_cm": max(travel, default=0.0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--table", action="store_true", help="print the object table and exit")
    ap.add_argument("--backend", default="pybullet")
    ap.add_argument("--objects", nargs="*", default=None)
    ap.add_argument("--coms", type=int, default=3, help="study CoMs per object (k < coms)")
    ap.add_argument("--height-cm", type=float, default=None, help="override every height")
    ap.add_argument("--walks", type=int, default=10, help="random 5-push walks per object")
    args = ap.parse_args()
    objs = list(load_objects(args.objects or None).values())
    if args.height_cm is not None:
        objs = [replace(o, height_cm=args.height_cm) for o in objs]
    if args.table:
        print(object_table(objs))
        return
    sim = make_simulator(args.backend)
    t0 = time.perf_counter()
    print(f"backend={args.backend}  tipping: floor mu 1, pusher mu 1, {SPEED_M_S * 100:.0f} cm/s;")
    print(f"sliding: floor mu 0.1, {SPEED_M_S * 100:.0f} cm/s, 5 pushes in one direction\n")
    hdr = (
        f"{'object':24s} {'h_cm':>5s} {'pushes':>6s} {'max_tilt':>8s} {'not_ok':>14s} "
        f"{'worst tilt at':>22s} | {'slide_cm':>8s} {'5-push_cm':>9s} {'status':>9s} | "
        f"{'walks mu 0.1':>16s} {'walks mu 1':>12s}"
    )
    print(hdr)
    print("-" * len(hdr))
    total_push, total_bad, all_tilt = 0, 0, 0.0
    walks: dict[float, list[dict]] = {0.1: [], 1.0: []}
    for obj in objs:
        tip = tipping_check(sim, obj, args.coms)
        sl = slide_check(sim, obj)
        w01 = random_walk_check(sim, obj, args.walks, 0.1)
        w1 = random_walk_check(sim, obj, args.walks, 1.0)
        walks[0.1].append(w01)
        walks[1.0].append(w1)
        total_push += tip["pushes"]
        total_bad += sum(tip["not_ok"].values())
        all_tilt = max(all_tilt, tip["max_tilt_deg"])
        bad = ",".join(f"{k}:{v}" for k, v in tip["not_ok"].items()) or "-"
        print(
            f"{obj.name:24s} {obj.height_cm:5.1f} {tip['pushes']:6d} {tip['max_tilt_deg']:8.2f} "
            f"{bad:>14s} {tip['worst']:>22s} | {sl['max_slide_cm']:8.1f} "
            f"{sl['travel_cm']:9.1f} {sl['status']:>9s} | {_counts(w01['statuses']):>16s} "
            f"{_counts(w1['statuses']):>12s}"
        )
    sim.close()
    for mu, ws in walks.items():
        tot: dict[str, int] = {}
        for w in ws:
            for k, v in w["statuses"].items():
                tot[k] = tot.get(k, 0) + v
        far = max(w["max_travel_cm"] for w in ws)
        print(f"random walks, floor mu {mu}: {_counts(tot)}; farthest end from centre {far:.1f} cm")
    print(
        f"\n{total_push} tipping pushes, {total_bad} not ok, worst tilt {all_tilt:.2f} deg; "
        f"{time.perf_counter() - t0:.1f} s"
    )


if __name__ == "__main__":
    main()
