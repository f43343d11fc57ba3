"""Simplification by K-means++ on normals (Li et al. 2020) against anchors, on real data.

Per file (first returns of a crop the size of the paper's 61 822 points, or a whole ISPRS
sample):

1. The paper's protocol (`method=normal_cluster`): elbow k, every cluster as a candidate
   simplified cloud with its reduction and TIN raster r (0.125 m-like cells: the mean
   point spacing), the cluster chosen (best r of the 3 largest, the paper's by-eye
   shortlist) and whether any cluster outside the shortlist would have scored higher.
   Time of the K-means: the paper's 100 restarts of K-means++ at the chosen k on every
   normal (its 22.4 s on 61 822 points), and the default elbow sweep.
2. At the same reduction as the chosen cluster, and at the paper's 81.833 % (keep 18 %):
   `normal_space`, uniform random, a 3-D voxel grid and a 2-D cell grid of the same
   size: r, and the 95th percentile of the 3-D distance from every point to the nearest
   kept point (coverage of walls, wires and towers, which the 2.5-D raster cannot see).
3. Speed of `simplify` with the default config on a 50 000-point cloud (ms per cloud).

Usage: .venv/bin/python benchmarks/bench_simplify.py [--quick | --smoke --out DIR]
Writes benchmarks/results/simplify.json (to --out DIR if given).
"""
from __future__ import annotations

import json
import platform
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lidar_obstacles.config import SimplifyConfig  # noqa: E402
from lidar_obstacles.core.kmeans import kmeans  # noqa: E402
from lidar_obstacles.core.simplify import (mean_spacing, normal_space_sample,  # noqa: E402
                                           simplify, tin_raster_correlation, voxel_sample)
from lidar_obstacles.io.las import read_las  # noqa: E402
from common import bench_args, per_mode, table  # noqa: E402 (benchmarks/ is on the path)

DATA = REPO.parent / "shared" / "data"
PAPER = dict(reduction=0.81833, r=0.890, restarts=100, seconds_100_runs=22.392, points=61822)


def load(rel: str, n: int):
    """xyz (n, 3) m and return numbers (None when not recorded) of the n points nearest (in
    XY) to the median point: a disc of the file's density."""
    cloud = read_las(DATA / rel)
    xyz, pts = cloud.xyz, cloud.points
    if len(xyz) > n:
        centre = np.median(xyz[:, :2], axis=0)
        pick = np.sort(np.argpartition(np.hypot(*(xyz[:, :2] - centre).T), n - 1)[:n])
        xyz, pts = xyz[pick], pts[pick]
    ret = pts["return_number"] if pts["return_number"].max() > 0 else None
    return xyz, ret


def p95_gap(kept: np.ndarray, pts: np.ndarray) -> float:
    """95th percentile of the 3-D distance from every point to the nearest kept point, m."""
    return float(np.percentile(cKDTree(kept).query(pts, k=1, workers=-1)[0], 95))


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def per_file(rel: str, n: int, cfg: SimplifyConfig, paper_restarts: int) -> tuple[dict, list]:
    xyz, ret = load(rel, n)
    res, seconds = timed(lambda: simplify(xyz, cfg=replace(cfg, method="normal_cluster"),
                                          return_number=ret,
                                          rng=np.random.default_rng(0)))
    clustered = res.labels >= 0
    pts, labels = xyz[clustered], res.labels[clustered]
    cell = mean_spacing(pts[:, :2])
    # r of every cluster, to check the shortlist of the 3 largest loses nothing
    r_all = [tin_raster_correlation(pts[labels == c], pts, cell=cell) for c in range(res.k)]
    best_any = int(np.nanargmax(r_all))
    normals_fit = None
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Number of distinct clusters")
        from lidar_obstacles.core.simplify import pca_normals

        normals_fit = pca_normals(pts, neighbours=cfg.neighbours)
        _, t_paper = timed(lambda: kmeans(normals_fit, res.k, restarts=paper_restarts,
                                          max_iter=cfg.max_iter, tol=cfg.tol, rng=0))
    chosen = res.candidates[res.chosen]
    row = dict(file=rel, points_in=len(xyz), clustered=len(pts), cell_m=round(cell, 4),
               k=res.k, chosen=res.chosen, chosen_points=chosen.points,
               chosen_reduction=chosen.reduction, chosen_r=res.r,
               best_any_cluster=best_any, best_any_r=float(r_all[best_any]),
               kmeans_paper_s=t_paper, paper_restarts=paper_restarts,
               kmeans_default_s=res.timings["kmeans"], normal_cluster_total_s=seconds,
               sse=[float(s) for s in res.sse],
               candidates=[dict(cluster=c.cluster, points=c.points, reduction=c.reduction,
                                r_shortlist=c.r, r=float(r_all[c.cluster]))
                           for c in res.candidates])
    rows = []
    for label, keep_share in (("same as chosen", chosen.points / len(pts)),
                              ("paper 18 %", 1.0 - PAPER["reduction"])):
        count = int(round(keep_share * len(pts)))
        rng = np.random.default_rng(1)
        flat = np.column_stack([pts[:, :2], np.zeros(len(pts))])
        picks = {"normal_space": normal_space_sample(pts, labels, count, rng),
                 "random": np.isin(np.arange(len(pts)), rng.choice(len(pts), count,
                                                                   replace=False)),
                 "voxel3d": voxel_sample(pts, count, rng),
                 "grid2d": voxel_sample(flat, count, rng)}
        out = dict(file=rel, at=label, kept=count, reduction=1.0 - count / len(pts))
        if label == "same as chosen":
            out["paper_cluster_r"] = res.r
            out["paper_cluster_p95_gap_m"] = p95_gap(pts[labels == res.chosen], pts)
        for name, mask in picks.items():
            out[f"{name}_r"] = tin_raster_correlation(pts[mask], pts, cell=cell)
            out[f"{name}_p95_gap_m"] = p95_gap(pts[mask], pts)
            out[f"{name}_min_cluster_share"] = float(min(
                mask[labels == c].mean() for c in range(res.k) if np.any(labels == c)))
        rows.append(out)
    return row, rows


