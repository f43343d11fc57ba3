"""Speed of the synthetic flight simulator, per scene, against an anchor.

Usage: .venv/bin/python benchmarks/bench_simulate.py [--quick | --smoke --out DIR]

Two measures per scene at the default 50 000 points per frame:
- `flight`: frames/s of `simulate_flight` over the first N frames (what `demo` runs);
- `along path`: ms per frame for frames taken every 30 s along a 30-minute flight
  (representative of the whole loop: villages, woods, power lines).
Anchor, measured in the same run: building a scipy cKDTree on 50 000 random points
(the first step of most downstream stages). The target is a frame in < 50 ms on one core,
i.e. a 30-minute flight (18 000 frames) in a few minutes.
Writes benchmarks/results/simulate.json (to --out DIR if given).
"""
from __future__ import annotations

import json
import time

import numpy as np
from scipy.spatial import cKDTree

from lidar_obstacles.core import simulate as sim
from common import bench_args, per_mode  # (benchmarks/ is on the path)


def _anchor(repeats: int) -> float:
    pts = np.random.default_rng(0).uniform(0, 100, (50_000, 3))
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        cKDTree(pts)
        best = min(best, time.perf_counter() - t)
    return best


def main() -> None:
    args = bench_args(__doc__, "30 frames, a frame every 2 min along the path",
                      "3 frames, two along the path")
    n_frames = per_mode(args, 150, 30, 3)
    step = per_mode(args, 30.0, 120.0, 900.0)
    anchor = _anchor(per_mode(args, 5, 5, 1))
    rows = []
    for scene in sim.SCENES:
        t = time.perf_counter()
        sim.scene_info(scene)
        build = time.perf_counter() - t
        settings = sim.SimSettings(scene=scene, duration=n_frames / 10.0)
        t = time.perf_counter()
        points = 0
        for frame in sim.simulate_flight(settings):
            points += len(frame.points)
        flight = time.perf_counter() - t
        # Frames spread over a 30-minute flight (private hooks: no need to fly there).
        sc = sim._scene(scene, 0)
        times = np.arange(0.0, 1800.0, step)
        t = time.perf_counter()
        along_pts = 0
        per_pulse = 1.15
        for k, stamp in enumerate(times):
            pos, _, rot, vel = sim._pose(sc, settings, float(stamp), np.zeros(2))
            pts, fired = sim._scan(sc, settings, np.random.default_rng([0, 1, k]), pos, rot,
                                   vel, int(50_000 / per_pulse))
            along_pts += len(pts["xyz"])
            per_pulse = max(len(pts["xyz"]) / fired, 0.5)
        along = (time.perf_counter() - t) / len(times)
        rows.append({"scene": scene, "build_s": build, "frames": n_frames,
                     "points_per_frame": points / n_frames,
                     "frames_per_s": n_frames / flight, "ms_per_frame": 1e3 * flight / n_frames,
                     "along_path_ms_per_frame": 1e3 * along,
                     "along_path_points_per_frame": along_pts / len(times),
                     "ratio_to_anchor": (flight / n_frames) / anchor,
                     "minutes_for_30_min_flight": 18_000 * max(flight / n_frames, along) / 60})
    print(f"anchor: cKDTree(50k points) = {anchor * 1e3:.2f} ms\n")
    print("| scene | build s | pts/frame | frames/s | ms/frame | along path ms/frame "
          "| ms/frame / anchor | 30-min flight, min |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['build_s']:.2f} | {r['points_per_frame']:.0f} | "
              f"{r['frames_per_s']:.1f} | {r['ms_per_frame']:.1f} | "
              f"{r['along_path_ms_per_frame']:.1f} | {r['ratio_to_anchor']:.1f} | "
              f"{r['minutes_for_30_min_flight']:.1f} |")
    (args.out / "simulate.json").write_text(json.dumps({"anchor_s": anchor, "rows": rows},
                                                       indent=2))


if __name__ == "__main__":
    main()
