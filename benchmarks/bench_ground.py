"""Ground filtering and obstacle classes on the real data, against anchors from PyPI.

- ISPRS filter test, 15 samples, one parameter set: Type I/II, total error, kappa, and the
  share of 6 x 6 blocks (eligible ones: >= 5 % of each class) with kappa > 0.8 (the
  paper's test). Speed of the ground filter alone (`classify_ground`, what the target is
  about) and of the whole detector, in points per second. The other two filters
  (`ground.method` `tin` and `ransac`) on the same samples, measured as the anchors are.
- Anchors in the same run on the same samples: `pysmrf` (SMRF in Python with PDAL's
  parameters; PDAL's C++ SMRF runs ~5.5 x faster than it) and `cloth-simulation-filter`
  (CSF, C++), accuracy and speed; `open3d-cpu`'s RANSAC `segment_plane` against this
  package's `ransac_plane` on the same 50 m tiles (time and inlier share).
- Power-line corridor and AHN4: wire/tower/building recall and precision, wire and tower
  points put in ground, ground kappa, the corridor's cranes (class 26) found as unclassified
  structures (1).

    python benchmarks/bench_ground.py [--quick | --smoke --out DIR]

Writes benchmarks/results/ground.json (to --out DIR if given). Anchors not installed are
skipped.
"""
from __future__ import annotations

import functools
import json
import time
from pathlib import Path

import numpy as np

from lidar_obstacles.config import ObstacleDetectorConfig, replace
from lidar_obstacles.core.classes import UNCLASSIFIED
from lidar_obstacles.core.ground import classify_ground
from lidar_obstacles.core.metrics import block_kappa, evaluate_classes, ground_object_errors
from lidar_obstacles.core.pipeline import ObstacleDetector
from lidar_obstacles.core.ransac import ransac_plane
from lidar_obstacles.evaluate import ISPRS_SAMPLES
from lidar_obstacles.io.las import read_las
from common import bench_args, installed, per_mode, quiet_stdout  # (benchmarks/ is on the path)

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
CFG = ObstacleDetectorConfig()
CRANE = 26  # the corridor files' inserted cranes (ASPRS 26, "reserved": the author's code)


def best_of(fn, repeats: int) -> tuple[object, float]:
    """fn()'s result and its fastest wall time (s) over `repeats` runs."""
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def best_of_paired(fn, anchor_fn, repeats: int) -> tuple[float, object, float]:
    """fn()'s fastest wall time and anchor_fn()'s result and fastest time, run in turns:
    the machine's speed drifts over minutes (on this 2-vCPU machine the same code measured
    19.1 x pysmrf when pysmrf ran after all the samples, 21.0 x sample by sample), so the
    ratio compares runs made at the same time."""
    best, best_anchor, out = np.inf, np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
        t0 = time.perf_counter()
        out = anchor_fn()
        best_anchor = min(best_anchor, time.perf_counter() - t0)
    return best, out, best_anchor


def ground_only(xyz: np.ndarray) -> np.ndarray:
    return classify_ground(xyz, tiling=CFG.tiling, ground=CFG.ground, tin=CFG.tin,
                           ransac=CFG.ransac, rng=np.random.default_rng(0)).ground


def method_ground(method: str):
    """The ground mask of `ground.method` `method` (the other two filters, measured as the
    anchors are)."""
    cfg = replace(CFG, {"ground.method": method})

    def ground(xyz: np.ndarray) -> np.ndarray:
        return classify_ground(xyz, tiling=cfg.tiling, ground=cfg.ground, tin=cfg.tin,
                               ransac=cfg.ransac, rng=np.random.default_rng(0)).ground
    return ground


def pysmrf_ground(xyz: np.ndarray) -> np.ndarray:
    """pysmrf with the SMRF paper's (and PDAL's default) parameters: 18 m window, slope
    0.15, threshold 0.5 m, scalar 1.25 (its own default window of 5 m scores ~12 %)."""
    import pysmrf

    return np.asarray(pysmrf.classify(xyz[:, 0], xyz[:, 1], xyz[:, 2], cellsize=1.0,
                                      windows=18, slope_threshold=0.15,
                                      elevation_threshold=0.5,
                                      elevation_scaler=1.25).is_ground, bool)


