"""Offline work on bags: simulate, las2bag, replay, play, export-dem.

Messages are built with the same rclpy message code the nodes publish with and serialized
with rclpy, so a bag written here is what a live node would have recorded, and `replay`
runs the very stage objects the nodes run.
"""
from __future__ import annotations

import calendar
import collections
import importlib
import logging
import pickle
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, NamedTuple

import numpy as np

from lidar_obstacles.config import DemBuilderConfig, ObstacleDetectorConfig
from lidar_obstacles.core.arrays import release_free_memory, reuse_freed_memory
from lidar_obstacles.errors import (BagError, CloudFormatError, ConfigError, LasError, count_reason,
                                    malformed_cloud)
from lidar_obstacles.core.pipeline import GroundStep, ObstacleResult
from lidar_obstacles.io.bags import (CRS_TOPIC, ODOMETRY, POINTCLOUD2, STRING, BagReader,
                                     BagWriter, TopicInfo, read_crs)
from lidar_obstacles.io.shared_pickle import (BlockPool, SharedPickle, attach, discard_shared,
                                              from_shared, to_shared)
from lidar_obstacles.ros import messages
from lidar_obstacles.ros.stages import (DemStage, DetectorStage, DetectorWork, Pose,
                                        coarse_xyz_warning, missing_frame_warning,
                                        moving_frame_warning, pose_of_odometry)

log = logging.getLogger(__name__)

# Topics `replay` writes and their types (the nodes' outputs, root namespace).
OUTPUT_TYPES = {
    "/ground": POINTCLOUD2, "/obstacles": POINTCLOUD2,
    "/obstacle_markers": "visualization_msgs/msg/MarkerArray",
    "/clearance": "nav_msgs/msg/OccupancyGrid", "/dem": POINTCLOUD2,
    "/dem_image": "sensor_msgs/msg/Image", "/dem_info": "nav_msgs/msg/MapMetaData",
    "/obstacle_edges": POINTCLOUD2,  # only with `features.enabled`
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}
TRANSIENT_LOCAL = {"/dem", "/dem_image", "/dem_info"}
DEFERRED = ""  # topic of a `run_stages` item that is work to do, not a message (see drain)
GPS_EPOCH_UNIX = 315_964_800  # 1980-01-06 00:00:00 UTC, GPS time 0
# UTC days (Unix seconds) from which GPS time ran ahead of UTC by one more second: the leap
# seconds since the GPS epoch (IERS; none announced after 2017)
LEAP_SECONDS_FROM = np.array([
    362_793_600, 394_329_600, 425_865_600, 489_024_000, 567_993_600, 631_152_000,
    662_688_000, 709_948_800, 741_484_800, 773_020_800, 820_454_400, 867_715_200,
    915_148_800, 1_136_073_600, 1_230_768_000, 1_341_100_800, 1_435_708_800, 1_483_228_800])
# `/diagnostics` as the nodes publish it: every second (of the bag's time, here), latency
# percentiles of the last LATENCY_WINDOW clouds, the rate over the last RATE_WINDOW.
DIAGNOSTICS_PERIOD_NS = 1_000_000_000
LATENCY_WINDOW, RATE_WINDOW = messages.LATENCY_WINDOW, messages.RATE_WINDOW
NO_POSE = "no odometry pose near the cloud's stamp"


def _serialize(msg: Any) -> bytes:
    from rclpy.serialization import serialize_message

    return serialize_message(msg)


def _progress(iterable: Iterable | None, total: int | None, desc: str, unit: str = "msg"):
    from tqdm import tqdm

    # disable=None: a bar on a terminal, silence in logs and CI.
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=None, file=sys.stderr)


# --------------------------------------------------------------------------- simulate


# A simulated flight's first cloud is stamped 2026-01-01 00:00:00 UTC, not 0: ROS reads a
# stamp of 0 as "unset" (tf2's "latest"), and a bag played with --clock at 0 leaves the
# nodes' ROS time not started.
SIM_EPOCH_NS = 1_767_225_600 * 10**9


def simulate(out: Path, *, scene: str, seed: int, duration: float, frame: str,
             rate: float = 10.0, points_per_frame: int = 50_000,
             storage: str = "mcap") -> dict:
    """Write a labelled synthetic flight: `/points` and `/odom`. Returns a summary."""
    from lidar_obstacles.core.simulate import SimSettings, simulate_flight

    settings = SimSettings(scene=scene, seed=seed, duration=duration, rate=rate,
                           points_per_frame=points_per_frame, frame=frame)
    cloud_frame = "map" if frame == "map" else "lidar"
    n_frames = int(np.ceil(duration * rate - 1e-9))  # frame k is stamped SIM_EPOCH + k / rate
    total = 0
    with BagWriter(out, storage=storage) as bag:
        bag.add_topic("/points", POINTCLOUD2)
        bag.add_topic("/odom", ODOMETRY)
        for f in _progress(simulate_flight(settings), n_frames, "simulate"):
            stamp_ns = SIM_EPOCH_NS + int(round(f.stamp * 1e9))
            # Odometry twist is in the child frame; the simulator gives it in the map frame.
            rot = Pose(stamp_ns, f.position, f.orientation, "map").rotation()
            # REP-105: the pose of the body ("lidar", the clouds' frame in sensor mode) in
            # "map"; a map-frame flight's clouds need no transform and pass unchanged.
            odom = messages.odometry(stamp_ns, "map", "lidar", f.position, f.orientation,
                                     rot.T @ f.velocity)
            bag.write("/odom", stamp_ns, _serialize(odom))
            hdr = messages.header(stamp_ns, cloud_frame)
            bag.write("/points", stamp_ns, _serialize(messages.cloud(f.points, hdr)))
            total += len(f.points)
    return {"bag": str(out), "messages": n_frames, "points": total, "scene": scene,
            "frame": frame, "frame_id": cloud_frame}


# --------------------------------------------------------------------------- las2bag


def gps_to_unix(gps_adjusted: np.ndarray) -> np.ndarray:
    """Unix time (UTC seconds) of adjusted standard GPS times (GPS seconds less 1e9): the
    GPS epoch's Unix time, less the leap seconds UTC had taken by then (18 since 2017, 16
    in 2012-2015)."""
    gps_unix = np.asarray(gps_adjusted, np.float64) + 1e9 + GPS_EPOCH_UNIX
    # (GPS runs ahead of UTC by the leaps before it: compare in GPS's own count)
    leaps = np.searchsorted(LEAP_SECONDS_FROM + np.arange(1, len(LEAP_SECONDS_FROM) + 1),
                            gps_unix, side="right")
    return gps_unix - leaps


