"""`lidar-obstacles evaluate` and the labelled inputs `tune` shares with it.

A labelled input is a LAS/LAZ file (the whole file is one cloud, tiled inside), a bag whose
clouds carry `classification` (the pipeline runs first), or a replay's output bag (its
`/ground` and `/obstacles` carry both `classification` and the predicted `class`).
No ROS install is needed: bags are decoded with rosbags.
"""
from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lidar_obstacles.config import (DemBuilderConfig, NodeInputConfig, ObstacleDetectorConfig,
                                    replace)
from lidar_obstacles.core.classes import GROUND
from lidar_obstacles.errors import (BagError, CloudFormatError, LasError, LidarObstaclesError,
                                    count_reason, malformed_cloud)

log = logging.getLogger(__name__)

LAS_SUFFIXES = (".las", ".laz")
ISPRS_SAMPLES = ("11", "12", "21", "22", "23", "24", "31", "41", "42", "51", "52", "53", "54",
                 "61", "71")
# Published total errors (%) beside which `--benchmark isprs` prints ours (data README).
PUBLISHED_TOTAL_ERROR = {"Axelsson PTD (2000)": 4.82, "CSF (2016)": 4.39,
                         "SMRF tuned per sample (2013)": 2.97, "Mongus (2014)": 2.74,
                         "PDAL 2.8 SMRF defaults (measured)": 5.14}


@dataclass
class LabelledCloud:
    """One cloud of a labelled input. xyz: (N, 3) float64 m; reference: (N,) uint8 ASPRS;
    predicted: (N,) uint8 or None when the pipeline has not run; height_above_ground: (N,)
    float32 m, the detector's, or None (a replay made before the field, or not run)."""

    stamp: float
    xyz: np.ndarray
    reference: np.ndarray
    predicted: np.ndarray | None = None
    vehicle: np.ndarray | None = None
    height_above_ground: np.ndarray | None = None
    frame: str | None = None  # (None: a file's, or not known)


@dataclass
class LabelledInput:
    name: str
    kind: str  # "las", "labelled_bag" or "replay_bag"
    clouds: list[LabelledCloud]
    crs: str = ""
    reject_reasons: dict[str, int] = field(default_factory=dict)  # clouds skipped, by reason

    @property
    def n_points(self) -> int:
        return sum(len(c.xyz) for c in self.clouds)


def _from_points(points: np.ndarray, stamp: float, xyz: np.ndarray | None = None
                 ) -> LabelledCloud:
    """A labelled cloud of structured `points` (N,); `xyz` (N, 3) m, float64, when known
    more exactly than the points' own fields hold them (a cloud moved into a far frame)."""
    from lidar_obstacles.io.pointcloud2 import xyz_of

    names = points.dtype.names or ()
    if "classification" not in names:
        raise CloudFormatError("clouds have no 'classification' field to evaluate against")
    pred = _class_codes(points, "class") if "class" in names else None
    hag = (np.asarray(points["height_above_ground"], np.float32)
           if pred is not None and "height_above_ground" in names else None)
    return LabelledCloud(stamp, xyz_of(points) if xyz is None else xyz,
                         _class_codes(points, "classification"), pred,
                         height_above_ground=hag)


def _class_codes(points: np.ndarray, name: str) -> np.ndarray:
    """Field `name` of structured `points` (N,) as ASPRS codes, uint8. CloudFormatError
    when it holds no codes: more than one value a point, or values that are not whole
    numbers 0-255, which uint8 made other classes without a word (a UINT16 300 class 44,
    an INT8 -1 class 255, a FLOAT32 NaN class 0, with numpy's RuntimeWarning)."""
    values = points[name]
    if values.ndim != 1:
        raise CloudFormatError(f"field '{name}' has {values.shape[-1]} values a point, "
                               "not one class code")
    if values.dtype.kind != "u" or values.dtype.itemsize != 1:
        with np.errstate(invalid="ignore"):
            bad = ~((values >= 0) & (values <= 255) & (np.floor(values) == values))
        if bad.any():
            raise CloudFormatError(f"field '{name}' holds {int(bad.sum())} values that are "
                                   f"no class code (0-255), e.g. {values[bad][0]}")
    return np.asarray(values, np.uint8)


