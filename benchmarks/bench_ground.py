"""Ground filtering and obstacle classes on the real data, with `pysmrf` as anchor.

- ISPRS filter test, 15 samples, one parameter set: Type I/II, total error, kappa, and the
  share of 6 x 6 blocks (eligible ones) with kappa > 0.8 (the paper's test); speed in points
  per second against pysmrf measured in the same run.
- Power-line corridor and AHN4: wire/tower/building recall and precision, wire and tower
  points put in ground, ground kappa.

    python benchmarks/bench_ground.py [--quick]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from lidar_obstacles.config import ObstacleDetectorConfig
from lidar_obstacles.core.metrics import evaluate_classes
from lidar_obstacles.core.pipeline import ObstacleDetector
from lidar_obstacles.evaluate import ISPRS_SAMPLES
from lidar_obstacles.io.las import read_las

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"


def run(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    las = read_las(path)
    det = ObstacleDetector(ObstacleDetectorConfig())
    t0 = time.perf_counter()
    res = det.process(las.xyz, stamp=0.0)
    return las.xyz, las.points["classification"], res.classes, time.perf_counter() - t0


def pysmrf_anchor(paths: list[Path]) -> dict | None:
    """pysmrf (PyPI) with its defaults: points per second and mean total error / kappa."""
    try:
        import pysmrf
    except ImportError:
        return None
    from lidar_obstacles.core.metrics import ground_object_errors

    n = t = 0.0
    errs = []
    for p in paths:
        las = read_las(p)
        xyz = las.xyz
        t0 = time.perf_counter()
        res = pysmrf.classify(xyz[:, 0], xyz[:, 1], xyz[:, 2])
        t += time.perf_counter() - t0
        n += len(xyz)
        e = ground_object_errors(las.points["classification"] == 2, np.asarray(res.is_ground))
        errs.append((e["total_error"], e["kappa"]))
    return {"points_per_second": n / t, "mean_total_error": float(np.mean([e[0] for e in errs])),
            "mean_kappa": float(np.mean([e[1] for e in errs]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    samples = ISPRS_SAMPLES[:4] if args.quick else ISPRS_SAMPLES
    rows, n_pts, secs, blocks = [], 0, 0.0, []
    for s in samples:
        xyz, ref, pred, dt = run(DATA / "isprs" / f"samp{s}-utm.laz")
        m = evaluate_classes(ref, pred, xy=xyz[:, :2])
        go = m["ground_object"]
        rows.append((s, go["type_i"], go["type_ii"], go["total_error"], go["kappa"]))
        blocks.append((m["blocks"]["n_eligible"], m["blocks"]["share_kappa_gt_0_8"]))
        n_pts += len(xyz)
        secs += dt
    mean = np.mean([r[1:] for r in rows], axis=0)
    elig = sum(b[0] for b in blocks)
    share08 = sum(b[0] * (b[1] or 0) for b in blocks) / max(elig, 1)
    out = {"isprs": {"samples": rows, "mean_type_i": mean[0], "mean_type_ii": mean[1],
                     "mean_total_error": mean[2], "mean_kappa": mean[3],
                     "blocks_eligible": elig, "blocks_share_kappa_gt_0_8": share08,
                     "points_per_second": n_pts / secs}}
    smrf = pysmrf_anchor([DATA / "isprs" / f"samp{s}-utm.laz" for s in samples])
    out["isprs"]["pysmrf"] = smrf
    anchor = smrf["points_per_second"] if smrf else None
    print("| ISPRS sample | Type I % | Type II % | total % | kappa |\n|---|---|---|---|---|")
    for s, a, b, c, k in rows:
        print(f"| samp{s} | {100 * a:.2f} | {100 * b:.2f} | {100 * c:.2f} | {k:.3f} |")
    print(f"| **mean** | {100 * mean[0]:.2f} | {100 * mean[1]:.2f} | **{100 * mean[2]:.2f}** "
          f"| **{mean[3]:.3f}** |")
    print(f"\n6x6 blocks with kappa > 0.8: {100 * share08:.1f} % of {elig} eligible "
          f"(paper: 88.6 %). Speed {n_pts / secs:,.0f} points/s"
          + (f"; pysmrf {anchor:,.0f} points/s ({n_pts / secs / anchor:.1f} x), total error "
             f"{100 * smrf['mean_total_error']:.2f} %, kappa {smrf['mean_kappa']:.3f}" if smrf
             else " (pysmrf not installed: `make bench` installs it)"))
    files = ["ahn-corridor/07CZ2_14.laz", "ahn-corridor/12AN2_20.laz", "ahn4/ahn_2496_9727.laz"]
    print("\n| file | ground kappa | wire recall | wire precision | tower recall | tower "
          "precision | building recall | building precision | wire+tower in ground % |")
    print("|---|---|---|---|---|---|---|---|---|")
    for f in files[:1] if args.quick else files:
        xyz, ref, pred, dt = run(DATA / f)
        m = evaluate_classes(ref, pred, xy=xyz[:, :2])
        pc = m["per_class"]

        def fmt(v):
            return "-" if v is None else f"{v:.3f}"

        unsafe = m["safety"]["obstacle_as_ground"]
        print(f"| {f} | {fmt(m['ground_object']['kappa'])} | "
              f"{fmt(pc['wire']['producers_accuracy'])} | {fmt(pc['wire']['users_accuracy'])} | "
              f"{fmt(pc['tower']['producers_accuracy'])} | {fmt(pc['tower']['users_accuracy'])} | "
              f"{fmt(pc['building']['producers_accuracy'])} | {fmt(pc['building']['users_accuracy'])} | "
              f"{'-' if unsafe is None else f'{100 * unsafe:.2f}'} |")
        out[f] = {"ground_kappa": m["ground_object"]["kappa"], "per_class": pc,
                  "safety": m["safety"], "seconds": dt}
    (REPO / "benchmarks" / "results").mkdir(parents=True, exist_ok=True)
    (REPO / "benchmarks" / "results" / "ground.json").write_text(json.dumps(out, indent=2,
                                                                           default=float))


if __name__ == "__main__":
    main()