def _las_slices(points: np.ndarray, *, has_gps: bool, slice_seconds: float,
                tile_size: float | None, strip_width: float, gps_adjusted: bool = False,
                start_ns: int = SIM_EPOCH_NS) -> tuple[list[np.ndarray], np.ndarray, str]:
    """Split a survey into messages, the way a scanner would have sent them: by GPS time
    when the file has it; else, when it holds several flight lines (`point_source_id`),
    line after line, each in strips across its own length; else in strips across the
    survey's length, or in tiles when `tile_size` is given. Returns (index arrays, stamps
    in ns, what it was sliced by: "gps_time", "flight_lines", "strips" or "tiles").

    Stamps: adjusted standard GPS time (`gps_adjusted`, the header's global encoding; or
    times beyond a week, from a writer that did not set it) is made UTC; seconds of an
    unknown GPS week, and slices without time, are counted from `start_ns` (a stamp of 0
    reads as unset in ROS)."""
    gps = points["gps_time"] if has_gps else None
    if tile_size is None and gps is not None and not np.isfinite(gps).all():
        # (its spread is NaN then, and the survey went quietly to strips)
        raise LasError(f"GPS time not finite at {int((~np.isfinite(gps)).sum())} of "
                       f"{len(gps)} points (corrupt?): slice by --tile-size instead")
    if tile_size is None and gps is not None and np.ptp(gps) > 0:
        order = np.argsort(gps, kind="stable")
        with np.errstate(invalid="ignore"):  # (a span beyond int64 slices: said below)
            key = np.floor((gps[order] - gps[order[0]]) / slice_seconds).astype(np.int64)
        cuts = np.flatnonzero(np.diff(key)) + 1
        groups = np.split(order, cuts)
        starts = np.array([gps[g[0]] for g in groups])
        if gps_adjusted or np.abs(starts).max() > 7 * 86400:
            base = gps_to_unix(starts)
        else:  # seconds of a GPS week the file does not name
            base = start_ns * 1e-9 + (starts - starts[0])
        # a Header's stamp holds int32 seconds: rclpy wrapped later ones round to negative
        # stamps, and the bag's clock (int64 ns) overflowed on absurd ones
        if base.max() >= 2**31:
            raise LasError(f"GPS time {gps.max():.10g} s gives a stamp past 2038, later than "
                           "a ROS time holds (corrupt GPS times?): slice by --tile-size "
                           "instead")
        if base.min() <= 0:  # (before the GPS epoch: written as 0, which reads as unset)
            raise LasError(f"GPS time {gps.min():.10g} s gives a stamp before 1970, earlier "
                           "than a ROS time holds (corrupt GPS times?): slice by --tile-size "
                           "instead")
        return groups, np.round(np.maximum(base, 0) * 1e9).astype(np.int64), "gps_time"
    x, y = points["x"], points["y"]
    names = points.dtype.names or ()
    lines = points["point_source_id"] if "point_source_id" in names else np.zeros(len(x), int)
    if tile_size is not None:
        ix = np.floor((x - x.min()) / tile_size).astype(np.int64)
        iy = np.floor((y - y.min()) / tile_size).astype(np.int64)
        ix = np.where(iy % 2 == 1, ix.max() - ix, ix)  # boustrophedon, as a survey is flown
        key, how = iy * (ix.max() + 1) + ix, "tiles"
    else:
        # per flight line, strips across its own longer side; lines in the file's order
        line_ids, first, line_of = np.unique(lines, return_index=True, return_inverse=True)
        rank = np.empty(len(line_ids), np.int64)
        rank[np.argsort(first, kind="stable")] = np.arange(len(line_ids))
        strip = np.empty(len(x), np.int64)
        for i in range(len(line_ids)):  # (a few lines: not a loop over points)
            member = line_of == i
            lx, ly = x[member], y[member]
            along = lx if np.ptp(lx) >= np.ptp(ly) else ly
            strip[member] = np.floor((along - along.min()) / strip_width).astype(np.int64)
        key = rank[line_of] * (int(strip.max()) + 1) + strip
        how = "flight_lines" if len(line_ids) > 1 else "strips"
    order = np.argsort(key, kind="stable")
    cuts = np.flatnonzero(np.diff(key[order])) + 1
    groups = np.split(order, cuts)
    stamps = start_ns + (np.arange(len(groups)) * slice_seconds * 1e9).astype(np.int64)
    return groups, stamps, how


def las2bag(src: Path, out: Path, *, slice_seconds: float = 0.1, tile_size: float | None = None,
            strip_width: float = 10.0, topic: str = "/points", frame_id: str = "map",
            storage: str = "mcap") -> dict:
    """Stream a LAS/LAZ survey as PointCloud2 messages.

    Coordinates are written as FLOAT64 x y z in the file's own CRS (lossless; the DEM
    exported from the bag lands on the survey's coordinates). Fields: intensity (float32),
    return_number, number_of_returns, classification (uint8), gps_time (float64, when the
    file has it) and point_id (uint32, the index in the file).
    """
    from lidar_obstacles.io.las import read_las

    if Path(out).suffix.lower() in (".las", ".laz"):  # (said before the file is read)
        raise ConfigError(f"OUT_BAG {out} is named as a LAS/LAZ file, but las2bag writes a "
                          "bag (a folder): name it without the suffix")
    las = read_las(src)
    pts = las.points
    if slice_seconds <= 0 or (tile_size is not None and tile_size <= 0) or strip_width <= 0:
        raise LasError("slice seconds, tile size and strip width must be positive")
    # Largest first, and the point padded to 8 bytes (C's struct layout): every field at a
    # multiple of its size, in every point (gps_time sat at byte 31 of a 43-byte point,
    # unaligned for a C++ reader that maps a point to a struct)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if las.has_gps_time:
        fields.append(("gps_time", "<f8"))
    fields += [("intensity", "<f4"), ("point_id", "<u4"), ("return_number", "u1"),
               ("number_of_returns", "u1"), ("classification", "u1")]
    rec = np.zeros(len(pts), dtype=np.dtype(fields, align=True))
    for name, _ in fields:
        if name != "point_id":
            rec[name] = pts[name] if name in (pts.dtype.names or ()) else 0
    rec["point_id"] = np.arange(len(pts), dtype=np.uint32)
    # a survey whose time is no date starts on the day its file was made, else on the
    # simulator's day
    start_ns = (SIM_EPOCH_NS if las.created is None else int(calendar.timegm(
        las.created.timetuple())) * 10**9)
    groups, stamps, sliced_by = _las_slices(pts, has_gps=las.has_gps_time,
                                            slice_seconds=slice_seconds, tile_size=tile_size,
                                            strip_width=strip_width,
                                            gps_adjusted=las.gps_adjusted, start_ns=start_ns)
    crs = f"EPSG:{las.epsg}" if las.epsg else las.crs_wkt
    from std_msgs.msg import String

    with BagWriter(out, storage=storage) as bag:
        bag.add_topic(topic, POINTCLOUD2)
        if crs:
            bag.add_topic(CRS_TOPIC, STRING, transient_local=True)
            bag.write(CRS_TOPIC, int(stamps[0]), _serialize(String(data=crs)))
        for idx, stamp in _progress(zip(groups, stamps), len(groups), "las2bag"):
            hdr = messages.header(int(stamp), frame_id)
            bag.write(topic, int(stamp), _serialize(messages.cloud(rec[idx], hdr)))
    return {"bag": str(out), "messages": len(groups), "points": int(len(pts)),
            "crs": crs, "sliced_by": sliced_by}


# --------------------------------------------------------------------------- replay


@dataclass
class ReplayStats:
    messages: int = 0
    rejected: int = 0
    points: int = 0
    points_out: int = 0  # the detector's obstacle points
    bag_seconds: float = 0.0
    wall_seconds: float = 0.0
    latencies: list[float] = field(default_factory=list)
    reject_reasons: dict[str, int] = field(default_factory=dict)  # by kind (reason_key)
    last_reject: str | None = None  # the latest rejected cloud's error, in full
    restarts: int = 0  # clouds that started the stream over (core.pipeline.Timeline)

    def summary(self) -> dict:
        lat = np.array(self.latencies) if self.latencies else np.zeros(1)
        return {"messages": self.messages, "rejected": self.rejected, "points": self.points,
                "bag_seconds": round(self.bag_seconds, 3),
                "wall_seconds": round(self.wall_seconds, 3),
                "real_time_factor": round(self.bag_seconds / self.wall_seconds, 2)
                if self.wall_seconds > 0 else None,
                "latency_p50_ms": round(1e3 * float(np.percentile(lat, 50)), 2),
                "latency_p95_ms": round(1e3 * float(np.percentile(lat, 95)), 2),
                "reject_reasons": self.reject_reasons, "last_reject": self.last_reject,
                "restarts": self.restarts}

    def counts(self) -> dict[str, int]:
        """The counts `obstacle_detector` would give in its diagnostics for these clouds."""
        no_pose = self.reject_reasons.get(NO_POSE, 0)
        return {"received": self.messages + self.rejected, "processed": self.messages,
                "rejected": self.rejected - no_pose, "dropped_no_pose": no_pose,
                "points_in": self.points, "points_out": self.points_out,
                "restarts": self.restarts}


def load_configs(params_file: Path | None, dem_base: DemBuilderConfig | None = None
                 ) -> tuple[ObstacleDetectorConfig, DemBuilderConfig]:
    """Both nodes' configs from a params file (or the defaults); the DEM's over `dem_base`."""
    from lidar_obstacles.config import load_params_file

    dem_base = dem_base or DemBuilderConfig()
    if params_file is None:
        return ObstacleDetectorConfig(), dem_base
    return (load_params_file(params_file, ObstacleDetectorConfig, "obstacle_detector"),
            load_params_file(params_file, DemBuilderConfig, "dem_builder", base=dem_base))


def passed_through(reader: BagReader) -> list[TopicInfo]:
    """The input topics `replay` copies into its output (`/odom`, `/survey_crs`, ...): not
    the clouds, and not topics of its own outputs, which a recorded flight may hold (its
    `/ground` or `/diagnostics`, copied, would be mixed with the new ones)."""
    return [t for t in reader.topics()
            if t.msgtype != POINTCLOUD2 and t.topic not in OUTPUT_TYPES]