def csf_ground(xyz: np.ndarray) -> np.ndarray:
    """CSF with slope smoothing, 0.5 m cloth, rigidness 2, 0.5 m threshold. On six ISPRS
    samples (11, 12, 21, 22, 31, 53) rigidness 1-3 with smoothing on/off scored 15.7-21.5 %
    total error at 0.5 m cloth, 16 % at 1 m; smoothing on was best (CSF's paper tunes its
    parameters per sample)."""
    import CSF

    csf = CSF.CSF()
    csf.params.bSloopSmooth = True
    csf.params.cloth_resolution = 0.5
    csf.params.rigidness = 2
    csf.params.class_threshold = 0.5
    csf.setPointCloud(xyz - xyz.min(axis=0))
    ground, off = CSF.VecInt(), CSF.VecInt()
    with quiet_stdout():
        csf.do_filtering(ground, off, exportCloth=False)
    mask = np.zeros(len(xyz), bool)
    mask[np.asarray(ground, np.int64)] = True
    return mask


def anchor(fn, clouds: list[tuple[np.ndarray, np.ndarray]], repeats: int) -> dict:
    """Points per second (best of `repeats` per cloud, as for this package) and mean errors
    of an anchor ground filter."""
    n = t = 0.0
    errs, blocks = [], []
    for xyz, ref in clouds:
        ground, dt = best_of(lambda: fn(xyz), repeats)
        t += dt
        n += len(xyz)
        e = ground_object_errors(ref == 2, ground)
        errs.append((e["total_error"], e["kappa"]))
        blocks.append(block_share(xyz, ref, ground))
    return {"points_per_second": n / t, "mean_total_error": float(np.mean([e[0] for e in errs])),
            "mean_kappa": float(np.mean([e[1] for e in errs])),
            "blocks_share_kappa_gt_0_8": pooled_share(blocks)}


# The grid's corner, in cells before the points' lowest x and y (HybridSettings.anchor)
GRID_PLACEMENTS = [(0.0, 0.0), (0.25, 0.0), (0.0, 0.5), (0.5, 0.5), (0.75, 0.25), (0.4, 0.8)]


def grid_placements(clouds: list[tuple[np.ndarray, np.ndarray]]) -> dict:
    """The hybrid filter's mean total error, kappa and block share with its 1 m raster
    placed differently over the same points: how much of a figure the grid's placement
    decides. classify_ground builds its HybridSettings from the four `ground.*`
    parameters; the class is swapped for one that places the grid."""
    from lidar_obstacles.core import ground as ground_module

    default = ground_module.HybridSettings
    rows = []
    try:
        for at in GRID_PLACEMENTS:
            ground_module.HybridSettings = functools.partial(default, anchor=at)
            run = anchor(ground_only, clouds, repeats=1)
            rows.append({"anchor_cells": at, **{k: run[k] for k in (
                "mean_total_error", "mean_kappa", "blocks_share_kappa_gt_0_8")}})
    finally:
        ground_module.HybridSettings = default
    return {"placements": rows, **{f"{k}_{f.__name__}": float(f([r[k] for r in rows]))
                                   for k in ("mean_total_error", "mean_kappa",
                                             "blocks_share_kappa_gt_0_8")
                                   for f in (np.min, np.mean, np.max)}}


def block_share(xyz: np.ndarray, ref: np.ndarray, ground: np.ndarray) -> tuple[int, float]:
    """(eligible 6 x 6 blocks, share of them with ground/object kappa > 0.8) of one sample."""
    b = block_kappa(xyz[:, :2], ref == 2, ground)
    return b["n_eligible"], b["share_kappa_gt_0_8"] or 0.0


