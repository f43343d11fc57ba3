"""Message-level stages shared by the live nodes and offline `replay`.

A stage takes one PointCloud2 (rclpy or rosbags message) and the vehicle pose, runs the
core pipeline object and returns the messages to publish as ``(topic, message)`` pairs.
The node publishes them; `replay` serializes them into a bag. Same objects, same results.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from lidar_obstacles.config import (CloudSimplifierConfig, DemBuilderConfig, NodeInputConfig,
                                    ObstacleDetectorConfig, PointsNodeConfig)
from lidar_obstacles.core.arrays import all_columns
from lidar_obstacles.core.classes import GROUND, NOISE
from lidar_obstacles.core.dem import DemTooLarge, too_large_message
from lidar_obstacles.core.pipeline import (DemPipeline, GroundStep, ObstacleDetector,
                                           ObstacleResult)
from lidar_obstacles.errors import CloudFormatError
from lidar_obstacles.io.pointcloud2 import (FLOAT32, append_fields, read_points,
                                            select_points, with_xyz, xyz_of)
from lidar_obstacles.ros import messages

if TYPE_CHECKING:
    from lidar_obstacles.core.dem import DemGrid


@dataclass(frozen=True)
class Pose:
    """A rigid pose: position (3,) metres and quaternion (4,) x y z w, in `frame_id`, of
    the body frame `child_frame_id` (odometry's; "" when unknown)."""

    stamp_ns: int
    position: np.ndarray
    orientation: np.ndarray
    frame_id: str
    child_frame_id: str = ""

    def rotation(self) -> np.ndarray:
        x, y, z, w = _unit(self.orientation)
        return np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _unit(q: np.ndarray) -> np.ndarray:
    """(4,) quaternion q at unit length; scaled by its largest element first, so that a
    huge one (1e300: the norm overflowed to inf, and the pose turned into no rotation)
    keeps its direction. All zeros for a quaternion of no length."""
    q = np.asarray(q, float)
    top = float(np.max(np.abs(q))) if q.size else 0.0
    if not top > 0:
        return np.zeros(4)
    q = q / top
    return q / np.linalg.norm(q)


def pose_of_odometry(msg) -> Pose:
    """Pose of a nav_msgs/Odometry (rclpy or rosbags)."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return Pose(messages.stamp_ns_of(msg.header), np.array([p.x, p.y, p.z], float),
                np.array([q.x, q.y, q.z, q.w], float), msg.header.frame_id,
                msg.child_frame_id)


# No pose of a survey or a flight lies further from its frame's origin (m): as the clouds'
# limit (io.las.MAX_COORDINATE); a position of 1e300 m moved the cloud there.
MAX_POSE_COORDINATE = 1e8


def pose_problem(pose: Pose) -> str | None:
    """Why a pose cannot place a cloud (None when it can): a position or orientation
    that is not finite, a position beyond MAX_POSE_COORDINATE, an orientation of no length
    (all zeros: "unset"), or an unset stamp (0, which would also have emptied the held
    poses as a clock gone back). Used as it came, such a pose put every point of its cloud
    at NaN, or at 1e12 m."""
    at = f"odometry pose at {pose.stamp_ns / 1e9:.3f} s"
    if not (np.isfinite(pose.position).all() and np.isfinite(pose.orientation).all()):
        return (f"{at} is not finite (position {pose.position.tolist()}, orientation "
                f"{pose.orientation.tolist()})")
    if np.abs(pose.position).max() > MAX_POSE_COORDINATE:
        return (f"{at} lies {np.abs(pose.position).max():.3g} m from its frame's origin, "
                f"beyond {MAX_POSE_COORDINATE:.0e} m of any flight")
    if not np.abs(pose.orientation).max() > 0:
        return f"{at} has a zero quaternion"
    if pose.stamp_ns == 0:
        return "odometry pose with an unset stamp (0)"
    return None


def moving_frame_warning(cloud_frame: str, pose: Pose | None, use_odometry: bool
                         ) -> str | None:
    """What to say, once, when the clouds' frame and the odometry's do not fit together
    (None when all is well or it cannot be told):

    - clouds in the vehicle's own frame (odometry's child frame) processed without
      `use_odometry`: the ground filter, the rolling contexts and the DEM then work in a
      frame that moves with every message (the simulated sensor-frame flight: ground
      kappa 0.956 instead of 0.969), and nothing else would tell;
    - with `use_odometry`, clouds in a third frame (a `lidar_link`, with odometry of
      `base_link`): without tf the clouds are placed as if in the child frame, so a
      sensor mounted off the body's origin, or tilted, puts the ground off or aslant (a
      lidar pitched 90 degrees made flat ground a wall of obstacles)."""
    if pose is None or not pose.child_frame_id:
        return None
    frame, child = cloud_frame.lstrip("/"), pose.child_frame_id.lstrip("/")
    if not use_odometry:
        if frame != child:
            return None
        return (f"the clouds are in '{cloud_frame}', the frame odometry moves "
                f"('{pose.frame_id}' -> '{pose.child_frame_id}'), and use_odometry is "
                "false: they are processed in a moving frame; set use_odometry: true to "
                f"place them in '{pose.frame_id}'")
    if frame in (child, pose.frame_id.lstrip("/")):
        return None
    return (f"the clouds are in '{cloud_frame}' and odometry places '{pose.child_frame_id}' "
            f"in '{pose.frame_id}': there is no tf here, so they are placed as if "
            f"'{cloud_frame}' were '{pose.child_frame_id}'; publish them in "
            f"'{pose.child_frame_id}' (or odometry of '{cloud_frame}') if the sensor is "
            "mounted off the body's origin or tilted")


@dataclass(frozen=True)
class Prepared:
    """A decoded cloud: its points (1-D structured), float64 xyz in the output frame."""

    points: np.ndarray
    xyz: np.ndarray
    stamp_ns: int
    frame_id: str


def missing_frame_warning(cloud_frame: str) -> str | None:
    """What to say, once, of clouds with no frame_id (None when they have one): they are
    processed all the same, in whatever frame they are, and every output goes out with no
    frame either, which RViz and tf cannot place."""
    if cloud_frame.strip("/"):
        return None
    return ("the clouds have no frame_id: the outputs have none either, and RViz or tf "
            "cannot place them; set the driver's frame (REP-103: a gravity-aligned frame "
            "such as 'map' or 'odom', or the sensor's with use_odometry)")


def coarse_xyz_warning(msg, pose: Pose | None, cfg: NodeInputConfig) -> str | None:
    """What to say, once, when clouds moved into the odometry frame keep FLOAT32 `x y z`
    (`odometry_xyz_type: input`) and the vehicle is so far from that frame's origin that
    FLOAT32 holds the coordinates only to more than a centimetre (beyond 131 km: a UTM
    frame's, whose northings it holds to 0.5 m). None when all is well."""
    if (not isinstance(cfg, PointsNodeConfig) or cfg.odometry_xyz_type != "input"
            or not cfg.use_odometry or pose is None
            or msg.header.frame_id.lstrip("/") == pose.frame_id.lstrip("/")):
        return None
    if not any(f.name in ("x", "y", "z") and f.datatype == FLOAT32 for f in msg.fields):
        return None
    far = float(np.max(np.abs(pose.position)))
    step = float(np.spacing(np.float32(far)))
    if step <= 0.01:
        return None
    return (f"the clouds are moved into '{pose.frame_id}', {far:.0f} m from its origin"
            f", and keep their FLOAT32 x y z (odometry_xyz_type: input), "
            f"which there hold a position only to {step:g} m; set odometry_xyz_type: "
            "float64, or give odometry in a local frame")


def coarse_dem_warning(grid: DemGrid) -> str | None:
    """What to say, once, when the `dem` cloud's FLOAT32 x y (the contract's type) cannot
    tell the grid's cells apart: beyond ~2 000 km from the frame's origin at 0.25 m cells
    (a UTM frame's northings: 800 rows gave 400 distinct y). None when all is well."""
    if grid.elevation.size == 0:
        return None
    rows, cols = grid.shape
    far = float(np.max(np.abs(np.asarray(grid.origin, float)
                              + np.array([cols, rows]) * grid.resolution)))
    step = float(np.spacing(np.float32(far)))
    if step <= grid.resolution / 4:
        return None
    return (f"the DEM lies {far:.0f} m from its frame's origin, where the `dem` cloud's "
            f"FLOAT32 x y hold a position only to {step:g} m, against cells of "
            f"{grid.resolution:g} m: take `dem_image` with `dem_info` (exact), or a local "
            "frame")


def prepare(msg, *, keep_non_finite: bool, max_points: int, pose: Pose | None,
            transform: bool, widen_xyz: bool = False) -> Prepared:
    """Decode a PointCloud2 and, when `transform`, move it into the pose's frame (a
    cloud already in that frame, the odometry's `header.frame_id`, passes unchanged).

    Raises CloudFormatError for malformed or oversize clouds. Non-finite points are dropped
    unless `keep_non_finite`; kept ones stay in the output but are never ground. A moved
    cloud's points keep the types of their fields, or carry x, y, z as FLOAT64 with
    `widen_xyz` (`with_xyz`); `xyz` is float64 either way, and is what is classified.
    """
    nanosec = int(msg.header.stamp.nanosec)
    if nanosec >= 1_000_000_000:  # (uint32: never negative) outputs were stamped -2^31 s
        raise CloudFormatError(f"header stamp has nanosec {nanosec}, not below 1e9")
    n_in = int(msg.width) * int(msg.height)
    if n_in > max_points:
        raise CloudFormatError(f"cloud has {n_in} points, more than input.max_points="
                               f"{max_points}")
    points = read_points(msg, keep_non_finite=keep_non_finite).reshape(-1)
    xyz = xyz_of(points)
    frame = msg.header.frame_id
    # (names as tf2 reads them: a leading '/' names the same frame, and the cloud was
    # moved by the pose a second time)
    if transform and pose is not None and frame.lstrip("/") != pose.frame_id.lstrip("/"):
        xyz = xyz @ pose.rotation().T + pose.position
        points = with_xyz(points, xyz, widen=widen_xyz)
        frame = pose.frame_id
    return Prepared(points, xyz, messages.stamp_ns_of(msg.header), frame)


def prepare_for(msg, cfg: ObstacleDetectorConfig, pose: Pose | None
                ) -> tuple[Prepared, np.ndarray]:
    """`prepare` with the detector's input settings, and which points are finite, (N,)
    bool."""
    prep = prepare(msg, keep_non_finite=cfg.input.keep_non_finite,
                   max_points=cfg.input.max_points, pose=pose, transform=cfg.use_odometry,
                   widen_xyz=cfg.odometry_xyz_type == "float64")
    return prep, all_columns(np.isfinite(prep.xyz))


@dataclass(frozen=True)
class DetectorWork:
    """A cloud between `DetectorStage.start` and `finish`: its decoded points (1-D
    structured, in the output frame), stamp and frame, which of them are finite (N,) bool,
    the ground step of those, and the seconds spent so far. Plain data and nothing more
    (`replay` hands it to another process)."""

    points: np.ndarray
    stamp_ns: int
    frame_id: str
    finite: np.ndarray
    ground: GroundStep
    seconds: float

    def dem_ground(self) -> tuple[np.ndarray, np.ndarray]:
        """(G, 3) float64 m ground points and their (G,) m height above the ground surface:
        what `dem_builder` would find itself with `dem.ground_source: detector`."""
        g = self.ground
        return g.xyz[g.ground], g.height_above_ground[g.ground]


def _attr(points: np.ndarray, name: str) -> np.ndarray | None:
    names = points.dtype.names or ()
    return np.asarray(points[name]) if name in names else None


# The markers' lifetime is stretched to three times the clouds' interval, up to this (s): a
# gap in a bag (two flight lines 20 minutes apart) should not leave boxes for an hour.
MARKER_STRETCH_MAX_S = 60.0


class DetectorStage:
    """`obstacle_detector`'s work on one message."""

    def __init__(self, cfg: ObstacleDetectorConfig) -> None:
        self.cfg = cfg
        self.pipeline = ObstacleDetector(cfg)
        self._last_marker_stamp_ns: int | None = None

    def reconfigure(self, cfg: ObstacleDetectorConfig) -> None:
        self.cfg = cfg
        self.pipeline.reconfigure(cfg)

    @staticmethod
    def vehicle(pose: Pose | None, frame_id: str) -> np.ndarray | None:
        """(3,) m the vehicle's position in the cloud's (output) frame, where the clearance
        grid and the DEM's window centre on it; None when the pose is in another frame
        (odometry in `odom`, clouds in `map`, without `use_odometry`): a grid around the
        pose's numbers in the wrong frame held nothing of the cloud."""
        if pose is None or pose.frame_id.lstrip("/") != frame_id.lstrip("/"):
            return None
        return pose.position

    def marker_lifetime(self, stamp_ns: int) -> float:
        """Seconds the markers of the cloud stamped stamp_ns stay (`obstacles.marker_lifetime`,
        0 = until replaced), stretched to three times the interval since the previous
        cloud's stamp, at most MARKER_STRETCH_MAX_S: a `tin` cloud may take 3 s, and its
        boxes should not vanish before the next replaces them. Called once per cloud, in
        order."""
        base = self.cfg.obstacles.marker_lifetime
        last, self._last_marker_stamp_ns = self._last_marker_stamp_ns, stamp_ns
        if base <= 0 or last is None or stamp_ns <= last:
            return base
        return max(base, min(3e-9 * (stamp_ns - last), MARKER_STRETCH_MAX_S))

    def process(self, msg, pose: Pose | None = None) -> tuple[list[tuple[str, object]], dict]:
        """Returns the messages to publish and a stats dict (points, timings)."""
        return self.finish(self.start(msg, pose))

    def start(self, msg, pose: Pose | None = None) -> DetectorWork:
        """The first half of `process`: decode the cloud (CloudFormatError when malformed)
        and find its ground."""
        cfg = self.cfg
        t0 = time.perf_counter()
        prep, finite = prepare_for(msg, cfg, pose)
        step = self.pipeline.ground_step(
            prep.xyz[finite], stamp=prep.stamp_ns * 1e-9,
            vehicle_xyz=self.vehicle(pose, prep.frame_id), frame=prep.frame_id)
        return DetectorWork(prep.points, prep.stamp_ns, prep.frame_id, finite, step,
                            time.perf_counter() - t0)

    def finish(self, work: DetectorWork) -> tuple[list[tuple[str, object]], dict]:
        """The second half of `process`: obstacles and the messages to publish, with a
        stats dict (points, timings)."""
        return self.publish(work, *self.classify(work.ground))

    def classify(self, ground: GroundStep) -> tuple[ObstacleResult, float]:
        """The obstacles of a cloud whose ground was found, and the seconds it took. Keeps
        state (the towers seen), so clouds come in order; `replay` runs it in a process
        of its own."""
        t0 = time.perf_counter()
        return self.pipeline.obstacle_step(ground), time.perf_counter() - t0

    def publish(self, work: DetectorWork, result: ObstacleResult, seconds: float
                ) -> tuple[list[tuple[str, object]], dict]:
        """The messages of a classified cloud, with a stats dict (points, timings, the
        seconds of all its work). Called once per cloud, in order (the markers' lifetime
        follows the clouds' interval)."""
        t0 = time.perf_counter()
        finite = work.finite
        n = len(work.points)
        classes = np.full(n, NOISE, np.uint8)  # non-finite points: noise, never ground
        hag = np.full(n, np.nan, np.float32)
        ground = np.zeros(n, bool)
        classes[finite], hag[finite], ground[finite] = (
            result.classes, result.height_above_ground, result.ground)
        out_points = append_fields(work.points, {"class": classes, "height_above_ground": hag},
                                   overwrite=True)
        hdr = messages.header(work.stamp_ns, work.frame_id)
        out: list[tuple[str, object]] = [
            ("ground", messages.cloud(select_points(out_points, ground), hdr)),
            ("obstacles", messages.cloud(select_points(out_points, ~ground), hdr)),
            ("obstacle_markers", messages.markers(result.objects, hdr,
                                                  self.marker_lifetime(work.stamp_ns))),
        ]
        if result.clearance is not None:
            c = result.clearance
            out.append(("clearance", messages.occupancy(c.cells, c.origin, c.resolution, hdr)))
        if result.edges is not None:  # `features.enabled`: the obstacles' feature points
            edges = np.zeros(n, bool)
            edges[finite] = result.edges
            out.append(("obstacle_edges", messages.cloud(select_points(out_points, edges), hdr)))
        # the points processed: the finite ones (kept non-finite ones only pass through)
        stats = {"points_in": int(np.count_nonzero(finite)), "ground": int(ground.sum()),
                 "obstacles": int((~ground).sum()),
                 "objects": len(result.objects), "timings": dict(result.timings),
                 "seconds": work.seconds + seconds + time.perf_counter() - t0,
                 "classes": classes, "restart": work.ground.restart}
        return out, stats


class DemStage:
    """`dem_builder`'s work: feed messages into the rolling DEM, publish it on demand."""

    def __init__(self, cfg: DemBuilderConfig, *, whole: bool = False) -> None:
        """whole: the DEM of the whole bag (`export-dem`), or, over `dem.max_cells`,
        none: `too_large` is set, the clouds after are only measured (`span`), and
        `too_large_message` names the survey's span."""
        self.cfg = cfg
        self.pipeline = DemPipeline(cfg, whole=whole)
        self.whole = whole
        self.too_large = False
        # the (2,) x, y m bounds of every cloud's points, with `whole`
        self.span: tuple[np.ndarray, np.ndarray] | None = None
        self.frame_id = "map"
        self.last_stamp_ns = 0
        # the DEM at its held-out check points, as of the last `dem_outputs`
        self.check_stats: dict[str, float | int | None] = {}
        self.coarse_warning: str | None = None  # of the last `dem_outputs`'s grid

    def reconfigure(self, cfg: DemBuilderConfig) -> None:
        self.cfg = cfg
        self.pipeline.reconfigure(cfg)

    def check_values(self) -> dict[str, str]:
        """The DEM at its held-out check points (`thinning.check_points`), as of the last
        `dem_outputs`, for the diagnostics: check_rmse_m, check_r2 ("-" until known) and
        check_n."""
        return {k: ("-" if v is None else f"{v:.4g}" if isinstance(v, float) else str(v))
                for k, v in self.check_stats.items()}

    def shares_ground_with(self, detector_cfg: ObstacleDetectorConfig) -> bool:
        """True when the detector's ground of a message is the ground this stage would
        find: `dem.ground_source: detector` with the same filter, frame and input limits,
        or `input` (the detector's ground is what it takes). `replay` then hands it over
        instead of filtering every cloud twice."""
        d, c = detector_cfg, self.cfg
        if c.dem.ground_source == "input":  # (the detector's ground is its input by name)
            return True
        return (c.dem.ground_source == "detector" and c.use_odometry == d.use_odometry
                and c.input.max_points == d.input.max_points
                and (c.tiling, c.ground, c.tin, c.ransac, c.context)
                == (d.tiling, d.ground, d.tin, d.ransac, d.context))

    def process(self, msg, pose: Pose | None = None) -> dict:
        """Find one message's ground (`dem.ground_source`) and add it to the DEM."""
        cfg = self.cfg
        t0 = time.perf_counter()
        prep = prepare(msg, keep_non_finite=False, max_points=cfg.input.max_points,
                       pose=pose, transform=cfg.use_odometry)
        vehicle = DetectorStage.vehicle(pose, prep.frame_id)
        if self.whole and len(prep.xyz):
            self._measure(prep.xyz)
        timings: dict = {}
        if not self.too_large:  # (the DEM given up: only the span is still wanted)
            try:
                timings = self._add(prep, vehicle)
            except DemTooLarge:
                self.too_large = True
        # the DEM's frame and time once the cloud is in (a refused one changes neither)
        self.frame_id = prep.frame_id
        self.last_stamp_ns = prep.stamp_ns
        return {"points_in": len(prep.points),
                "points_out": 0 if self.too_large else self.pipeline.last_added,
                "timings": timings, "seconds": time.perf_counter() - t0,
                "restart": "" if self.too_large else self.pipeline.last_restart}

    def _measure(self, xyz: np.ndarray) -> None:
        """The whole survey's span (`span`) with a cloud's points (N, 3) m, those the DEM
        would take: not its stray points (`far_points`), and none of a cloud the ground
        filter refuses (CloudFormatError: it lies 1e9 m off)."""
        from lidar_obstacles.core.ground import check_extent, far_points

        far = far_points(xyz)
        near = xyz[~far] if far.any() else xyz
        lo, hi = check_extent(near, self.cfg.ground.cell)
        lo, hi = np.asarray(lo, float)[:2], np.asarray(hi, float)[:2]
        self.span = ((lo, hi) if self.span is None else
                     (np.minimum(lo, self.span[0]), np.maximum(hi, self.span[1])))

    def too_large_message(self) -> str:
        """Why the whole survey's DEM was not made (`too_large`): its span and what fits."""
        assert self.span is not None
        return too_large_message(*self.span, self.cfg)

    def _add(self, prep, vehicle: np.ndarray | None) -> dict:
        """One prepared message's ground into the DEM (`dem.ground_source`); its timings."""
        cfg = self.cfg
        if cfg.dem.ground_source == "input":
            hag = _attr(prep.points, "height_above_ground")
            if hag is None:  # (a raw cloud would all go into the DEM, crowns and roofs)
                raise CloudFormatError("no height_above_ground field: dem.ground_source: "
                                       "input takes obstacle_detector's ground (remap "
                                       "points:=ground)")
            classes = _attr(prep.points, "class")
            ground = slice(None) if classes is None else classes == GROUND
            return self.pipeline.add_ground(prep.xyz[ground], stamp=prep.stamp_ns * 1e-9,
                                            vehicle_xyz=vehicle,
                                            height_above_ground=hag[ground],
                                            frame=prep.frame_id)
        return self.pipeline.process(prep.xyz, stamp=prep.stamp_ns * 1e-9,
                                     vehicle_xyz=vehicle,
                                     intensity=_attr(prep.points, "intensity"),
                                     frame=prep.frame_id)

    def add_ground(self, ground_xyz: np.ndarray, ground_hag: np.ndarray, *, stamp_ns: int,
                   frame_id: str, points_in: int, vehicle_xyz: np.ndarray | None = None
                   ) -> dict:
        """Add one message's ground, already found by a DetectorStage that
        `shares_ground_with` this stage: ground_xyz (G, 3) float64 m in `frame_id` (the
        detector's output frame), ground_hag (G,) m above the detector's ground surface.
        `points_in`: the message's finite points, which `process` would have taken (the
        stats' points in, as the node counts them: not the G ground points)."""
        t0 = time.perf_counter()
        self.frame_id = frame_id
        self.last_stamp_ns = stamp_ns
        timings = self.pipeline.add_ground(ground_xyz, stamp=stamp_ns * 1e-9,
                                           vehicle_xyz=vehicle_xyz,
                                           height_above_ground=ground_hag, frame=frame_id)
        return {"points_in": points_in, "points_out": self.pipeline.last_added,
                "timings": timings, "seconds": time.perf_counter() - t0,
                "restart": self.pipeline.last_restart}

    def grid(self) -> DemGrid:
        """The current DEM (its empty cells near new data filled first)."""
        return self.pipeline.dem.snapshot()

    def dem_outputs(self, stamp_ns: int | None = None) -> list[tuple[str, object]]:
        """`dem`, `dem_image`, `dem_info` of the current grid (empty list before any data);
        `check_stats` are measured on that grid."""
        grid = self.grid()
        self.check_stats = self.pipeline.check_accuracy(grid)
        self.coarse_warning = coarse_dem_warning(grid)
        if grid.elevation.size == 0:
            return []
        hdr = messages.header(self.last_stamp_ns if stamp_ns is None else stamp_ns,
                              self.frame_id)
        dem_cloud, image, info = messages.dem_messages(grid, hdr)
        return [("dem", dem_cloud), ("dem_image", image), ("dem_info", info)]


class SimplifierStage:
    """`cloud_simplifier`'s work on one message: the kept points, with all their fields."""

    def __init__(self, cfg: CloudSimplifierConfig) -> None:
        self.cfg = cfg
        # One stream for the whole flight: the same bag gives the same clouds, in order.
        self.rng = np.random.default_rng(cfg.simplify.seed)

    def reconfigure(self, cfg: CloudSimplifierConfig) -> None:
        if cfg.simplify.seed != self.cfg.simplify.seed:
            self.rng = np.random.default_rng(cfg.simplify.seed)
        self.cfg = cfg

    def process(self, msg, pose: Pose | None = None) -> tuple[list[tuple[str, object]], dict]:
        """Returns [("points_simplified", cloud)] and a stats dict (points in and out, r:
        the TIN raster correlation of the kept points with every clustered point, or None
        when not computed (`SimplifyResult.r`), timings). Non-finite points are never
        kept. Raises CloudFormatError for a malformed cloud."""
        from lidar_obstacles.core.simplify import simplify

        cfg = self.cfg
        t0 = time.perf_counter()
        prep = prepare(msg, keep_non_finite=False, max_points=cfg.input.max_points,
                       pose=pose, transform=cfg.use_odometry,
                       widen_xyz=cfg.odometry_xyz_type == "float64")
        points = prep.points
        result = simplify(prep.xyz, cfg=cfg.simplify,
                          return_number=_attr(points, "return_number"), rng=self.rng)
        hdr = messages.header(prep.stamp_ns, prep.frame_id)
        out = [("points_simplified", messages.cloud(select_points(points, result.keep), hdr))]
        stats = {"points_in": len(prep.points), "points_out": int(result.keep.sum()),
                 "r": result.r if np.isfinite(result.r) else None, "k": result.k,
                 "reason": result.reason,
                 "timings": dict(result.timings), "seconds": time.perf_counter() - t0}
        return out, stats