def _odom_topics(reader: BagReader) -> list[str]:
    return [t.topic for t in reader.topics() if t.msgtype == ODOMETRY]


@dataclass(frozen=True)
class ObstacleWork:
    """The second half of the detector's work on one cloud (`DetectorStage.finish`),
    deferred by `run_stages`: plain data, so that it can run in another process."""

    record_ns: int
    work: DetectorWork


@dataclass(frozen=True)
class DemWork:
    """One cloud's ground, handed from the detector to the DEM in `replay`: plain data, so
    that the DEM can run in another process. ground_xyz (G, 3) float64 m in `frame_id`,
    ground_hag (G,) m above the detector's surface, vehicle_xyz (3,) m or None. Without
    ground (None): no cloud, the DEM as it stands is due (the end of the bag). points_in:
    the cloud's finite points, what `dem_builder` counts as its points in."""

    stamp_ns: int
    record_ns: int
    frame_id: str = ""
    vehicle_xyz: np.ndarray | None = None
    ground_xyz: np.ndarray | None = None
    ground_hag: np.ndarray | None = None
    reject_reasons: dict[str, int] = field(default_factory=dict)  # the clouds' so far
    points_in: int = 0


@dataclass(frozen=True)
class DetectorDiagnostics:
    """The detector's `/diagnostics`, due at a cloud (stamp_ns: its time): the rate and
    the counts of the clouds so far. `drain` makes the message, once every earlier
    cloud's work is done: their latencies and obstacle points are then known."""

    stamp_ns: int
    rate_hz: float
    reject_reasons: dict[str, int]
    counts: dict[str, int]
    dropped_before: int  # clouds dropped as of the previous diagnostics


class Done(NamedTuple):
    """Deferred work, done: the items to write, (topic, record stamp ns, CDR bytes),
    serialized where they were made because they may cross processes (rclpy messages do
    not pickle); for a cloud's obstacles, the detector's seconds on it and its obstacle
    points."""

    items: list[tuple[str, int, Any]]  # bytes, or a PickleBuffer of them crossing processes
    seconds: float | None = None
    points_out: int = 0


def finish_obstacles(stage: DetectorStage, job: ObstacleWork) -> Done:
    """The detector's messages of one cloud, and its seconds in the detector (both halves)."""
    return publish_obstacles(stage, job, *stage.classify(job.work.ground))


def publish_obstacles(stage: DetectorStage, job: ObstacleWork, result: ObstacleResult,
                      seconds: float) -> Done:
    """The messages of one classified cloud (`DetectorStage.publish`), serialized."""
    outputs, det_stats = stage.publish(job.work, result, seconds)
    return Done([("/" + name, job.record_ns, _serialize(out)) for name, out in outputs],
                det_stats["seconds"], det_stats["obstacles"])


class _BagTimer:
    """A timer on the bag's clock, as a node's ROS timer on the live one: due once every
    `period_ns` of the clouds' stamps, and at the end of the bag whatever the time. A clock
    that went back more than a period starts it again, as ROS's timers do."""

    def __init__(self, period_ns: int) -> None:
        self.period_ns = period_ns
        self.next_ns: int | None = None

    def due(self, stamp_ns: int, end: bool = False) -> bool:
        """Whether it is due at a cloud stamped `stamp_ns` (`end`: the end of the bag)."""
        if end or (self.next_ns is not None and stamp_ns >= self.next_ns):
            self.next_ns = stamp_ns + self.period_ns
            return True
        if self.next_ns is None or stamp_ns + self.period_ns < self.next_ns:
            self.next_ns = stamp_ns + self.period_ns  # (started, or started again)
        return False


class DemSchedule:
    """The DEM side of `replay`: every cloud goes into the rolling DEM; its messages are
    due at `dem.publish_rate` and `dem_builder`'s `/diagnostics` every second, on the
    bag's clock, as the node's timers would publish them. Items are (topic, record stamp
    ns, message)."""

    def __init__(self, stage: DemStage) -> None:
        self.stage = stage
        self.publish_timer = _BagTimer(int(1e9 / stage.cfg.dem.publish_rate))
        self.diagnostics_timer = _BagTimer(DIAGNOSTICS_PERIOD_NS)
        self.counts = {"processed": 0, "points_in": 0, "points_out": 0}
        self.latencies: collections.deque[float] = collections.deque(maxlen=LATENCY_WINDOW)
        self.stamps: collections.deque[float] = collections.deque(maxlen=RATE_WINDOW)
        # the clouds rejected so far (replay's, which the DEM never sees)
        self.reject_reasons: dict[str, int] = {}
        self.dropped_reported = 0  # clouds dropped as of the last diagnostics

    def _due(self, stamp_ns: int, record_ns: int, end: bool = False
             ) -> list[tuple[str, int, Any]]:
        """The DEM messages and the diagnostics due at this cloud (all of them at the end
        of the bag)."""
        items = self.outputs(stamp_ns, record_ns) if self.publish_timer.due(stamp_ns, end) else []
        if self.diagnostics_timer.due(stamp_ns, end):
            items.append(("/diagnostics", record_ns, self.diagnostics(stamp_ns)))
        return items

    def outputs(self, stamp_ns: int, record_ns: int) -> list[tuple[str, int, Any]]:
        """The DEM messages now (none before any ground)."""
        return [("/" + name, record_ns, out) for name, out in self.stage.dem_outputs(stamp_ns)]

    def diagnostics(self, stamp_ns: int):
        """`dem_builder`'s `/diagnostics` message now."""
        no_pose = self.reject_reasons.get(NO_POSE, 0)
        rejected = sum(self.reject_reasons.values())
        counts = {"received": self.counts["processed"] + rejected,
                  "processed": self.counts["processed"], "rejected": rejected - no_pose,
                  "dropped_no_pose": no_pose, "points_in": self.counts["points_in"],
                  "points_out": self.counts["points_out"]}
        msg = messages.diagnostics(messages.header(stamp_ns, ""), "dem_builder",
                                   "/dem_builder", counts, self.reject_reasons,
                                   self.latencies, messages.rate_hz(self.stamps),
                                   self.stage.check_values(),
                                   dropped_before=self.dropped_reported)
        self.dropped_reported = messages.dropped(counts)
        return msg

    def _count(self, stats: dict, stamp_ns: int) -> None:
        """One cloud into the DEM: its stage stats (points in and out, seconds)."""
        self.counts["processed"] += 1
        self.counts["points_in"] += stats["points_in"]
        self.counts["points_out"] += stats["points_out"]
        self.latencies.append(stats["seconds"])
        self.stamps.append(stamp_ns * 1e-9)

    def add_cloud(self, msg, pose: Pose | None, stamp_ns: int, record_ns: int
                  ) -> tuple[list, int]:
        """A cloud whose ground the DEM finds itself (`dem.ground_source`): the items due,
        and the points of the cloud it took (the finite ones)."""
        stats = self.stage.process(msg, pose)
        self._count(stats, stamp_ns)
        return self._due(stamp_ns, record_ns), stats["points_in"]

    def finish(self, stamp_ns: int, record_ns: int) -> list[tuple[str, int, Any]]:
        """The end of the bag: the DEM as it stands and the last diagnostics."""
        return self._due(stamp_ns, record_ns, end=True)

    def __call__(self, work: DemWork) -> Done:
        """A cloud's ground from the detector (or, without ground, the end of the bag)."""
        self.reject_reasons = work.reject_reasons
        if work.ground_xyz is None or work.ground_hag is None:
            items = self.finish(work.stamp_ns, work.record_ns)
        else:
            stats = self.stage.add_ground(work.ground_xyz, work.ground_hag,
                                          stamp_ns=work.stamp_ns, frame_id=work.frame_id,
                                          points_in=work.points_in,
                                          vehicle_xyz=work.vehicle_xyz)
            self._count(stats, work.stamp_ns)
            items = self._due(work.stamp_ns, work.record_ns)
        return Done([(topic, stamp, _serialize(msg)) for topic, stamp, msg in items])


