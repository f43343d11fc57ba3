"""Ground of one scan at a time on simulated UAV flights: this package against Patchwork++.

Usage: .venv/bin/python benchmarks/bench_scan_ground.py [--quick | --smoke --out DIR]

Patchwork++ (Lee et al. 2022; `pypatchworkpp` on PyPI) is the reference ground segmenter
for scans from a moving vehicle: it takes one scan, in a level frame centred on the
sensor, with the sensor's height above the ground as its prior. Both run here on the same
messages of simulated 10 Hz flights (40 m above the terrain, ~50 000 points a message):

- `ours`: the obstacle detector's ground step (`StreamingGround`) on the map-frame clouds,
  with its rolling ground context of earlier messages;
- `ours, no context` (`context.radius` 0): each scan alone, as Patchwork++ sees it;
- `patchwork++`: its defaults but for `sensor_height` (the flight's 40 m) and `max_range`
  (150 m: its 80 m default leaves the swath's far corners unlabelled, counted here as not
  ground);
- `patchwork++ best`: the best kappa of a small grid of its settings, chosen per flight
  (generous to the anchor: it sees the answers).

Patchwork++ gets the points relative to the vehicle in the level map frame (what a flight
stack with odometry has) and their intensity scaled to 0-1. Reported per flight: ground
kappa, Type I and II (%), the share of building, wire and tower points taken for ground
(%), and ms per message (Patchwork++'s `estimateGround` alone, C++; ours the whole ground
step in Python). Writes benchmarks/results/scan_ground.json (to --out DIR if given).
Without pypatchworkpp installed, this package's rows only.
"""
from __future__ import annotations

import itertools
import json
import sys
import time

import numpy as np

from lidar_obstacles.config import ObstacleDetectorConfig, replace
from lidar_obstacles.core.metrics import ground_object_errors
from lidar_obstacles.core.pipeline import StreamingGround
from lidar_obstacles.core.simulate import INTENSITY_SCALE, SimSettings, simulate_flight
from common import (bench_args, installed, per_mode,  # (benchmarks/ is on the path)
                    quiet_stdout, table)

ALTITUDE = SimSettings().altitude  # m above the terrain: Patchwork++'s sensor height
# (scene, seed): the default flights, and an urban one whose blocks of buildings fill
# most of the swath
FLIGHTS = [("mixed", 0), ("corridor", 0), ("forest", 0), ("urban", 0), ("urban", 1)]
GRID = {"th_dist": [0.125, 0.2, 0.3], "max_range": [80.0, 150.0],
        "enable_RNR": [True, False]}


def flight(scene: str, seed: int, seconds: float) -> list:
    return list(simulate_flight(SimSettings(scene=scene, seed=seed, duration=seconds,
                                            frame="map")))


def xyz_of(frame) -> np.ndarray:
    p = frame.points
    return np.column_stack([p["x"], p["y"], p["z"]]).astype(np.float64)


def ours(frames: list, cfg: ObstacleDetectorConfig) -> tuple[np.ndarray, float]:
    """(P,) bool ground over the flight's points, seconds per message."""
    ground = StreamingGround(cfg)
    out, spent = [], 0.0
    for f in frames:
        xyz = xyz_of(f)
        t0 = time.perf_counter()
        g = ground.classify(xyz, f.stamp)[0]  # (and timings, far points, distinct points)
        spent += time.perf_counter() - t0
        out.append(g.ground)
    return np.concatenate(out), spent / len(frames)


def patchwork(frames: list, **settings) -> tuple[np.ndarray, float]:
    """(P,) bool ground of Patchwork++ with `settings` over its defaults, seconds per
    message."""
    import pypatchworkpp

    params = pypatchworkpp.Parameters()
    params.verbose = False
    params.sensor_height = ALTITUDE
    params.max_range = 150.0
    for name, value in settings.items():
        setattr(params, name, value)
    with quiet_stdout():  # its constructor greets on stdout
        seg = pypatchworkpp.patchworkpp(params)
    out, spent = [], 0.0
    for f in frames:
        p = f.points
        scan = np.column_stack([xyz_of(f) - f.position, p["intensity"] / INTENSITY_SCALE])
        t0 = time.perf_counter()
        seg.estimateGround(scan)
        spent += time.perf_counter() - t0
        g = np.zeros(len(p), bool)
        g[np.asarray(seg.getGroundIndices(), np.int64)] = True
        out.append(g)
    return np.concatenate(out), spent / len(frames)


def scores(ref: np.ndarray, ground: np.ndarray) -> dict:
    e = ground_object_errors(ref == 2, ground)
    hard = np.isin(ref, [6, 14, 15])
    return {"kappa": e["kappa"], "type_i_pct": 100 * e["type_i"],
            "type_ii_pct": 100 * e["type_ii"],
            "building_wire_tower_as_ground_pct": 100 * float(ground[hard].mean())
            if hard.any() else float("nan")}


def main() -> int:
    args = bench_args(__doc__, "3 s flights of two scenes, no grid search",
                      "a 1 s flight, one setting of the grid")
    with_patchwork = installed("pypatchworkpp", "pypatchworkpp")
    seconds = per_mode(args, 10.0, 3.0, 1.0)
    flights = per_mode(args, FLIGHTS, FLIGHTS[:1] + FLIGHTS[-1:], FLIGHTS[:1])
    # the grid search runs only the anchor: the smoke run checks it runs, on one setting
    grid = per_mode(args, GRID, {}, {name: values[:1] for name, values in GRID.items()})
    cfg = ObstacleDetectorConfig()
    alone = replace(cfg, {"context.radius": 0.0})
    rows = []
    for scene, seed in flights:
        frames = flight(scene, seed, seconds)
        ref = np.concatenate([f.points["classification"] for f in frames])
        runs = {"ours": lambda: ours(frames, cfg),
                "ours, no context": lambda: ours(frames, alone)}
        if with_patchwork:
            runs["patchwork++"] = lambda: patchwork(frames)
        for method, run in runs.items():
            ground, sec = run()
            rows.append(dict(flight=f"{scene} (seed {seed})", method=method,
                             ms_per_message=1e3 * sec, **scores(ref, ground)))
        if with_patchwork and grid:
            best = None
            for values in itertools.product(*grid.values()):
                settings = dict(zip(grid, values))
                ground, sec = patchwork(frames, **settings)
                row = dict(flight=f"{scene} (seed {seed})", method="patchwork++ best",
                           ms_per_message=1e3 * sec, settings=settings, **scores(ref, ground))
                if best is None or row["kappa"] > best["kappa"]:
                    best = row
            rows.append(best)
        print(f"  {scene} seed {seed}: done", file=sys.stderr, flush=True)
    cols = ["flight", "method", "kappa", "type_i_pct", "type_ii_pct",
            "building_wire_tower_as_ground_pct", "ms_per_message"]
    print(f"{len(flights)} simulated flights of {seconds:.0f} s (10 Hz, ~50 000 points a "
          f"message, {ALTITUDE:.0f} m above the terrain); Patchwork++ given the points "
          "relative to the vehicle in the level map frame.\n")
    print(table(rows, cols))
    tuned = [r for r in rows if r["method"] == "patchwork++ best"]
    if tuned:
        print("\npatchwork++ best settings per flight: " + "; ".join(
            f"{r['flight']}: {r['settings']}" for r in tuned))
    (args.out / "scan_ground.json").write_text(json.dumps(rows, indent=2, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