def load_input(path: str | Path, *, topic: str | None = None,
               cfg: NodeInputConfig | None = None, skip_malformed: bool = False
               ) -> LabelledInput:
    """Read a labelled LAS/LAZ file or bag. LasError/BagError/CloudFormatError when unusable.

    A labelled bag's clouds are read as the detector would take them (``cfg``, default
    ObstacleDetectorConfig()): with `use_odometry`, moved into the odometry frame by the
    pose nearest in time (a cloud with none within `odometry_max_age` is skipped, as the
    node drops it); with an odometry topic, the vehicle's position comes with each cloud
    (the clearance grid is centred on it). A malformed cloud is a CloudFormatError naming
    it, unless `skip_malformed`: then it is skipped and counted in `reject_reasons`, as
    `replay` does."""
    cfg = cfg if cfg is not None else ObstacleDetectorConfig()
    path = Path(path)
    if path.suffix.lower() in LAS_SUFFIXES:
        from lidar_obstacles.io.las import read_las

        las = read_las(path)
        crs = f"EPSG:{las.epsg}" if las.epsg else las.crs_wkt
        return LabelledInput(path.name, "las", [_from_points(las.points, 0.0)], crs)
    from tqdm import tqdm

    from lidar_obstacles.io.bags import BagReader, read_crs
    from lidar_obstacles.io.pointcloud2 import read_points

    rejected: dict[str, int] = {}
    with BagReader(path) as reader:
        topics = {t.topic: t for t in reader.topics()}
        if "/ground" in topics and "/obstacles" in topics and topic is None:
            by_stamp: dict[int, list[np.ndarray]] = {}
            outputs = ["/ground", "/obstacles"]
            for rec in tqdm(reader.records(outputs), total=reader.count(outputs),
                            desc=f"read {path.name}", unit="msg", disable=None,
                            file=sys.stderr):
                msg = reader.deserialize(rec)
                stamp = int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)
                by_stamp.setdefault(stamp, []).append(np.asarray(read_points(msg)))
            clouds = [_from_points(np.concatenate(parts), s * 1e-9)
                      for s, parts in sorted(by_stamp.items())]
            if clouds and clouds[0].predicted is None:
                raise CloudFormatError(f"{path}: /obstacles has no 'class' field")
            kind = "replay_bag"
        else:
            clouds = _labelled_clouds(reader, topic, cfg, rejected, skip_malformed)
            kind = "labelled_bag"
        crs = read_crs(reader)
    if not clouds:
        raise BagError(f"bag {path} has no clouds")
    return LabelledInput(path.name, kind, clouds, crs, rejected)