def run_stages(reader: BagReader, *, topic: str | None, detector: DetectorStage | None,
               dem: DemStage | None, stats: ReplayStats, desc: str = "replay",
               passthrough: bool = False, skip_malformed: bool = False
               ) -> Iterator[tuple[str, int, Any]]:
    """Feed every cloud of a bag through the stages, in bag order.

    Yields (topic, stamp_ns, message-or-raw-bytes) to write, and work to do later, in
    order, as (DEFERRED, stamp_ns, work) (see `drain`): the second half of the detector
    (ObstacleWork: obstacles and the messages) and, when the DEM takes the detector's
    ground, the DEM's (DemWork). `replay` hands the obstacles and the DEM each to a
    process of its own while this one finds the next cloud's ground; the detector's
    halves and the DEM each keep their state (ground context; towers seen; the rolling
    DEM) and see the clouds in order, so the result is the same as one process's.
    Otherwise the DEM work is done here. A malformed cloud stops the run with a
    CloudFormatError naming it (:func:`malformed_cloud`); with `skip_malformed` it is
    counted and skipped, as the node drops it. Each stage's `/diagnostics` is due every
    second of the bag's time and at its end (the detector's as a DetectorDiagnostics to
    drain).
    """
    run = _StageRun(reader, topic=topic, detector=detector, dem=dem, stats=stats, desc=desc,
                    passthrough=passthrough, skip_malformed=skip_malformed)
    try:
        for record in reader.records(run.wanted):
            if record.topic in run.odom:
                run.add_pose(record)
            if record.topic == run.cloud_topic:
                yield from run.cloud(record)
            elif record.topic in run.passed:
                yield from run.copy(record)
        yield from run.end()
    finally:
        run.close()


class _StageRun:
    """One run of `run_stages`: the stages' setup for the bag, and what it keeps from one
    cloud to the next (the poses, the detector's diagnostics timer, the warnings given, the
    bag's span)."""

    def __init__(self, reader: BagReader, *, topic: str | None, detector: DetectorStage | None,
                 dem: DemStage | None, stats: ReplayStats, desc: str, passthrough: bool,
                 skip_malformed: bool) -> None:
        self.reader, self.detector, self.stats = reader, detector, stats
        self.desc, self.skip_malformed = desc, skip_malformed
        self.cloud_topic = reader.pointcloud_topic(topic)
        self.odom = _odom_topics(reader)
        self.use_odom = any(s is not None and s.cfg.use_odometry for s in (detector, dem))
        self.passed = {t.topic for t in passed_through(reader)} if passthrough else set()
        self.wanted = [self.cloud_topic, *self.odom, *sorted(self.passed.difference(self.odom))]
        from lidar_obstacles.core.pipeline import ObstacleDetector  # noqa: F401 (fail early)
        from lidar_obstacles.ros.node_base import PoseBuffer

        self.poses = PoseBuffer()
        # the same ground filter twice on every cloud is wasted: the DEM takes the detector's
        self.share_ground = (detector is not None and dem is not None
                             and dem.shares_ground_with(detector.cfg))
        self.max_age = (detector or dem).cfg.odometry_max_age  # type: ignore[union-attr]
        self.schedule = DemSchedule(dem) if dem is not None and not self.share_ground else None
        if self.schedule is not None:
            self.schedule.reject_reasons = stats.reject_reasons  # (the same clouds reach both)
        self.stamps: collections.deque[float] = collections.deque(maxlen=RATE_WINDOW)
        self.diagnostics_timer = _BagTimer(DIAGNOSTICS_PERIOD_NS)  # the detector's
        self.dropped_reported = 0  # clouds dropped as of the detector's last diagnostics
        # the times the bag spans: they may go back (its duration came out negative)
        self.lo_ns: int | None = None
        self.hi_ns: int | None = None
        self.last_ns: int | None = None  # the last cloud's header stamp
        self.warned: set[int | str] = set()  # (each warning once)
        self.bar = _progress(None, reader.count([self.cloud_topic]), desc)
        self.seen = 0  # clouds read (the bar counts nothing when it is off)
        self.t_start = time.perf_counter()

    def add_pose(self, record) -> None:
        """An odometry record into the poses (one that cannot be used: left out, said once)."""
        problem = self.poses.add(pose_of_odometry(self.reader.deserialize(record)))
        if problem is not None:
            self._warn_once("odometry", f"ignored {problem} (and any more such)")

    def copy(self, record) -> Iterator[tuple[str, int, Any]]:
        """A record of a topic passed through, as it is (or rebuilt: `cdr_of_record`)."""
        raw = cdr_of_record(self.reader, record)
        if raw is not None:
            yield record.topic, record.stamp_ns, raw

    def cloud(self, record) -> Iterator[tuple[str, int, Any]]:
        """One cloud through the stages: its work deferred and the DEM's items due, then
        the detector's diagnostics if due. A cloud without a pose, or malformed (with
        `skip_malformed`), is counted as rejected and only the diagnostics follow."""
        self.bar.update(1)
        self.seen += 1
        try:
            msg = self.reader.deserialize_cloud(record)
        except CloudFormatError as exc:  # (no header: the record's time stands for it)
            yield from self._malformed(exc, record.stamp_ns, record.stamp_ns)
            return
        stamp_ns = messages.stamp_ns_of(msg.header)
        self._note_stamps(record.stamp_ns, stamp_ns)
        pose = self.poses.nearest(stamp_ns, self.max_age)
        self._warn_about_cloud(msg, pose)
        if self.use_odom and pose is None:
            self.stats.rejected += 1
            self.stats.reject_reasons[NO_POSE] = self.stats.reject_reasons.get(NO_POSE, 0) + 1
            yield from self._detector_diagnostics(stamp_ns, record.stamp_ns)
            return
        t0 = time.perf_counter()
        try:
            deferred, dem_items, n_points = self._start(msg, pose, stamp_ns, record.stamp_ns)
        except CloudFormatError as exc:
            yield from self._malformed(exc, stamp_ns, record.stamp_ns)
            return
        self._note_restart(deferred)
        self._count(n_points, t0)
        for job in deferred:
            yield DEFERRED, record.stamp_ns, job
        yield from dem_items
        yield from self._detector_diagnostics(stamp_ns, record.stamp_ns)

    def _malformed(self, exc: CloudFormatError, stamp_ns: int, record_ns: int
                   ) -> Iterator[tuple[str, int, Any]]:
        """A malformed cloud (stamp_ns its header's stamp): the run stopped with an error
        naming it, or, with `skip_malformed`, counted as rejected, and only the detector's
        diagnostics follow if due."""
        if not self.skip_malformed:
            raise malformed_cloud(self.seen, self.cloud_topic, stamp_ns, exc) from None
        self.stats.rejected += 1
        count_reason(self.stats.reject_reasons, str(exc))
        self.stats.last_reject = str(exc)
        yield from self._detector_diagnostics(stamp_ns, record_ns)

    def _note_stamps(self, record_ns: int, stamp_ns: int) -> None:
        """A cloud's times: the recording's span, by the bag's own times (a header stamp
        may be unset, 0, which made a 5-cloud bag 70 years long and the replay 2e9 x real
        time), and its header stamp, for the rate and the end of the bag."""
        self.lo_ns = record_ns if self.lo_ns is None else min(self.lo_ns, record_ns)
        self.hi_ns = record_ns if self.hi_ns is None else max(self.hi_ns, record_ns)
        self.last_ns = stamp_ns
        self.stamps.append(stamp_ns * 1e-9)

    def _warn_about_cloud(self, msg, pose: Pose | None) -> None:
        """The warnings a cloud may call for (a moving frame without odometry, coordinates
        too coarse for the detector, no frame), each once."""
        for kind, warning in enumerate((
                moving_frame_warning(msg.header.frame_id, pose, self.use_odom),
                self.detector and coarse_xyz_warning(msg, pose, self.detector.cfg),
                missing_frame_warning(msg.header.frame_id))):
            if warning:
                self._warn_once(kind, warning)

    def _warn_once(self, key: int | str, text: str) -> None:
        """`text` on stderr, above the progress bar, unless the warning `key` was given."""
        if key not in self.warned:
            self.bar.write(f"{self.desc}: warning: {text}", file=sys.stderr)
            self.warned.add(key)

    def _start(self, msg, pose: Pose | None, stamp_ns: int, record_ns: int
               ) -> tuple[list, list, int]:
        """The stages' work on a cloud now: the detector's first half (its second, and the
        DEM's on its ground, deferred) and the DEM on its own ground. Returns the deferred
        work, the DEM's items due and the cloud's points as the nodes count them: its
        finite ones (width x height counted an organized cloud's NaN padding, its missing
        returns). CloudFormatError for a cloud that cannot be used."""
        deferred: list = []
        n_points = 0
        if self.detector is not None:
            work = self.detector.start(msg, pose)
            n_points = int(np.count_nonzero(work.finite))
            deferred.append(ObstacleWork(record_ns, work))
            if self.share_ground:
                # the detector's ground is all the DEM needs: nothing to parse
                deferred.append(DemWork(
                    work.stamp_ns, record_ns, work.frame_id, work.ground.vehicle_xyz,
                    *work.dem_ground(), dict(self.stats.reject_reasons), points_in=n_points))
        dem_items: list = []
        if self.schedule is not None:
            dem_items, dem_points = self.schedule.add_cloud(msg, pose, stamp_ns, record_ns)
            n_points = n_points if self.detector is not None else dem_points
        return deferred, dem_items, n_points

    def _note_restart(self, deferred: list) -> None:
        """A cloud that started the stream afresh (forgetting what was remembered): counted,
        and said once."""
        restart = (deferred[0].work.ground.restart if self.detector is not None else
                   self.schedule.stage.pipeline.last_restart if self.schedule is not None
                   else "")
        if restart:
            self.stats.restarts += 1
            self._warn_once("restart", f"cloud {self.seen} started afresh, what was "
                            f"remembered forgotten: {restart} (and any more such; "
                            "counted in the summary's restarts)")

    def _count(self, n_points: int, t0: float) -> None:
        """A cloud processed (its work begun at perf_counter `t0`) into the stats."""
        if self.detector is None:  # (the detector's time is counted when its work is done)
            self.stats.latencies.append(time.perf_counter() - t0)
        self.stats.messages += 1
        if self.stats.messages % 100 == 0:
            release_free_memory()  # as the nodes do every 10 s
        self.stats.points += n_points

    def _detector_diagnostics(self, stamp_ns: int, record_ns: int, end: bool = False
                              ) -> list[tuple[str, int, Any]]:
        """The detector's `/diagnostics` if due at this cloud (every second of the bag's
        time, and at its end), as a DetectorDiagnostics for `drain` to make once every
        earlier cloud's work is done."""
        if self.detector is None or not self.diagnostics_timer.due(stamp_ns, end):
            return []
        counts = self.stats.counts()
        due = DetectorDiagnostics(stamp_ns, messages.rate_hz(self.stamps),
                                  dict(self.stats.reject_reasons), counts,
                                  self.dropped_reported)
        self.dropped_reported = messages.dropped(counts)
        return [(DEFERRED, record_ns, due)]

    def end(self) -> Iterator[tuple[str, int, Any]]:
        """The end of the bag (if it had a cloud): the detector's last diagnostics, and the
        DEM as it stands (deferred when it takes the detector's ground)."""
        if self.last_ns is None:
            return
        yield from self._detector_diagnostics(self.last_ns, self.last_ns, end=True)
        if self.share_ground:
            yield DEFERRED, self.last_ns, DemWork(
                self.last_ns, self.last_ns, reject_reasons=dict(self.stats.reject_reasons))
        elif self.schedule is not None:
            yield from self.schedule.finish(self.last_ns, self.last_ns)

    def close(self) -> None:
        """The progress bar closed; the run's wall time and the bag's span into the stats."""
        self.bar.close()
        self.stats.wall_seconds = time.perf_counter() - self.t_start
        if self.lo_ns is not None and self.hi_ns is not None:
            # A bag of n messages at rate r covers n periods, not n-1.
            period = ((self.hi_ns - self.lo_ns) / max(self.stats.messages - 1, 1)
                      if self.stats.messages > 1 else 1e8)
            self.stats.bag_seconds = (self.hi_ns - self.lo_ns + period) * 1e-9