def pooled_share(blocks: list[tuple[int, float]]) -> float:
    """The share of all samples' eligible blocks with kappa > 0.8."""
    return sum(n * share for n, share in blocks) / max(sum(n for n, _ in blocks), 1)


def ransac_anchor(clouds: list[tuple[np.ndarray, np.ndarray]], tile: float = 50.0) -> dict:
    """This package's RANSAC plane against open3d's segment_plane on the same tiles: same
    threshold (0.3 m), trials capped alike (1000), so the comparison is time per plane and
    the share of points on the plane found."""
    import open3d as o3d

    tiles = []
    for xyz, _ in clouds:
        ij = np.floor((xyz[:, :2] - xyz[:, :2].min(axis=0)) / tile).astype(np.int64)
        key = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
        order = np.argsort(key, kind="stable")
        for part in np.split(order, np.flatnonzero(np.diff(key[order])) + 1):
            if len(part) >= 100:
                tiles.append(xyz[part] - xyz[part].mean(axis=0))
    ours_t = o3d_t = 0.0
    ours_share, o3d_share = [], []
    rng = np.random.default_rng(0)
    for pts in tiles:
        t0 = time.perf_counter()
        res = ransac_plane(pts, distance_threshold=0.3, max_trials=1000, rng=rng)
        ours_t += time.perf_counter() - t0
        ours_share.append(res.inliers.mean())
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        t0 = time.perf_counter()
        _, inl = pcd.segment_plane(distance_threshold=0.3, ransac_n=3, num_iterations=1000)
        o3d_t += time.perf_counter() - t0
        o3d_share.append(len(inl) / len(pts))
    return {"tiles": len(tiles), "ours_seconds": ours_t, "open3d_seconds": o3d_t,
            "ours_mean_inlier_share": float(np.mean(ours_share)),
            "open3d_mean_inlier_share": float(np.mean(o3d_share))}


def near_towers(xyz: np.ndarray, ref: np.ndarray, n: int) -> np.ndarray:
    """(N,) bool: the n points nearest (in XY) to the towers' (class 15) centre."""
    centre = xyz[ref == 15, :2].mean(axis=0) if np.any(ref == 15) else np.median(xyz[:, :2], 0)
    keep = np.zeros(len(xyz), bool)
    keep[np.argpartition(np.hypot(*(xyz[:, :2] - centre).T), n - 1)[:n]] = True
    return keep