def _labelled_clouds(reader, topic: str | None, cfg: NodeInputConfig,
                     rejected: dict[str, int], skip_malformed: bool = False
                     ) -> list[LabelledCloud]:
    """The clouds of a labelled bag, in bag order, prepared as the node prepares them. The
    node drops a cloud it cannot place, and so do these, counting them by reason in
    `rejected`. A malformed cloud is a CloudFormatError naming it, unless
    `skip_malformed`: then it is dropped and counted too, and one warning names the first
    one, for the user to find it. A BagError when none is left."""
    from lidar_obstacles.io.bags import ODOMETRY
    from lidar_obstacles.ros.node_base import PoseBuffer
    from lidar_obstacles.ros.offline import NO_POSE
    from lidar_obstacles.ros.stages import (DetectorStage, moving_frame_warning,
                                            pose_of_odometry, prepare)

    cloud_topic = reader.pointcloud_topic(topic)
    odom = [t.topic for t in reader.topics() if t.msgtype == ODOMETRY]
    poses = PoseBuffer()
    clouds, seen, malformed, first = [], 0, 0, ""
    moving: str | None = None  # the moving-frame warning, judged at the first pose
    ignored_odometry = False
    for rec in reader.records([cloud_topic, *odom]):
        if rec.topic in odom:
            problem = poses.add(pose_of_odometry(reader.deserialize(rec)))
            if problem is not None and not ignored_odometry:  # (left out, as the node does)
                log.warning("evaluate: ignored %s (and any more such)", problem)
                ignored_odometry = True
            continue
        seen += 1
        try:
            msg = reader.deserialize_cloud(rec)
        except CloudFormatError as exc:  # (no header: the record's time stands for it)
            if not skip_malformed:
                raise malformed_cloud(seen, cloud_topic, rec.stamp_ns, exc) from None
            count_reason(rejected, str(exc))
            malformed += 1
            first = first or (f"cloud {seen} (stamp {rec.stamp_ns // 10**9}."
                              f"{rec.stamp_ns % 10**9:09d} s): {exc}")
            continue
        stamp_ns = int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)
        pose = poses.nearest(stamp_ns, cfg.odometry_max_age)
        if moving is None and pose is not None:
            moving = moving_frame_warning(msg.header.frame_id, pose, cfg.use_odometry) or ""
            if moving:
                log.warning("evaluate: %s", moving)
        if cfg.use_odometry and pose is None:
            rejected[NO_POSE] = rejected.get(NO_POSE, 0) + 1
            continue
        try:
            prep = prepare(msg, keep_non_finite=False, max_points=cfg.input.max_points,
                           pose=pose, transform=cfg.use_odometry)
            cloud = _from_points(prep.points, stamp_ns * 1e-9, prep.xyz)
        except CloudFormatError as exc:
            if not skip_malformed:
                raise malformed_cloud(seen, cloud_topic, stamp_ns, exc) from None
            count_reason(rejected, str(exc))
            malformed += 1
            first = first or (f"cloud {seen} (stamp {stamp_ns // 10**9}."
                              f"{stamp_ns % 10**9:09d} s): {exc}")
            continue
        if cloud.predicted is not None:  # (it was scored, re-run on half a scan: kappa 0.12)
            raise BagError(
                f"{cloud_topic} of {reader.path} is a detector's output (its points have a "
                "'class' field), not a labelled scan: without --topic, `evaluate` scores a "
                "replay's /ground and /obstacles together")
        cloud.vehicle = DetectorStage.vehicle(pose, prep.frame_id)
        cloud.frame = prep.frame_id
        clouds.append(cloud)
    if not clouds and malformed:
        raise BagError(f"none of the {seen} clouds on {cloud_topic} can be evaluated: "
                       f"{malformed} malformed, the first {first}")
    if not clouds and rejected:
        raise BagError(f"use_odometry is true but none of the {seen} clouds on "
                       f"{cloud_topic} has an odometry pose within "
                       f"{cfg.odometry_max_age} s of its stamp")
    if malformed:
        log.warning("evaluate: skipped %d malformed of the %d clouds on %s, the first %s",
                    malformed, seen, cloud_topic, first)
    return clouds


def run_detector(inp: LabelledInput, cfg: ObstacleDetectorConfig, *,
                 progress: bool = False, deadline: float | None = None) -> list[float]:
    """Run the obstacle detector over every cloud of `inp` in order (one pipeline object, so
    the ground context streams as in the node); fills `predicted`. Returns seconds per cloud.
    TimeoutError when time.monotonic() passes `deadline` between two clouds."""
    from lidar_obstacles.core.pipeline import ObstacleDetector

    det = ObstacleDetector(cfg)
    latencies: list[float] = []
    clouds = inp.clouds
    if progress:
        from tqdm import tqdm

        clouds = tqdm(clouds, desc=f"detect {inp.name}", disable=None, file=sys.stderr)
    for c in clouds:
        if deadline is not None and time.monotonic() > deadline:
            raise TimeoutError(f"out of time after {len(latencies)} of {len(inp.clouds)} "
                               f"clouds of {inp.name}")
        t0 = time.perf_counter()
        res = det.process(c.xyz, stamp=c.stamp, vehicle_xyz=c.vehicle, frame=c.frame)
        latencies.append(time.perf_counter() - t0)
        c.predicted, c.height_above_ground = res.classes, res.height_above_ground
    return latencies