def drain(item: tuple[str, int, Any], *, detector: DetectorStage | None = None,
          schedule: DemSchedule | None = None, stats: ReplayStats | None = None
          ) -> list[tuple[str, int, Any]]:
    """The items to write for one item of `run_stages`. Deferred work is done now, by
    `detector` (ObstacleWork) or `schedule` (DemWork), or, when it was handed to a worker
    process, its result awaited (a Future). The detector's seconds and obstacle points go
    to `stats`, from which its diagnostics are made."""
    name, stamp_ns, payload = item
    if name != DEFERRED:
        return [item]
    if isinstance(payload, DetectorDiagnostics):
        return [("/diagnostics", stamp_ns, _detector_diagnostics(payload, stats))]
    if isinstance(payload, ObstacleWork):
        if detector is None:
            raise ValueError("deferred obstacle work needs a DetectorStage to do it")
        done = finish_obstacles(detector, payload)
    elif isinstance(payload, DemWork):
        if schedule is None:
            raise ValueError("deferred DEM work needs a DemSchedule to do it")
        done = schedule(payload)
    else:
        done = payload.result()  # a Future of a worker process
    if done.seconds is not None and stats is not None:
        stats.latencies.append(done.seconds)
        stats.points_out += done.points_out
    return done.items


def _detector_diagnostics(due: DetectorDiagnostics, stats: ReplayStats | None):
    """`obstacle_detector`'s `/diagnostics` message at `due`: its counts then, with the
    latencies and obstacle points of the clouds before it, all drained by now."""
    latencies = stats.latencies[-LATENCY_WINDOW:] if stats is not None else []
    counts = {**due.counts, "points_out": stats.points_out if stats is not None else 0}
    return messages.diagnostics(messages.header(due.stamp_ns, ""), "obstacle_detector",
                                "/obstacle_detector", counts, due.reject_reasons, latencies,
                                due.rate_hz, dropped_before=due.dropped_before)


# The worker processes of `replay`: one for the detector's second half, one for the DEM,
# each with its own state, doing its work in the order it was given.
_WORKER_DETECTOR: DetectorStage | None = None
_WORKER_SCHEDULE: DemSchedule | None = None
_WORKER_DONE = 0


def _start_worker(det_cfg: ObstacleDetectorConfig | None, dem_cfg: DemBuilderConfig | None,
                  parent_pid: int) -> None:
    import ctypes
    import ctypes.util
    import os
    import signal

    from lidar_obstacles.core.arrays import single_threaded_blas

    global _WORKER_DETECTOR, _WORKER_SCHEDULE
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # (not the parent's handler, inherited)
    # A parent killed outright (kill -9, the OOM killer) cannot stop its workers, and a
    # fork's inherited pipe ends never tell them: they waited for work for good. On Linux
    # they get SIGTERM when it dies (PR_SET_PDEATHSIG); elsewhere they stay.
    try:
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").prctl(1, signal.SIGTERM)
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent_pid:  # it died before that was set
        os._exit(0)
    single_threaded_blas()
    _WORKER_DETECTOR = DetectorStage(det_cfg) if det_cfg is not None else None
    _WORKER_SCHEDULE = DemSchedule(DemStage(dem_cfg)) if dem_cfg is not None else None


def _work_in_worker(shared_job: SharedPickle) -> SharedPickle:
    """A worker's job, and its result, through shared memory: a cloud's GroundStep is
    classified into (ObstacleResult, seconds); DemWork is done into a `Done`, its CDR
    bytes out of band like the job's arrays. The result goes into the job's block when
    it fits (the job was read out of it): the caller's pool takes the block back."""
    global _WORKER_DONE
    _WORKER_DONE += 1
    if _WORKER_DONE % 100 == 0:
        release_free_memory()  # as the nodes do every 10 s
    job = from_shared(shared_job)
    into = attach(shared_job.block) if shared_job.kept and shared_job.block else None
    if isinstance(job, GroundStep):
        if _WORKER_DETECTOR is None:
            raise RuntimeError("a cloud's obstacles sent to a worker started without them")
        return to_shared(_WORKER_DETECTOR.classify(job), into=into)
    if _WORKER_SCHEDULE is None:
        raise RuntimeError("DEM work sent to a worker started without a DEM")
    done = _WORKER_SCHEDULE(job)
    return to_shared(done._replace(items=[(t, ns, pickle.PickleBuffer(raw))
                                          for t, ns, raw in done.items]), into=into)


class _Later:
    """A worker's Future of one job's result, which comes through shared memory. Until
    the result is taken, `discard` frees whichever block of its own is still waiting: the
    job's, if the worker never started it, or the result's (`pool`'s blocks are left to
    the pool). Once the result is read, the job's block goes back to `pool`."""

    def __init__(self, future, job: SharedPickle, pool: BlockPool) -> None:
        self._future, self._job, self._pool = future, job, pool
        self.taken = False

    def _take(self, timeout: float | None) -> Any:
        self.taken = True
        result = from_shared(self._future.result(timeout), pool=self._pool)
        if self._job.kept and self._job.block is not None:
            self._pool.give(self._job.block)
        return result

    def discard(self) -> None:
        if self.taken:
            return
        self.taken = True
        if self._future.cancelled() or not self._future.done():
            discard_shared(self._job)
        elif self._future.exception() is None:
            discard_shared(self._future.result())