def main() -> None:
    args = bench_args(__doc__, "4 ISPRS samples, one corridor tile",
                      "the smallest ISPRS sample, one repeat, 10 000 corridor points round "
                      "a tower")
    samples = per_mode(args, ISPRS_SAMPLES, ISPRS_SAMPLES[:4], ("24",))
    repeats = per_mode(args, 5, 5, 1)
    rows, blocks, clouds = [], [], []
    n_pts, ground_s, total_s = 0, 0.0, 0.0
    if installed("pysmrf", "pysmrf"):
        smrf_s, smrf_errs, smrf_blocks = 0.0, [], []
    else:
        smrf_s, smrf_errs, smrf_blocks = None, None, []
    with_csf = installed("CSF", "cloth-simulation-filter")
    with_open3d = installed("open3d", "open3d-cpu")
    for s in samples:
        las = read_las(DATA / "isprs" / f"samp{s}-utm.laz")
        xyz, ref = las.xyz, np.asarray(las.points["classification"])
        clouds.append((xyz, ref))
        if smrf_errs is not None:
            dt_ground, smrf_ground, dt_smrf = best_of_paired(
                lambda: ground_only(xyz), lambda: pysmrf_ground(xyz), repeats)
            smrf_s += dt_smrf
            e = ground_object_errors(ref == 2, smrf_ground)
            smrf_errs.append((e["total_error"], e["kappa"]))
            smrf_blocks.append(block_share(xyz, ref, smrf_ground))
        else:
            _, dt_ground = best_of(lambda: ground_only(xyz), repeats)
        res, dt_total = best_of(lambda: ObstacleDetector(CFG).process(xyz), 1)
        m = evaluate_classes(ref, res.classes, xy=xyz[:, :2])
        go = m["ground_object"]
        rows.append((s, go["type_i"], go["type_ii"], go["total_error"], go["kappa"]))
        blocks.append((m["blocks"]["n_eligible"], m["blocks"]["share_kappa_gt_0_8"]))
        n_pts += len(xyz)
        ground_s += dt_ground
        total_s += dt_total
    mean = np.mean([r[1:] for r in rows], axis=0)
    elig = sum(b[0] for b in blocks)
    share08 = pooled_share([(n, share or 0.0) for n, share in blocks])
    ours_pps = n_pts / ground_s
    out = {"isprs": {"samples": rows, "mean_type_i": mean[0], "mean_type_ii": mean[1],
                     "mean_total_error": mean[2], "mean_kappa": mean[3],
                     "blocks_eligible": elig, "blocks_share_kappa_gt_0_8": share08,
                     "ground_points_per_second": ours_pps,
                     "detector_points_per_second": n_pts / total_s}}
    smrf = None if smrf_errs is None else {
        "points_per_second": n_pts / smrf_s,
        "mean_total_error": float(np.mean([e[0] for e in smrf_errs])),
        "mean_kappa": float(np.mean([e[1] for e in smrf_errs])),
        "blocks_share_kappa_gt_0_8": pooled_share(smrf_blocks)}
    # CSF is ~100 x slower: one run is plenty
    csf = anchor(csf_ground, clouds, repeats=1) if with_csf else None
    rans = ransac_anchor(clouds[:4] if args.quick else clouds) if with_open3d else None
    methods = {m: anchor(method_ground(m), clouds, repeats=1) for m in ("tin", "ransac")}
    placed = grid_placements(clouds)
    out["isprs"].update(pysmrf=smrf, csf=csf, ransac_vs_open3d=rans, methods=methods,
                        grid_placements=placed)

    print("| ISPRS sample | Type I % | Type II % | total % | kappa |\n|---|---|---|---|---|")
    for s, a, b, c, k in rows:
        print(f"| samp{s} | {100 * a:.2f} | {100 * b:.2f} | {100 * c:.2f} | {k:.3f} |")
    print(f"| **mean** | {100 * mean[0]:.2f} | {100 * mean[1]:.2f} | **{100 * mean[2]:.2f}** "
          f"| **{mean[3]:.3f}** |")
    print(f"\n6x6 blocks with kappa > 0.8: {100 * share08:.1f} % of {elig} eligible "
          "(paper: 88.6 %; target 95 %).\n")
    print(f"The ground filter with its 1 m raster placed {len(GRID_PLACEMENTS)} ways over the "
          "same points (its corner 0-0.8 of a cell before them): total error "
          f"{100 * placed['mean_total_error_min']:.2f}-{100 * placed['mean_total_error_max']:.2f} %"
          f" (mean {100 * placed['mean_total_error_mean']:.2f} %), kappa "
          f"{placed['mean_kappa_min']:.4f}-{placed['mean_kappa_max']:.4f} (mean "
          f"{placed['mean_kappa_mean']:.4f}), blocks "
          f"{100 * placed['blocks_share_kappa_gt_0_8_min']:.1f}-"
          f"{100 * placed['blocks_share_kappa_gt_0_8_max']:.1f} %.\n")
    print("| ground filter (same run) | total error % | kappa | blocks kappa > 0.8 % "
          "| points/s | x pysmrf |")
    print("|---|---|---|---|---|---|")
    base = smrf["points_per_second"] if smrf else None

    def ratio(pps):
        return f"{pps / base:.1f}" if base else "-"

    print(f"| this package (hybrid) | {100 * mean[2]:.2f} | {mean[3]:.3f} | "
          f"{100 * share08:.1f} | {ours_pps:,.0f} | **{ratio(ours_pps)}** |")
    for name, a in (("this package (tin)", methods["tin"]),
                    ("this package (ransac)", methods["ransac"]), ("pysmrf", smrf), ("CSF", csf)):
        if a:
            print(f"| {name} | {100 * a['mean_total_error']:.2f} | {a['mean_kappa']:.3f} | "
                  f"{100 * a['blocks_share_kappa_gt_0_8']:.1f} | "
                  f"{a['points_per_second']:,.0f} | {ratio(a['points_per_second'])} |")
    print("| PDAL 2.8 SMRF (data README) | 5.14 | 0.833 | | | ~5.5 |")
    print(f"\nWhole detector (ground, obstacles, clearance): {n_pts / total_s:,.0f} points/s.")
    if rans:
        print(f"\nRANSAC plane on {rans['tiles']} ISPRS tiles of 50 m (0.3 m, 1000 trials): "
              f"this package {rans['ours_seconds']:.2f} s, open3d {rans['open3d_seconds']:.2f} s "
              f"({rans['open3d_seconds'] / rans['ours_seconds']:.1f} x ours); mean inlier share "
              f"{rans['ours_mean_inlier_share']:.3f} vs {rans['open3d_mean_inlier_share']:.3f}.")

    files = ["ahn-corridor/07CZ2_14.laz", "ahn-corridor/12AN2_20.laz", "ahn4/ahn_2496_9727.laz"]
    print("\n| file | ground kappa | wire recall | wire precision | tower recall | tower "
          "precision | building recall | building precision | wire+tower in ground % | 6x6 blocks "
          "kappa > 0.8 | cranes (26) unclassified % |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for f in per_mode(args, files, files[:1], files[:1]):
        las = read_las(DATA / f)
        xyz, ref = las.xyz, np.asarray(las.points["classification"])
        if args.smoke:
            keep = near_towers(xyz, ref, 10_000)
            xyz, ref = xyz[keep], ref[keep]
        t0 = time.perf_counter()
        res = ObstacleDetector(CFG).process(xyz)
        dt = time.perf_counter() - t0
        m = evaluate_classes(ref, res.classes, xy=xyz[:, :2])
        pc = m["per_class"]

        def fmt(v):
            return "-" if v is None else f"{v:.3f}"

        unsafe = m["safety"]["obstacle_as_ground"]
        blk = m["blocks"]
        crane = ref == CRANE  # the corridor's inserted cranes: structures, not vegetation
        cranes = float((res.classes[crane] == UNCLASSIFIED).mean()) if crane.any() else None
        print(f"| {f} | {fmt(m['ground_object']['kappa'])} | "
              f"{fmt(pc['wire']['producers_accuracy'])} | {fmt(pc['wire']['users_accuracy'])} | "
              f"{fmt(pc['tower']['producers_accuracy'])} | {fmt(pc['tower']['users_accuracy'])} | "
              f"{fmt(pc['building']['producers_accuracy'])} | "
              f"{fmt(pc['building']['users_accuracy'])} | "
              f"{'-' if unsafe is None else f'{100 * unsafe:.2f}'} | "
              f"{100 * (blk['share_kappa_gt_0_8'] or 0):.0f} % of {blk['n_eligible']} | "
              f"{'-' if cranes is None else f'{100 * cranes:.1f}'} |")
        out[f] = {"ground_kappa": m["ground_object"]["kappa"], "per_class": pc,
                  "cranes_unclassified": cranes,
                  "blocks_eligible": blk["n_eligible"],
                  "blocks_share_kappa_gt_0_8": blk["share_kappa_gt_0_8"],
                  "safety": m["safety"], "seconds": dt}
    print("\nTargets: ISPRS total error <= 4.0 %, kappa >= 0.88, ground filter >= 20 x pysmrf; "
          "corridor wire recall >= 0.98 / precision >= 0.90, tower recall >= 0.95, 14/15 in "
          "ground <= 0.5 %, ground kappa >= 0.90; AHN4 building recall >= 0.90.")
    (args.out / "ground.json").write_text(json.dumps(out, indent=2, default=float))


if __name__ == "__main__":
    main()