def _concat(inp: LabelledInput) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """xyz (N, 3), reference and predicted classes (N,) of every cloud, less the stray
    points far from their cloud (:func:`far_points`): a blunder kilometres off, which
    the detector calls noise, would stretch the blocks, the DEM and the maps over the
    distance (at 1e20 m the maps could not be drawn)."""
    xyz, ref, pred, _ = _concat_all(inp)
    return xyz, ref, pred


def _concat_all(inp: LabelledInput
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`_concat`, and the (N,) heights above ground of the same points (None when a
    cloud has none)."""
    from lidar_obstacles.core.ground import far_points

    near = np.concatenate([~far_points(c.xyz) for c in inp.clouds])
    xyz = np.concatenate([c.xyz for c in inp.clouds])[near]
    ref = np.concatenate([c.reference for c in inp.clouds])[near]
    pred = np.concatenate([c.predicted for c in inp.clouds])[near]  # type: ignore[misc]
    hags = [c.height_above_ground for c in inp.clouds]
    hag = (None if any(h is None for h in hags)
           else np.concatenate([h for h in hags if h is not None])[near])
    return xyz, ref, pred, hag


def dem_comparison(xyz: np.ndarray, reference: np.ndarray, predicted: np.ndarray, *,
                   height_above_ground: np.ndarray | None = None,
                   cfg: DemBuilderConfig | None = None, check_points: int = 100,
                   seed: int = 0) -> dict:
    """DEM from the predicted ground vs DEM from the reference ground, same grid, same
    interpolator, over the cells inside the data (holding a point of any class: the
    interpolator's reach beyond the survey is not the ground's error); plus errors at
    up to `check_points` reference ground points held out of both. With the detector's
    height_above_ground (N,) m, the predicted ground is what `dem_builder` builds on, its
    bare earth (`dem.ground_band`, `dem.patch_*`), as `bench_dem.py` compares it.

    Returns {"grid": grid_errors with "coverage" (the share of the reference DEM's cells
    inside the data that the predicted DEM has), "check_points": grid_errors,
    "reference_dem": DemGrid, "predicted_dem": DemGrid, "inside": (rows, cols) bool, the
    cells compared} (the grids for pictures; not JSON)."""
    from lidar_obstacles.core.dem import build_dem
    from lidar_obstacles.core.metrics import GROUND_CODES, grid_errors, grid_values_at
    from lidar_obstacles.core.pipeline import bare_earth_of

    cfg = cfg or DemBuilderConfig()
    ref_ground = np.isin(reference, GROUND_CODES)
    pred_ground = predicted == GROUND
    if height_above_ground is not None:
        pred_ground = bare_earth_of(xyz, pred_ground, height_above_ground, cfg.dem)
    rng = np.random.default_rng(seed)
    idx = np.flatnonzero(ref_ground)
    held = rng.choice(idx, size=min(check_points, len(idx) // 10), replace=False) \
        if len(idx) >= 30 else np.zeros(0, int)
    keep = np.ones(len(xyz), bool)
    keep[held] = False
    lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    box = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))  # xmin, ymin, xmax, ymax
    ref_dem = build_dem(xyz[ref_ground & keep], cfg=cfg, bounds=box)
    pred_dem = build_dem(xyz[pred_ground & keep], cfg=cfg, bounds=box)
    inside = build_dem(xyz, cfg=replace(cfg, {"dem.fill_distance": 0.0}),
                       bounds=box).count > 0
    ref_cells = np.where(inside, ref_dem.elevation, np.nan)
    grid = grid_errors(ref_cells, pred_dem.elevation)
    # the share of those cells the predicted DEM has at all: the errors are of the cells
    # both have, and a ground lost over a whole area showed only in a smaller n
    n_ref = int(np.isfinite(ref_cells).sum())
    grid["coverage"] = grid["n"] / n_ref if n_ref else None
    out: dict[str, Any] = {"grid": grid, "reference_dem": ref_dem, "predicted_dem": pred_dem,
                           "inside": inside}
    if len(held):
        est = grid_values_at(pred_dem.elevation, xyz[held, :2],
                             resolution=pred_dem.resolution, origin=tuple(pred_dem.origin))
        out["check_points"] = grid_errors(xyz[held, 2], est)
    return out


def evaluate(src: str | Path, *, params_file: str | Path | None = None,
             report_dir: str | Path | None = None, blocks: str = "6x6",
             topic: str | None = None, with_dem: bool = True,
             skip_malformed: bool = False) -> dict:
    """All the figures of `lidar-obstacles evaluate` for one input (JSON-ready dict). A
    malformed cloud of a labelled bag stops it unless `skip_malformed` (`load_input`)."""
    from lidar_obstacles.core.metrics import (evaluate_classes, jsonable, latency_stats,
                                              parse_blocks, raised_objects_as_ground)

    parse_blocks(blocks)  # a mistyped grid said now, not after the pipeline's run
    if report_dir is not None:
        _check_report_folder(Path(report_dir))  # before the work, not after it
    det_cfg, dem_cfg = _configs(params_file)
    inp = load_input(src, topic=topic, cfg=det_cfg, skip_malformed=skip_malformed)
    latencies: list[float] = []
    if inp.kind != "replay_bag":
        latencies = run_detector(inp, det_cfg, progress=True)
    elif params_file is not None:  # the classes are the replay's, found with its parameters
        log.warning("evaluate: %s is a replay's output, whose classes are scored as they "
                    "are: the detector's parameters of %s do not apply (%s)", inp.name,
                    params_file, "its DEM parameters do" if with_dem else "nor, with "
                    "--no-dem, its DEM parameters")
    xyz, ref, pred, hag = _concat_all(inp)
    codes = np.unique(ref)
    if len(codes) == 1:  # a raw survey's "unclassified" everywhere: figures of nothing
        log.warning("evaluate: every reference point of %s has class %d: is it labelled? "
                    "(kappa against a single class is 0 or undefined)", inp.name, codes[0])
    metrics: dict[str, Any] = {"source": str(src), "kind": inp.kind,
                               "clouds": len(inp.clouds),
                               "rejected": sum(inp.reject_reasons.values()),
                               "reject_reasons": inp.reject_reasons,
                               "far_points": inp.n_points - len(ref)}
    metrics.update(evaluate_classes(ref, pred, xy=xyz[:, :2], blocks=blocks))
    dem = None
    if with_dem:
        dem = dem_comparison(xyz, ref, pred, height_above_ground=hag, cfg=dem_cfg)
        metrics["dem"] = {"grid": dem["grid"], "check_points": dem.get("check_points")}
        # every class's objects put in ground, by their height above the reference ground
        metrics["safety"].update(raised_objects_as_ground(
            ref, pred, xyz[:, 2] - dem["reference_dem"].sample(xyz[:, :2])))
    if latencies:
        metrics["latency"] = latency_stats(latencies)
    metrics = jsonable(metrics)
    if report_dir is not None:
        try:
            metrics["report"] = str(write_evaluation_report(Path(report_dir), metrics, xyz,
                                                            ref, pred, dem, latencies, inp.name))
        except OSError as exc:
            raise LidarObstaclesError(f"cannot write the report in {report_dir}: {exc}") from None
    return metrics


def _configs(params_file) -> tuple[ObstacleDetectorConfig, DemBuilderConfig]:
    from lidar_obstacles.config import load_params_file

    if params_file is None:
        return ObstacleDetectorConfig(), DemBuilderConfig()
    return (load_params_file(params_file, ObstacleDetectorConfig, "obstacle_detector"),
            load_params_file(params_file, DemBuilderConfig, "dem_builder"))


def write_evaluation_report(out: Path, metrics: dict, xyz, ref, pred, dem, latencies,
                            name: str) -> Path:
    """PNGs, metrics.json and a self-contained report.html in folder `out`, all or none: an
    interrupted report left some of its files and no report.html. Written into a folder
    beside `out` that replaces it once complete (:func:`atomic_folder`), when `out` is not
    there, empty or an earlier report; LidarObstaclesError when it is something else.
    Returns the path of report.html."""
    from lidar_obstacles.io.atomic import atomic_folder

    _check_report_folder(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_folder(out, lambda tmp: _report_files(tmp, metrics, xyz, ref, pred, dem, latencies,
                                                 name))
    return out / "report.html"


def _check_report_folder(out: Path) -> None:
    """LidarObstaclesError unless `out` is free for a report: not there, an empty folder or
    an earlier report. Anything else is the user's, which the report would replace."""
    if out.exists() and not (out.is_dir() and (not any(out.iterdir())
                                               or (out / "report.html").is_file())):
        raise LidarObstaclesError(f"{out} exists and is not a report: not overwriting it")


def _report_files(out: Path, metrics: dict, xyz, ref, pred, dem, latencies, name: str) -> None:
    """The files of :func:`write_evaluation_report`, into the existing folder `out`."""
    from lidar_obstacles import report

    images: dict[str, Path] = {}
    images["confusion matrix"] = report.confusion_png(
        metrics["confusion"]["matrix"], metrics["confusion"]["labels"], out / "confusion.png")
    # Maps need an area: a cloud of one point, or of one spot or line, has none to draw.
    if len(xyz) < 3 or not (np.ptp(xyz[:, 0]) > 0 and np.ptp(xyz[:, 1]) > 0):
        report.write_report(out, metrics, images, title=f"lidar_obstacles evaluation: {name}",
                            notes="The points span no area: no maps drawn.")
        return
    if metrics.get("blocks"):
        b = metrics["blocks"]
        grid = np.array([[np.nan if v is None else v for v in row] for row in b["kappa"]])
        images["kappa per block"] = report.block_kappa_png(grid, tuple(b["extent"]),
                                                           out / "block_kappa.png", xy=xyz[:, :2])
    images["classes (predicted)"] = report.cloud_views_png(xyz, pred, out / "classes.png",
                                                           title=f"{name}: predicted classes")
    images["classes (reference)"] = report.cloud_views_png(xyz, ref, out / "reference.png",
                                                           title=f"{name}: reference classes")
    images["errors"] = report.error_views_png(xyz, ref, pred, out / "errors.png",
                                              title=f"{name}: ground/object errors")
    if dem is not None:
        p = dem["predicted_dem"]
        if np.isfinite(p.elevation).any() and min(p.elevation.shape) >= 2:
            images["DEM hillshade"] = report.hillshade_png(
                p.elevation, p.resolution, tuple(p.origin), out / "dem_hillshade.png",
                title="DEM from the predicted ground")
            # the cells `dem.grid`'s figures are of: inside the data (the interpolation
            # beyond the survey is no ground's error, and the picture said otherwise)
            err = np.where(dem["inside"], p.elevation - dem["reference_dem"].elevation, np.nan)
            if np.isfinite(err).any():
                images["DEM error"] = report.dem_error_png(
                    err, p.resolution, tuple(p.origin), out / "dem_error.png",
                    title="DEM error: predicted minus reference ground")
    if latencies:
        images["latency"] = report.latency_histogram_png(latencies, out / "latency.png")
    report.write_report(out, metrics, images, title=f"lidar_obstacles evaluation: {name}")


def benchmark_isprs(folder: str | Path, *, params_file: str | Path | None = None) -> dict:
    """All 15 ISPRS reference samples with one parameter set: per-sample and mean Type I,
    Type II, total error and kappa (the mean of the 15 samples' figures, as the ISPRS
    test's tables compare filters), with the published figures beside them; and the
    paper's test of 6 x 6 blocks: per sample its eligible blocks (>= 5 % of each class) and
    the share of them with ground/object kappa > 0.8, over all samples pooled (every
    eligible block counts once) and as the mean of the samples' shares."""
    import sys

    from tqdm import tqdm

    from lidar_obstacles.core.metrics import block_kappa, ground_object_errors

    folder = Path(folder)
    # said before the first sample's minute of work, not as "samp11-utm.laz/samp11-utm.laz
    # not found" of a file, or at the first missing one after the others ran
    if not folder.is_dir():
        raise LasError(f"--benchmark isprs takes the folder of the 15 ISPRS samples, "
                       f"{'not a file' if folder.exists() else 'not found'}: {folder}")
    missing = [f"samp{s}-utm.laz" for s in ISPRS_SAMPLES
               if not (folder / f"samp{s}-utm.laz").is_file()]
    if missing:
        raise LasError(f"{folder} lacks {len(missing)} of the 15 ISPRS samples: "
                       f"{', '.join(missing)}")
    det_cfg, _ = _configs(params_file)
    rows = {}
    for s in tqdm(ISPRS_SAMPLES, desc="isprs", disable=None, file=sys.stderr):
        path = folder / f"samp{s}-utm.laz"
        inp = load_input(path)
        t0 = time.perf_counter()
        run_detector(inp, det_cfg)
        seconds = time.perf_counter() - t0
        xyz, ref, pred = _concat(inp)
        e = ground_object_errors(ref == GROUND, pred == GROUND)
        b = block_kappa(xyz[:, :2], ref == GROUND, pred == GROUND)
        rows[f"samp{s}"] = {"points": int(len(ref)), "type_i": e["type_i"],
                            "type_ii": e["type_ii"], "total_error": e["total_error"],
                            "kappa": e["kappa"], "blocks_eligible": b["n_eligible"],
                            "blocks_kappa_gt_0_8": b["share_kappa_gt_0_8"],
                            "seconds": round(seconds, 3)}
    keys = ("type_i", "type_ii", "total_error", "kappa")
    mean = {k: float(np.mean([r[k] for r in rows.values()])) for k in keys}
    eligible = sum(r["blocks_eligible"] for r in rows.values())
    good = sum(r["blocks_eligible"] * (r["blocks_kappa_gt_0_8"] or 0.0) for r in rows.values())
    shares = [r["blocks_kappa_gt_0_8"] for r in rows.values()
              if r["blocks_kappa_gt_0_8"] is not None]
    blocks = {"eligible": eligible,
              "share_kappa_gt_0_8_pooled": good / eligible if eligible else None,
              "share_kappa_gt_0_8_mean_of_samples": float(np.mean(shares)) if shares else None}
    return {"samples": rows, "mean": mean, "blocks": blocks,
            "points_per_second": sum(r["points"] for r in rows.values())
            / sum(r["seconds"] for r in rows.values()),
            "published_total_error_percent": PUBLISHED_TOTAL_ERROR}


def isprs_table(result: dict) -> str:
    """Markdown table of benchmark_isprs (percent)."""
    def share(value: float | None) -> str:
        return "-" if value is None else f"{100 * value:.1f}"

    lines = ["| sample | points | Type I % | Type II % | total % | kappa | blocks > 0.8 % "
             "(of eligible) |", "|---|---|---|---|---|---|---|"]
    for name, r in result["samples"].items():
        lines.append(f"| {name} | {r['points']} | {100 * r['type_i']:.2f} | "
                     f"{100 * r['type_ii']:.2f} | {100 * r['total_error']:.2f} | "
                     f"{r['kappa']:.3f} | {share(r['blocks_kappa_gt_0_8'])} "
                     f"({r['blocks_eligible']}) |")
    m, b = result["mean"], result["blocks"]
    lines.append(f"| **mean** of the samples | | {100 * m['type_i']:.2f} | "
                 f"{100 * m['type_ii']:.2f} | **{100 * m['total_error']:.2f}** | "
                 f"**{m['kappa']:.3f}** | {share(b['share_kappa_gt_0_8_mean_of_samples'])} |")
    lines.append(f"| all eligible blocks pooled | | | | | | "
                 f"**{share(b['share_kappa_gt_0_8_pooled'])}** ({b['eligible']}) |")
    for name, te in result["published_total_error_percent"].items():
        lines.append(f"| {name} | | | | {te:.2f} | | |")
    return "\n".join(lines)