def speed(cfgs: dict[str, SimplifyConfig], repeat: int, n: int) -> list[dict]:
    xyz, ret = load("ahn4/ahn_2496_9727.laz", n)  # 56 000: ~50 000 first returns
    out = []
    for name, cfg in cfgs.items():
        best: dict | None = None
        for i in range(repeat):
            res = simplify(xyz, cfg=cfg, return_number=ret,
                           rng=np.random.default_rng(i))
            if best is None or res.timings["total"] < best["total"]:
                best = dict(res.timings)
        assert best is not None
        out.append(dict(config=name, clustered=int((res.labels >= 0).sum()), k=res.k,
                        r=res.r, **{f"{k}_ms": 1000 * v for k, v in best.items()}))
    return out


def main() -> int:
    args = bench_args(__doc__, "fewer files, 10 restarts",
                      "3 000 AHN4 points, 1 restart, a 5 000-point cloud for the speed")
    quick = args.quick
    cfg = SimplifyConfig()
    files = per_mode(args, [("ahn4/ahn_2496_9727.laz", 70_000),
                            ("ahn-corridor/07CZ2_14.laz", 50_000),
                            ("ahn-corridor/12AN2_20.laz", 50_000),
                            ("isprs/samp11-utm.laz", 60_000), ("isprs/samp31-utm.laz", 60_000),
                            ("isprs/samp52-utm.laz", 60_000)],
                     [("ahn4/ahn_2496_9727.laz", 70_000), ("isprs/samp11-utm.laz", 60_000)],
                     [("ahn4/ahn_2496_9727.laz", 3_000)])
    protocol, compare = [], []
    for rel, n in files:
        print(rel, file=sys.stderr, flush=True)
        row, rows = per_file(rel, n, cfg, per_mode(args, PAPER["restarts"], 10, 1))
        protocol.append(row)
        compare += rows
    fast = replace(cfg, validate=True)
    spd = speed({"default": cfg, "default, validate=true": fast,
                 "restarts=10, sample_size=20000": replace(cfg, restarts=10,
                                                           sample_size=20000)},
                per_mode(args, 3, 1, 1), per_mode(args, 56_000, 56_000, 5_000))

    print(f"# Simplification by K-means++ on normals ({args.mode}, "
          f"{platform.node()})\n")
    print(f"Paper (desert, 61 822 first returns): k = 8, best cluster {PAPER['reduction']:.3%} "
          f"reduction, r = {PAPER['r']}, 100 K-means++ runs in {PAPER['seconds_100_runs']} s.\n")
    print("## Paper's protocol (normal_cluster)\n")
    print(table(protocol, ["file", "clustered", "cell_m", "k", "chosen", "chosen_points",
                           "chosen_reduction", "chosen_r", "best_any_cluster", "best_any_r",
                           "paper_restarts", "kmeans_paper_s", "kmeans_default_s",
                           "normal_cluster_total_s"]))
    print("\nCandidates (reduction, r) per file:\n")
    for row in protocol:
        cands = ", ".join(f"{c['cluster']}: {c['reduction']:.1%} r={c['r']:.3f}"
                          for c in row["candidates"])
        print(f"- {row['file']}: {cands}")
    print("\n## normal_space against anchors at the same reduction (TIN raster r; p95 3-D "
          "gap to the nearest kept point, m; smallest share kept of any normal cluster)\n")
    print(table(compare, ["file", "at", "reduction", "paper_cluster_r", "normal_space_r",
                          "random_r", "voxel3d_r", "grid2d_r"]))
    print()
    print(table(compare, ["file", "at", "paper_cluster_p95_gap_m", "normal_space_p95_gap_m",
                          "random_p95_gap_m", "voxel3d_p95_gap_m", "grid2d_p95_gap_m",
                          "normal_space_min_cluster_share", "random_min_cluster_share",
                          "voxel3d_min_cluster_share", "grid2d_min_cluster_share"]))
    print("\n## simplify() per cloud: AHN4 crop (~50 000 first returns), best of repeats, ms\n")
    cols = sorted({k for r in spd for k in r if k.endswith("_ms")})
    print(table(spd, ["config", "clustered", "k", "r"] + cols))
    result = dict(quick=quick, machine=platform.node(), paper=PAPER, protocol=protocol,
                  compare=compare, speed=spd)
    (args.out / "simplify.json").write_text(json.dumps(result, indent=2, default=float) + "\n")
    print(f"\nwrote {args.out / 'simplify.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