class _ObstaclesLater(_Later):
    """A cloud's obstacles; `result` makes its messages (a `Done`) in this process, from
    the points it kept: they need not cross to the worker and back, and the worker, the
    busiest process, is spared ~8 ms of messages per cloud."""

    def __init__(self, future, job: SharedPickle, pool: BlockPool, stage: DetectorStage,
                 work: ObstacleWork) -> None:
        super().__init__(future, job, pool)
        self._stage, self._work = stage, work

    def result(self, timeout: float | None = None) -> Done:
        return publish_obstacles(self._stage, self._work, *self._take(timeout))


class _DemLater(_Later):
    """A DEM job's `Done`."""

    def result(self, timeout: float | None = None) -> Done:
        done = self._take(timeout)
        return done._replace(items=[(t, ns, bytes(raw)) for t, ns, raw in done.items])


class _WorkerProcesses:
    """`replay`'s deferred work in two more processes: the obstacles in one, the DEM in
    the other, while this process reads the bag, finds the ground and makes the
    detector's messages (threads would share one interpreter lock). One worker each, so
    each does its work in the order given; the results are futures, awaited by the
    writer in bag order. Work and results go through shared memory (`to_shared`).

    Forked, not spawned: a spawned child re-imports the caller's main module, which runs an
    unguarded script a second time. Both are forked at once, before the writer thread and
    the progress bar exist, so that each fork copies a process with no other threads."""

    def __init__(self, det_cfg: ObstacleDetectorConfig, dem_cfg: DemBuilderConfig | None
                 ) -> None:
        import multiprocessing
        import os
        from concurrent.futures import ProcessPoolExecutor
        from multiprocessing import resource_tracker

        from lidar_obstacles.core.arrays import single_threaded_blas

        ctx = multiprocessing.get_context("fork")
        # BLAS on one thread here, before the forks (the libraries the stages loaded since
        # the caller's own call): the workers then find it so and need not set it, which
        # in a forked child starts OpenBLAS's threads (~0.2 s of CPU per worker)
        single_threaded_blas()
        # one tracker of the shared memory blocks for all three processes: each block is
        # made in one process and unlinked in another
        resource_tracker.ensure_running()
        self._pools = {kind: ProcessPoolExecutor(max_workers=1, mp_context=ctx,
                                                 initializer=_start_worker,
                                                 initargs=(*args, os.getpid()))
                       for kind, args in (("obstacles", (det_cfg, None)),
                                          ("dem", (None, dem_cfg))) if args != (None, None)}
        for pool in self._pools.values():
            pool.submit(int)  # the forks happen now, before any other thread exists
        self._pending: collections.deque[_Later] = collections.deque()
        self._blocks = BlockPool()  # the jobs' blocks, which carry their results back

    def submit(self, job: ObstacleWork | DemWork, detector: DetectorStage | None = None
               ) -> _ObstaclesLater | _DemLater:
        """A Future of the job's `Done`; `detector` makes the obstacle messages here."""
        later: _Later
        if isinstance(job, ObstacleWork):
            if detector is None:
                raise ValueError("obstacle work needs this process's DetectorStage")
            shared = to_shared(job.work.ground, pool=self._blocks)
            later = _ObstaclesLater(self._pools["obstacles"].submit(_work_in_worker, shared),
                                    shared, self._blocks, detector, job)
        else:
            shared = to_shared(job, pool=self._blocks)
            later = _DemLater(self._pools["dem"].submit(_work_in_worker, shared), shared,
                              self._blocks)
        while self._pending and self._pending[0].taken:
            self._pending.popleft()
        self._pending.append(later)
        return later

    def close(self) -> None:
        """Stop the workers; free the shared memory of work and results never taken."""
        for pool in self._pools.values():
            pool.shutdown(wait=True, cancel_futures=True)
        for later in self._pending:
            later.discard()
        self._pending.clear()
        self._blocks.close()


class _Discarded(Exception):
    """The output bag is not wanted: replay was stopped, or no cloud was processed."""


class _BackgroundWriter:
    """Opens, writes and closes the output bag on one thread, in order, awaiting the worker
    processes' results where they come, while the caller finds the next cloud's ground.
    Every bag operation is on that thread because sqlite3 lets only the thread that opened
    a database use it. The queue is short, so memory stays bounded; an error on the thread
    (opening the bag included) is raised in the caller."""

    def __init__(self, out: Path, storage: str, topics: list[tuple[str, str, bool]],
                 stats: ReplayStats, depth: int = 8) -> None:
        import queue
        import threading

        self._out, self._storage, self._topics = out, storage, topics
        self._stats = stats
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._keep: bool | None = None  # set by close: finish the bag, or drop it
        self._opened = threading.Event()
        self._thread = threading.Thread(target=self._run, name="replay-writer", daemon=True)
        self._thread.start()
        try:
            self._opened.wait()  # so that a bad output is said before any work
        except BaseException:  # (Ctrl-C meanwhile)
            self.close(keep=False)
            raise
        if self._error is not None:
            self.close(keep=False)  # (raises it)

    def _run(self) -> None:
        try:
            with BagWriter(self._out, storage=self._storage) as bag:
                for name, msgtype, transient_local in self._topics:
                    bag.add_topic(name, msgtype, transient_local=transient_local)
                self._opened.set()
                while (item := self._queue.get()) is not None:
                    if self._error is None and self._keep is not False:
                        self._write(bag, item)
                # (an item skipped here is freed by _WorkerProcesses.close)
                if self._error is not None:
                    raise self._error
                if not self._keep:
                    raise _Discarded()  # BagWriter removes the partial bag
        except _Discarded:
            pass
        except BaseException as exc:  # noqa: BLE001 - handed to the caller
            self._error = self._error or exc
        finally:
            self._opened.set()

    def _write(self, bag: BagWriter, item: tuple[str, int, Any]) -> None:
        try:
            for name, stamp_ns, msg in drain(item, stats=self._stats):
                bag.write(name, stamp_ns, msg if isinstance(msg, bytes) else _serialize(msg))
        except BaseException as exc:  # noqa: BLE001 - the rest is skipped, then raised
            self._error = exc

    def put(self, item: tuple[str, int, Any]) -> None:
        if self._error is not None:
            raise self._error
        self._queue.put(item)

    def close(self, *, keep: bool) -> None:
        """Once everything queued is taken, finish the bag under its name (keep) or remove
        it; raise the thread's error, if any."""
        self._keep = keep
        self._queue.put(None)
        self._thread.join()
        if self._error is not None:
            raise self._error


def replay(src: Path, out: Path, *, topic: str | None = None, params_file: Path | None = None,
           storage: str = "mcap", with_dem: bool = True, skip_malformed: bool = False) -> dict:
    """Run both nodes' stages over a bag and write what they would publish. A malformed
    cloud stops it (CloudFormatError, no output left), unless `skip_malformed`: then it is
    counted in the summary's `rejected` and `reject_reasons`, as the node drops it."""
    # As the CLI does, and here too for callers from Python (benchmarks, scripts): without
    # it the main process faulted every cloud's arrays in again, 38 -> 28 ms of CPU per
    # 50 000-point message (half of it system time). The forked workers inherit it.
    reuse_freed_memory()
    det_cfg, dem_cfg = load_configs(params_file)
    stats = ReplayStats()
    detector = DetectorStage(det_cfg)
    dem = DemStage(dem_cfg) if with_dem else None
    topics = [(name, msgtype, name in TRANSIENT_LOCAL) for name, msgtype in OUTPUT_TYPES.items()
              if (name != "/obstacle_edges" or det_cfg.features.enabled)
              and (with_dem or name not in TRANSIENT_LOCAL)]
    t_start = time.perf_counter()
    with BagReader(src) as reader:
        cloud_topic = reader.pointcloud_topic(topic)
        topics += [(t.topic, t.msgtype, t.topic == CRS_TOPIC) for t in passed_through(reader)]
        # (when the DEM finds its own ground, run_stages does its work here)
        workers = _WorkerProcesses(det_cfg, dem_cfg if dem is not None
                                   and dem.shares_ground_with(det_cfg) else None)
        try:
            writer = _BackgroundWriter(out, storage, topics, stats)
            keep = False
            try:
                for name, stamp_ns, payload in run_stages(
                        reader, topic=topic, detector=detector, dem=dem, stats=stats,
                        passthrough=True, skip_malformed=skip_malformed):
                    if name == DEFERRED and not isinstance(payload, DetectorDiagnostics):
                        payload = workers.submit(payload, detector)
                    writer.put((name, stamp_ns, payload))
                keep = stats.messages > 0
            finally:
                writer.close(keep=keep)
        finally:
            workers.close()
    stats.wall_seconds = time.perf_counter() - t_start  # the writing included
    if stats.messages == 0:
        raise BagError(f"no cloud of {src} could be processed "
                       f"({stats.rejected} rejected: {stats.reject_reasons})")
    return {"bag": str(out), "topic": cloud_topic, **stats.summary()}


