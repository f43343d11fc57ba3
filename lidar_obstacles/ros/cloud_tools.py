"""`lidar-obstacles simplify` and `features`: one method on a LAS/LAZ file or on every
cloud of a bag.

- A LAS/LAZ input gives a LAS/LAZ output (`.laz` compressed) with the kept points and every
  dimension of the input, its scales, offsets and CRS.
- A bag input gives a bag with the kept points of each cloud on `/points_simplified`
  (what the `cloud_simplifier` node publishes) or `/points_features`, stamped like the
  input, all fields kept; the other topics are copied.

Both write atomically: a failure leaves no half-written output.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from lidar_obstacles.config import (CloudSimplifierConfig, FeaturesConfig, ObstacleDetectorConfig,
                                    load_params_file)
from lidar_obstacles.core.ground import far_points
from lidar_obstacles.errors import (BagError, CloudFormatError, LasError, count_reason,
                                    malformed_cloud)
from lidar_obstacles.io.atomic import LAS, check_replaceable
from lidar_obstacles.io.bags import CRS_TOPIC, POINTCLOUD2, BagReader, BagWriter
from lidar_obstacles.ros import messages
from lidar_obstacles.ros.offline import _progress, _serialize, cdr_of_record
from lidar_obstacles.ros.stages import SimplifierStage, prepare

LAS_SUFFIXES = (".las", ".laz")
# `features` on a survey: square tiles of this edge (m), each with this margin (m) of
# neighbours around it, so memory stays bounded and a progress bar can move. The margin
# holds a point's k = 14..32 nearest neighbours at ISPRS's 2-3.5 m spacing.
FEATURE_TILE = 100.0
FEATURE_MARGIN = 10.0


def _is_las(path: Path) -> bool:
    return path.suffix.lower() in LAS_SUFFIXES


def _check_paths(src: Path, out: Path) -> None:
    """Bad paths, said before any work: a missing input (before whether the output suits
    it), an output of the other kind than the input, a LAS/LAZ output over a file of
    another kind."""
    if not src.exists():
        raise (LasError if _is_las(src) else BagError)(f"input not found: {src}")
    if _is_las(src) and not _is_las(out):
        raise LasError(f"a LAS/LAZ input needs a .las or .laz output, got {out}")
    if not _is_las(src) and _is_las(out):
        raise BagError(f"a bag input needs a bag output (a folder name), got {out}")
    if _is_las(out):
        check_replaceable(out, LAS)


def simplify(src: Path, out: Path, *, params_file: Path | None = None,
             topic: str | None = None, storage: str = "mcap",
             skip_malformed: bool = False) -> dict:
    """K-means++ simplification on normals (`cloud_simplifier`'s parameters, from
    `params_file` when given) of a LAS/LAZ file or of every cloud of a bag (a malformed
    cloud stops it unless `skip_malformed`: see `_bag_clouds`)."""
    from lidar_obstacles.core.simplify import SIMPLIFY_STEPS
    from lidar_obstacles.core.simplify import simplify as simplify_points
    from lidar_obstacles.io.las import read_las, write_las_subset

    cfg = (CloudSimplifierConfig() if params_file is None
           else load_params_file(params_file, CloudSimplifierConfig, "cloud_simplifier"))
    _check_paths(src, out)
    t0 = time.perf_counter()
    if _is_las(src):
        las = read_las(src, allow_empty=True)  # (0 points in, 0 out: `features` makes such)
        n = len(las.points)
        names = las.points.dtype.names or ()
        # Offline, the TIN raster correlation of the result with the input is worth its
        # second or so: it is the paper's measure of what the simplification kept.
        bar = _progress(None, len(SIMPLIFY_STEPS), "simplify", unit="step")
        started: list[str] = []

        def progress(name: str) -> None:  # the bar: steps done, and the one under way
            bar.set_postfix_str(name, refresh=not started)
            if started:
                bar.update(1)
            started.append(name)

        try:
            result = simplify_points(
                las.xyz, cfg=dataclasses.replace(cfg.simplify, validate=True),
                return_number=las.points["return_number"] if "return_number" in names else None,
                rng=np.random.default_rng(cfg.simplify.seed), progress=progress)
            bar.update(len(SIMPLIFY_STEPS) - bar.n)
        finally:
            bar.close()
        kept = write_las_subset(src, result.keep, out)
        return {"output": str(out), "points_in": n, "points_out": kept,
                "reduction": 1.0 - kept / n if n else 0.0, "method": cfg.simplify.method,
                "k": result.k, "r": result.r if np.isfinite(result.r) else None,
                "note": result.reason or None,  # why nothing was simplified, if so
                "seconds": time.perf_counter() - t0}
    stage = SimplifierStage(cfg)

    def keep_of(msg) -> tuple[object, int, int]:
        outputs, stats = stage.process(msg)
        return outputs[0][1], stats["points_in"], stats["points_out"]

    summary = _bag_clouds(src, out, topic=topic, storage=storage,
                          out_topic="/points_simplified", keep_of=keep_of, desc="simplify",
                          skip_malformed=skip_malformed)
    n_in = summary["points_in"]
    summary["reduction"] = 1.0 - summary["points_out"] / n_in if n_in else 0.0
    return {**summary, "method": cfg.simplify.method, "seconds": time.perf_counter() - t0}


def features(src: Path, out: Path, *, params_file: Path | None = None,
             topic: str | None = None, storage: str = "mcap",
             skip_malformed: bool = False) -> dict:
    """Gaussian-map feature points (the `features.*` parameters of `obstacle_detector`,
    from `params_file` when given) of a LAS/LAZ file or of every cloud of a bag (a
    malformed cloud stops it unless `skip_malformed`: see `_bag_clouds`)."""
    from lidar_obstacles.io.las import read_las, write_las_subset

    cfg = (ObstacleDetectorConfig() if params_file is None
           else load_params_file(params_file, ObstacleDetectorConfig, "obstacle_detector")).features
    _check_paths(src, out)
    rng = np.random.default_rng(cfg.seed)
    t0 = time.perf_counter()
    if _is_las(src):
        # 0 points in, 0 out: a file with no feature point, which `features` itself writes
        las = read_las(src, allow_empty=True)
        n = len(las.points)
        feature = tiled_features(las.xyz, cfg=cfg, rng=rng)
        kept = write_las_subset(src, feature, out)
        return {"output": str(out), "points_in": n, "points_out": kept,
                "share": kept / n if n else 0.0, "seconds": time.perf_counter() - t0}

    def keep_of(msg) -> tuple[object, int, int]:
        from lidar_obstacles.core.arrays import all_columns
        from lidar_obstacles.core.features import gaussian_map_features
        from lidar_obstacles.io.pointcloud2 import select_points

        prep = prepare(msg, keep_non_finite=False, max_points=2**31 - 1, pose=None,
                       transform=False)
        use = np.flatnonzero(all_columns(np.isfinite(prep.xyz)))
        use = use[~far_points(prep.xyz[use])]  # stray points are no object's feature
        mask = np.zeros(len(prep.points), bool)
        mask[use] = gaussian_map_features(prep.xyz[use], cfg=cfg, rng=rng).feature
        hdr = messages.header(prep.stamp_ns, prep.frame_id)
        return (messages.cloud(select_points(prep.points, mask), hdr), len(prep.points),
                int(mask.sum()))

    summary = _bag_clouds(src, out, topic=topic, storage=storage,
                          out_topic="/points_features", keep_of=keep_of, desc="features",
                          skip_malformed=skip_malformed)
    summary["share"] = summary["points_out"] / max(summary["points_in"], 1)
    return {**summary, "seconds": time.perf_counter() - t0}


def tiled_features(xyz: np.ndarray, *, cfg: FeaturesConfig,
                   rng: np.random.Generator) -> np.ndarray:
    """(N,) bool feature points of a whole survey xyz (N, 3) m, found tile by tile
    (FEATURE_TILE m squares, each with FEATURE_MARGIN m of neighbours around it), with a
    progress bar. A point's neighbours beyond the margin are missed, which only matters
    where the scan is sparser than the margin holds."""
    from lidar_obstacles.core.features import gaussian_map_features

    feature = np.zeros(len(xyz), bool)
    near_cloud = np.flatnonzero(~far_points(xyz))  # a stray kilometres off: no tile of its own
    xyz = xyz[near_cloud]
    if len(xyz) == 0:  # (an empty file: no tile, and no corner to start them from)
        return feature
    lo = xyz[:, :2].min(axis=0)
    ij = np.floor((xyz[:, :2] - lo) / FEATURE_TILE).astype(np.int64)
    key = ij[:, 1] * (int(ij[:, 0].max()) + 1) + ij[:, 0]
    order = np.argsort(key, kind="stable")
    cuts = np.flatnonzero(np.diff(key[order])) + 1
    found_here = np.zeros(len(xyz), bool)
    tree = cKDTree(xyz[:, :2])
    tiles = []
    for tile in np.split(order, cuts):
        tlo = lo + ij[tile[0]] * FEATURE_TILE - FEATURE_MARGIN
        thi = tlo + FEATURE_TILE + 2 * FEATURE_MARGIN
        centre, half = (tlo + thi) / 2, (thi - tlo) / 2
        # the tile and its margin: a square query (Chebyshev radius) on the map positions
        near = np.asarray(tree.query_ball_point(centre, half[0], p=np.inf), dtype=np.int64)
        tiles.append((tile, near))
    # by points (the margins' included), not tiles: a 50 m survey is one tile of ~20 s
    bar = _progress(None, sum(len(near) for _, near in tiles), "features", unit="pt")
    inside = np.zeros(len(xyz), bool)  # (one mask, set and cleared per tile)
    try:
        for tile, near in tiles:
            inside[tile] = True
            found = gaussian_map_features(xyz[near], cfg=cfg, rng=rng,
                                          progress=bar.update).feature
            found_here[near[found & inside[near]]] = True
            inside[tile] = False
    finally:
        bar.close()
    feature[near_cloud] = found_here
    return feature


def _bag_clouds(src: Path, out: Path, *, topic: str | None, storage: str, out_topic: str,
                keep_of: Callable[[object], tuple[object, int, int]], desc: str,
                skip_malformed: bool = False) -> dict:
    """Run `keep_of` (message -> (output message, points in, points out)) on every cloud of
    bag `src` and write the outputs on `out_topic` of bag `out`, other topics copied.
    A malformed cloud stops the run with a CloudFormatError naming it, and `out` is not
    written; with `skip_malformed`, malformed clouds are counted by kind and skipped, as
    the nodes drop them, the latest one's error kept in full."""
    n_in = n_out = clouds = seen = 0
    rejected: dict[str, int] = {}
    last_reject = None
    with BagReader(src) as reader, BagWriter(out, storage=storage) as bag:
        cloud_topic = reader.pointcloud_topic(topic)
        bag.add_topic(out_topic, POINTCLOUD2)
        # a recorded `out_topic` (a live simplifier's) is not copied: mixed with the new
        # clouds, it would count each of them twice
        others = [t for t in reader.topics() if t.topic not in (cloud_topic, out_topic)]
        for t in others:
            bag.add_topic(t.topic, t.msgtype, transient_local=t.topic == CRS_TOPIC)
        bar = _progress(None, reader.count([cloud_topic]), desc)
        try:
            for record in reader.records([cloud_topic, *(t.topic for t in others)]):
                if record.topic != cloud_topic:
                    raw = cdr_of_record(reader, record)
                    if raw is not None:
                        bag.write(record.topic, record.stamp_ns, raw)
                    continue
                bar.update(1)
                seen += 1
                msg = None
                try:
                    msg = reader.deserialize_cloud(record)
                    msg_out, a, b = keep_of(msg)
                except CloudFormatError as exc:
                    if not skip_malformed:  # (undecoded: the record's time stands for it)
                        stamp_ns = (record.stamp_ns if msg is None
                                    else messages.stamp_ns_of(msg.header))
                        raise malformed_cloud(seen, cloud_topic, stamp_ns, exc) from None
                    count_reason(rejected, str(exc))
                    last_reject = str(exc)
                    continue
                bag.write(out_topic, record.stamp_ns, _serialize(msg_out))
                clouds, n_in, n_out = clouds + 1, n_in + a, n_out + b
        finally:
            bar.close()
        if clouds == 0:
            raise BagError(f"no cloud of {src} could be processed ({sum(rejected.values())} "
                           f"rejected: {rejected})")
    return {"bag": str(out), "topic": out_topic, "messages": clouds, "points_in": n_in,
            "points_out": n_out, "rejected": sum(rejected.values()),
            "reject_reasons": rejected, "last_reject": last_reject}