def cdr_of_record(reader: BagReader, record) -> bytes | None:
    """CDR bytes of a record to pass on. ROS 2 records go as they are; ROS 1 clouds and
    odometry are rebuilt as ROS 2 messages; other ROS 1 types are not carried (None)."""
    if not record.ros1:
        return record.raw
    if record.msgtype not in (POINTCLOUD2, ODOMETRY):
        return None  # (and never deserialized: a String or a tf message has no header)
    from lidar_obstacles.io.pointcloud2 import read_points

    msg = reader.deserialize(record)
    stamp_ns = messages.stamp_ns_of(msg.header)
    if record.msgtype == POINTCLOUD2:
        return _serialize(messages.cloud(read_points(msg, keep_non_finite=True),
                                         messages.header(stamp_ns, msg.header.frame_id)))
    if record.msgtype == ODOMETRY:
        pose = pose_of_odometry(msg)
        return _serialize(messages.odometry(stamp_ns, pose.frame_id, msg.child_frame_id,
                                            pose.position, pose.orientation))
    return None


# --------------------------------------------------------------------------- export-dem


def crop_to_data(grid):
    """The grid cut to the rows and columns that hold measured cells (the rolling grid grows
    in blocks and fills a margin around the data; the survey's DEM stops at the survey)."""
    import dataclasses

    rows = np.flatnonzero((grid.count > 0).any(axis=1))
    cols = np.flatnonzero((grid.count > 0).any(axis=0))
    r, c = slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)
    origin = np.asarray(grid.origin, float) + np.array([cols[0], rows[0]]) * grid.resolution
    return dataclasses.replace(grid, elevation=grid.elevation[r, c],
                               interpolated=grid.interpolated[r, c], count=grid.count[r, c],
                               origin=origin)


def export_dem(src: Path, out: Path, *, topic: str | None = None,
               params_file: Path | None = None, crs: str | None = None,
               skip_malformed: bool = False) -> dict:
    """Build the DEM of a whole bag offline; write a GeoTIFF and a hillshade PNG beside it.
    A malformed cloud stops it unless `skip_malformed` (as `replay`)."""
    from lidar_obstacles.config import parse_crs, replace
    from lidar_obstacles.io.atomic import PNG, TIFF, check_replaceable
    from lidar_obstacles.io.geotiff import write_geotiff, write_hillshade_png

    png = out.with_name(out.stem + "_hillshade.png")
    if crs is not None:  # said before the work, naming the option the user gave
        try:
            parse_crs(crs)
        except ConfigError as exc:
            raise ConfigError(str(exc).replace("parameter 'export.crs'", "--crs")) from None
    check_replaceable(out, TIFF)  # said before the work, and before either is written
    check_replaceable(png, PNG)
    # offline the DEM covers the whole survey, unless the params file sets `dem.extent`
    _, dem_cfg = load_configs(params_file, replace(DemBuilderConfig(), {"dem.extent": 0.0}))
    if dem_cfg.dem.extent > 0:  # (the shipped config/dem_builder.yaml sets the live node's)
        log.warning("export-dem: warning: dem.extent is %g m in %s: the DEM keeps only that "
                    "square around the last position; set it to 0 for the whole survey",
                    dem_cfg.dem.extent, params_file)
    stats = ReplayStats()
    stage = DemStage(dem_cfg, whole=True)
    with BagReader(src) as reader:
        bag_crs = read_crs(reader)
        for _ in run_stages(reader, topic=topic, detector=None, dem=stage, stats=stats,
                            desc="export-dem", skip_malformed=skip_malformed):
            pass
    if stage.too_large:  # (over dem.max_cells, the rest of the bag was only measured)
        raise ConfigError(stage.too_large_message())
    if stats.messages == 0:  # (said as replay says it, not as "no ground")
        raise BagError(f"no cloud of {src} could be processed "
                       f"({stats.rejected} rejected: {stats.reject_reasons})")
    grid = stage.grid()
    if not np.isfinite(grid.elevation).any():
        raise BagError(f"no ground found in {src}: cannot build a DEM")
    grid = crop_to_data(grid)
    crs_text = crs or dem_cfg.export.crs or bag_crs
    try:
        epsg, wkt = parse_crs(crs_text)
    except ConfigError as exc:
        if crs_text != bag_crs:
            raise
        # The survey's own CRS, which the DEM cannot be in: the DEM is still wanted
        log.warning("export-dem: warning: the survey's CRS (%s in the bag) is not written: "
                    "%s; --crs gives one", CRS_TOPIC,
                    str(exc).removeprefix("parameter 'export.crs': "))
        epsg, wkt, crs_text = None, "", ""
    write_geotiff(out, grid, crs_epsg=epsg, crs_wkt=wkt)
    write_hillshade_png(png, grid)
    return {"geotiff": str(out), "hillshade": str(png), "crs": crs_text,
            "rows": int(grid.elevation.shape[0]), "cols": int(grid.elevation.shape[1]),
            "resolution": float(grid.resolution), **stats.summary()}


# --------------------------------------------------------------------------- play


def _msg_class(msgtype: str):
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def _subscriptions_settled(node, topics: list[str], *, quiet_s: float, timeout_s: float) -> bool:
    """Wait until the subscriptions to `topics` exist and have not changed for `quiet_s`.

    A node with `input.reliability: auto` sees a new reliable publisher, then re-creates its
    subscription as reliable at its next once-a-second check; clouds sent before that go
    best effort (lossy for large clouds) or are lost in the switch. `quiet_s` is longer than
    that check. While a subscription is best effort it may still be such a node's, which
    has not seen this publisher yet (discovery on a loaded machine: a CI run lost 4 of 30
    clouds in a switch that came after 2.5 s), so the wait is 2.5 x longer then. False when
    nothing settled within `timeout_s` (no subscriber, say).
    """
    from rclpy.qos import ReliabilityPolicy

    deadline = time.monotonic() + timeout_s
    seen: tuple | None = None
    since = time.monotonic()
    while time.monotonic() < deadline:
        now = tuple(sorted((t, i.node_namespace, i.node_name, int(i.qos_profile.reliability))
                           for t in topics for i in node.get_subscriptions_info_by_topic(t)))
        lossy = any(r == int(ReliabilityPolicy.BEST_EFFORT) for *_, r in now)
        if now != seen:
            seen, since = now, time.monotonic()
        elif now and time.monotonic() - since >= quiet_s * (2.5 if lossy else 1.0):
            return True
        time.sleep(0.05)
    return False


class _BagClock:
    """`/clock` of `play --clock`: the bag's time (its records' receive time, as `ros2 bag
    play --clock` gives), every 1/hz s of wall time from a thread and at each message
    played, so that nodes with `use_sim_time` run on it.

    It holds `start_ns` until a pass starts (`run`), then runs at `rate` from the pass's
    first record, never past the record that is due next (`until_ns`): a message played
    late holds the clock back, so no node's time passes a message not yet sent. A new
    pass (`--loop`) jumps back to its first record, as rosbag2's does.
    """

    def __init__(self, node, hz: float, rate: float, start_ns: int) -> None:
        import threading

        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock

        self._clock_msg = Clock
        # Absolute, whatever the player's namespace, and best effort with depth 1: what
        # rclpy's and rclcpp's TimeSource subscribe with (rclcpp::ClockQoS, rosbag2's offer)
        self._pub = node.create_publisher(
            Clock, "/clock", QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        self._rate = rate
        self._lock = threading.Lock()
        self._base_ns = self._until_ns = start_ns
        self._base_wall: float | None = None  # None: held at _base_ns
        self._stop = threading.Event()
        self.tick()
        self._thread = threading.Thread(target=self._run, args=(1.0 / hz,), daemon=True,
                                        name="play-clock")
        self._thread.start()

    def _run(self, period: float) -> None:
        while not self._stop.wait(period):
            self.tick()

    def run(self, t0_wall: float, t0_ns: int, *, until_ns: int) -> None:
        """The pass that started at monotonic `t0_wall` with its record at `t0_ns`; the
        clock goes no further than `until_ns` (the next record's)."""
        with self._lock:
            jumped = (self._base_wall, self._base_ns) != (t0_wall, t0_ns)
            self._base_wall, self._base_ns, self._until_ns = t0_wall, t0_ns, until_ns
        if jumped:
            self.tick()

    def tick(self) -> None:
        """Publish the bag's time now."""
        with self._lock:
            now_ns = self._base_ns
            if self._base_wall is not None:
                ran = (time.monotonic() - self._base_wall) * self._rate * 1e9
                # (rounded: at a record's due time, exactly its stamp, not 1 ns short)
                now_ns = min(self._base_ns + round(ran), self._until_ns)
            self._pub.publish(self._clock_msg(clock=messages.header(now_ns, "").stamp))

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


def _sim_time_subscribers(node, topics: list[str]) -> list[str]:
    """The nodes that subscribe to one of `topics` and to `/clock`: nodes with
    `use_sim_time` (rclpy's and rclcpp's TimeSource subscribe it on the node itself). A
    look at the graph, no request to the nodes."""
    clocked = {(i.node_namespace, i.node_name)
               for i in node.get_subscriptions_info_by_topic("/clock")}
    return sorted({f"{i.node_namespace.rstrip('/')}/{i.node_name}" for t in topics
                   for i in node.get_subscriptions_info_by_topic(t)
                   if (i.node_namespace, i.node_name) in clocked})


def _elsewhere_hint(node, played: dict[str, str]) -> str:
    """A hint naming the subscribed topics that end like a played one (`played`: bag topic
    -> the name it is published on) but are not it: a node under /uav1 while play publishes
    /points. With the namespace that would reach them; "" if there are none."""
    found: dict[str, str | None] = {}  # topic -> the namespace that reaches it, if one does
    for graph_name, _ in node.get_topic_names_and_types():
        if graph_name in played.values() or not node.count_subscribers(graph_name):
            continue
        for bag_topic in played:
            if graph_name.endswith(bag_topic):  # (bag topics are absolute: "/" included)
                found[graph_name] = graph_name[:-len(bag_topic)]
            elif graph_name.rsplit("/", 1)[-1] == bag_topic.rsplit("/", 1)[-1]:
                found.setdefault(graph_name, None)
    if not found:
        return ""
    ways = [f"--namespace {ns}" if ns else "no --namespace"
            for ns in sorted({ns for ns in found.values() if ns is not None})]
    how = f" ({' or '.join(ways)}?)" if ways else ""
    return f"; subscribed elsewhere: {', '.join(sorted(found))}{how}"


def play(src: Path, *, rate: float = 1.0, loop: bool = False, topics: list[str] | None = None,
         namespace: str = "", settle_s: float = 2.5, wait_s: float = 15.0,
         clock_hz: float | None = None) -> dict:
    """Publish a bag into the live ROS graph at its recorded rate (scaled by `rate`).

    Bag topics are published relative to `namespace` (``/points`` -> ``/uav1/points``).
    Playing starts once the subscribers are matched and unchanged for `settle_s`, or after
    `wait_s` if none come. Ctrl-C (KeyboardInterrupt) stops it wherever it is, and is
    raised again with the count of messages published. With `clock_hz`, `/clock` carries
    the bag's time (`_BagClock`) from the start, `clock_hz` times a second; without it,
    a subscriber with `use_sim_time` is warned of once (its time would stand still).
    """
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    if rate <= 0:
        raise BagError("--rate must be positive")
    if clock_hz is not None and not clock_hz > 0:
        raise BagError("--clock must be positive")
    with BagReader(src) as reader:
        have = [t.topic for t in reader.topics()]
        missing = sorted(set(topics or ()) - set(have))
        if missing:  # (a misspelt one was dropped without a word)
            raise BagError(f"bag {src} has no topic {', '.join(missing)} (it has: "
                           f"{', '.join(have) or 'none'})")
        infos = [t for t in reader.topics() if topics is None or t.topic in topics]
        if not infos:
            raise BagError(f"bag {src} has none of the requested topics")
        if reader.count([t.topic for t in infos]) == 0:
            raise BagError(f"bag {src} holds no message to play")
        for t in infos:  # (each cloud topic's first cloud, as the nodes check theirs)
            first = next(reader.records([t.topic]), None) if t.msgtype == POINTCLOUD2 else None
            hint = first and messages.large_cloud_hint(len(first.raw), t.topic)
            if hint:
                log.warning("play: %s", hint)
        start_ns = 0  # the first record's time: /clock's until playing starts
        if clock_hz is not None:
            start_ns = next(reader.records([t.topic for t in infos])).stamp_ns
        # No signal handlers of rclpy's: on SIGINT they shut the context down under a
        # publish (RCLError), before Python's own handler stops the loop.
        rclpy.init(args=None, signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node("lidar_obstacles_player", namespace=namespace or None)
        pubs = {}
        for t in infos:
            # Transient-local where the recording says its publisher was (the DEM topics: a
            # DEM consumer subscribes so, and a volatile one offered it nothing), with the
            # depth it had, so a late joiner gets what it would have got from the node.
            latched = 1 if t.topic == CRS_TOPIC else reader.latched_depth(t.topic)
            qos = (QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
                   if latched is None else
                   QoSProfile(depth=latched, reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.TRANSIENT_LOCAL))
            # Bag topics are absolute names; published relative so `-r __ns:=` style use works.
            pubs[t.topic] = node.create_publisher(_msg_class(t.msgtype), t.topic.lstrip("/"), qos)
        sent = 0
        clock: _BagClock | None = None
        try:
            if clock_hz is not None:
                clock = _BagClock(node, clock_hz, rate, start_ns)
            names = [p.topic_name for p in pubs.values()]
            if not _subscriptions_settled(node, names, quiet_s=settle_s, timeout_s=wait_s):
                log.warning("play: no steady subscriber on %s after %g s; playing anyway%s",
                            ", ".join(names), wait_s,
                            _elsewhere_hint(node, {t: p.topic_name for t, p in pubs.items()}))
            sim_time = [] if clock is not None else _sim_time_subscribers(node, names)
            if sim_time:
                log.warning("play: %s subscribed to /clock (use_sim_time): nothing "
                            "publishes it without --clock, so their ROS time stands still and "
                            "their timers (dem_builder's DEM) never fire; use --clock",
                            ", ".join(sim_time))
            while True:
                t0_wall = time.monotonic()
                t0_bag = None
                for record in reader.records([t.topic for t in infos]):
                    t0_bag = record.stamp_ns if t0_bag is None else t0_bag
                    due = t0_wall + (record.stamp_ns - t0_bag) * 1e-9 / rate
                    delay = due - time.monotonic()
                    if clock is not None:
                        clock.run(t0_wall, t0_bag, until_ns=record.stamp_ns)
                    if delay > 0:
                        time.sleep(delay)
                    raw = cdr_of_record(reader, record)
                    if clock is not None:
                        clock.tick()  # (the record's time now: the clock reached it)
                    if raw is not None:
                        pubs[record.topic].publish(raw)
                        sent += 1
                if not loop:
                    break
            # Reliable delivery needs the publisher alive until the subscribers have the data:
            # destroyed at once, the last cloud was lost. Waited for in short slices: Ctrl-C
            # is only seen between them.
            unacked = list(pubs)
            deadline = time.monotonic() + wait_s
            while unacked and time.monotonic() < deadline:
                unacked = [t for t in unacked
                           if not pubs[t].wait_for_all_acked(Duration(seconds=0.1))]
            if unacked:
                log.warning("play: %s not acknowledged by every subscriber after %g s",
                            ", ".join(unacked), wait_s)
        except KeyboardInterrupt as exc:  # (SIGTERM too, from the CLI: same type)
            raise type(exc)(f"published: {sent}") from None
        finally:
            if clock is not None:
                clock.close()
            node.destroy_node()
            rclpy.try_shutdown()
    return {"published": sent}
