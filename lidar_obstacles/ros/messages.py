"""Results of the core -> rclpy messages (used by the nodes and, serialized, by `replay`)."""
from __future__ import annotations

import array
import os
from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Quaternion, Vector3
from geometry_msgs.msg import Pose as PoseMsg  # (ros.stages.Pose is the odometry pose we hold)
from nav_msgs.msg import MapMetaData, OccupancyGrid, Odometry
from sensor_msgs.msg import Image, PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from lidar_obstacles.core.classes import CLASS_COLOURS, CLASS_NAMES
from lidar_obstacles.io.pointcloud2 import make_pointcloud2

if TYPE_CHECKING:
    from lidar_obstacles.core.dem import DemGrid
    from lidar_obstacles.core.obstacles import ObstacleObject

# Fast DDS's default shared-memory segment: a sample larger than this goes by UDP, in
# fragments that best effort does not repair, and the small samples beside it (odometry)
# wait for reliable repairs (README: Input QoS and large clouds).
FASTDDS_SEGMENT_BYTES = 512 * 1024
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def large_cloud_hint(n_bytes: int, topic: str) -> str | None:
    """What to do about clouds of `n_bytes` on `topic` when they pass Fast DDS's default
    shared-memory segment and no profile file is named (else None): measured here, a
    best-effort subscriber received 8-18 of 50 such clouds, and odometry beside them came
    up to 1.4 s late, so that clouds waiting for their pose were dropped."""
    rmw = os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    if (n_bytes <= FASTDDS_SEGMENT_BYTES or not rmw.startswith("rmw_fastrtps")
            or any(os.environ.get(v) for v in PROFILE_VARIABLES)):
        return None
    return (f"clouds of {n_bytes / 1e6:.1f} MB on {topic}, over Fast DDS's 512 kB shared-memory "
            "segment, and no FASTRTPS_DEFAULT_PROFILES_FILE: best-effort subscribers lose "
            "such clouds and odometry beside them comes late; set it to the package's "
            "config/fastdds_large_data.xml (installed in share/lidar_obstacles/config; the "
            "launch file's large_data:=true) in every process that sends or takes them")


def header(stamp_ns: int, frame_id: str) -> Header:
    return Header(stamp=Time(sec=int(stamp_ns // 1_000_000_000),
                             nanosec=int(stamp_ns % 1_000_000_000)), frame_id=frame_id)


def stamp_ns_of(h) -> int:
    """Nanoseconds of a Header (rclpy or rosbags)."""
    return int(h.stamp.sec) * 1_000_000_000 + int(h.stamp.nanosec)


def cloud(points: np.ndarray, hdr: Header) -> PointCloud2:
    """A PointCloud2 of a structured array (1-D, or 2-D for organized clouds)."""
    return make_pointcloud2(points, header=hdr, msg_cls=PointCloud2, field_cls=PointField)


def markers(objects: Iterable[ObstacleObject], hdr: Header,
            lifetime_s: float = 0.0) -> MarkerArray:
    """One box and one text label per obstacle object; the first marker clears old ones.

    objects: boxes with min_xyz / max_xyz (3,) metres in hdr.frame_id, heights in metres.
    Each gives a CUBE (id 2 * obj.id, at least 0.1 m a side) and a TEXT_VIEW_FACING label
    (id 2 * obj.id + 1, 1 m above the box). lifetime_s: seconds, 0 = until replaced.
    """
    out = [Marker(header=hdr, action=Marker.DELETEALL)]
    life = Duration(sec=int(lifetime_s), nanosec=int((lifetime_s % 1) * 1e9))
    for obj in objects:
        name = CLASS_NAMES.get(int(obj.cls), "unclassified")
        r, g, b = CLASS_COLOURS.get(int(obj.cls), (0.7, 0.7, 0.7))
        lo, hi = np.asarray(obj.min_xyz, float), np.asarray(obj.max_xyz, float)
        centre, size = (lo + hi) / 2.0, np.maximum(hi - lo, 0.1)
        pose = PoseMsg(position=Point(x=float(centre[0]), y=float(centre[1]),
                                      z=float(centre[2])), orientation=Quaternion(w=1.0))
        out.append(Marker(header=hdr, ns=name, id=2 * int(obj.id), type=Marker.CUBE,
                          action=Marker.ADD, pose=pose, lifetime=life,
                          scale=Vector3(x=float(size[0]), y=float(size[1]), z=float(size[2])),
                          color=ColorRGBA(r=r, g=g, b=b, a=0.5)))
        label = PoseMsg(position=Point(x=float(centre[0]), y=float(centre[1]),
                                       z=float(hi[2]) + 1.0), orientation=Quaternion(w=1.0))
        out.append(Marker(header=hdr, ns=name, id=2 * int(obj.id) + 1,
                          type=Marker.TEXT_VIEW_FACING, action=Marker.ADD, pose=label,
                          lifetime=life, scale=Vector3(z=1.5),
                          color=ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0),
                          text=f"{name} {obj.height_above_ground:.1f} m, "
                               f"clearance {obj.clearance:.1f} m"))
    return MarkerArray(markers=out)


def _map_meta(stamp: Time, rows: int, cols: int, origin, resolution: float) -> MapMetaData:
    return MapMetaData(map_load_time=stamp, resolution=float(resolution), width=int(cols),
                       height=int(rows),
                       origin=PoseMsg(position=Point(x=float(origin[0]), y=float(origin[1])),
                                      orientation=Quaternion(w=1.0)))


def occupancy(cells: np.ndarray, origin: np.ndarray, resolution: float,
              hdr: Header) -> OccupancyGrid:
    """nav_msgs/OccupancyGrid from (rows, cols) int8 cells (row = y from origin).

    cells: 0-100 occupancy, -1 unknown. origin: (2,) x, y of the lower-left corner of cell
    (0, 0), metres. resolution: cell edge, metres.
    """
    rows, cols = cells.shape
    return OccupancyGrid(header=hdr, info=_map_meta(hdr.stamp, rows, cols, origin, resolution),
                         data=array.array("b", np.ascontiguousarray(cells, np.int8).tobytes()))


def dem_messages(grid: DemGrid, hdr: Header) -> tuple[PointCloud2, Image, MapMetaData]:
    """`dem` (organized cloud x y z interpolated), `dem_image` (32FC1) and `dem_info`.

    grid: elevation (rows, cols) metres (NaN unknown), interpolated (rows, cols) uint8,
    origin (2,) metres, resolution metres. The cloud is (rows, cols) points of float32
    x, y, z (metres) and uint8 interpolated, 16 bytes each; the image rows * cols float32
    elevations.
    Row r, column c of all three is the cell whose centre is
    origin + ((c + 0.5) * resolution, (r + 0.5) * resolution).
    """
    elev = np.ascontiguousarray(grid.elevation, dtype=np.float32)
    rows, cols = elev.shape
    res = float(grid.resolution)
    xs = (grid.origin[0] + (np.arange(cols) + 0.5) * res).astype(np.float32)
    ys = (grid.origin[1] + (np.arange(rows) + 0.5) * res).astype(np.float32)
    # 16 bytes a point, not 13: the next point's x at a multiple of 4 for C++ readers that
    # map a point to a struct (zeros in the padding: the same grid, the same bytes)
    pts = np.zeros((rows, cols), dtype={"names": ["x", "y", "z", "interpolated"],
                                        "formats": ["<f4", "<f4", "<f4", "u1"],
                                        "offsets": [0, 4, 8, 12], "itemsize": 16})
    pts["x"] = xs[None, :]
    pts["y"] = ys[:, None]
    pts["z"] = elev
    pts["interpolated"] = grid.interpolated
    dem_cloud = cloud(pts, hdr)
    image = Image(header=hdr, height=rows, width=cols, encoding="32FC1",
                  is_bigendian=0, step=cols * 4)
    image.data = array.array("B", elev.tobytes())
    return dem_cloud, image, _map_meta(hdr.stamp, rows, cols, grid.origin, res)


def odometry(stamp_ns: int, frame_id: str, child_frame_id: str, position, orientation,
             velocity=None) -> Odometry:
    """nav_msgs/Odometry of a pose (position (3,), quaternion x y z w)."""
    msg = Odometry(header=header(stamp_ns, frame_id), child_frame_id=child_frame_id)
    p, q = position, orientation
    msg.pose.pose = PoseMsg(position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                            orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                   w=float(q[3])))
    if velocity is not None:
        msg.twist.twist.linear = Vector3(x=float(velocity[0]), y=float(velocity[1]),
                                         z=float(velocity[2]))
    return msg


# The counts of clouds that gave no output, each for its own reason: any of them since the
# last report makes a node's diagnostics WARN ("failed", a bug, makes them ERROR).
DROPPED = ("rejected", "dropped_no_pose", "dropped_superseded", "lost", "failed")
# `/diagnostics` gives latency percentiles of the last LATENCY_WINDOW clouds and the rate
# over the last RATE_WINDOW (the nodes and `replay` alike)
LATENCY_WINDOW = 200
RATE_WINDOW = 50


def rate_hz(stamps_s: Sequence[float], now_s: float | None = None) -> float:
    """Messages per second over (M,) arrival times in seconds, oldest first (0 for < 2).

    now_s: the time it is reported at, on the same clock. Once no message has come for
    longer than the mean gap, the span runs to now_s, and the rate falls towards 0: a live
    node whose input stopped reported the last rate it had for good."""
    if len(stamps_s) < 2:
        return 0.0
    span = stamps_s[-1] - stamps_s[0]
    gaps = len(stamps_s) - 1
    if now_s is not None and span > 0 and now_s - stamps_s[-1] > span / gaps:
        span = now_s - stamps_s[0]
    return gaps / span if span > 0 else 0.0


def dropped(counts: Mapping[str, int]) -> int:
    """How many clouds gave no output, of a node's counts (`DROPPED`)."""
    return sum(int(counts.get(k, 0)) for k in DROPPED)


def diagnostics(hdr: Header, name: str, hardware_id: str, counts: Mapping[str, int],
                reject_reasons: Mapping[str, int], latencies_s: Sequence[float],
                rate: float, extra: Mapping[str, str] | None = None, *,
                dropped_before: int = 0, received_before: int | None = None
                ) -> DiagnosticArray:
    """One node's `/diagnostics` message: its status named "<name>: processing", with the
    rate (Hz), the latency percentiles of (M,) per-cloud seconds ("nan" before any), every
    count and, as "dropped: <reason>", the count of each reason a cloud gave no output.

    Level ERROR, for good, once a cloud failed on a bug (the node's state is then in
    doubt); WARN when clouds were dropped (`DROPPED`) since the last report, which counted
    `dropped_before` of them, or when none came since then (`received_before`, the
    clouds received as of the last report; None: not judged, as `replay`, whose reports
    come with the clouds): a dead sensor must not look healthy. Else OK. The counts are the
    node's whole life; the clouds dropped while a node starts (before its subscribers
    match, or waiting for odometry) would otherwise have left it WARN for good. The nodes
    publish it every second; `replay` writes it every second of the bag's time."""
    lat = np.asarray(latencies_s, float)
    p50, p95 = np.percentile(lat, (50, 95)) if len(lat) else (np.nan, np.nan)
    values = {"rate_hz": f"{rate:.2f}",
              "latency_p50_ms": f"{1e3 * p50:.1f}",
              "latency_p95_ms": f"{1e3 * p95:.1f}"}
    values.update({k: str(v) for k, v in counts.items()})
    values.update(extra or {})
    values.update({f"dropped: {k}": str(v) for k, v in reject_reasons.items()})
    bad = dropped(counts)
    new = bad - dropped_before
    failed = int(counts.get("failed", 0))
    received = int(counts.get("received", 0))
    idle = received_before is not None and received == received_before
    if failed:
        level = DiagnosticStatus.ERROR
        message = f"{failed} clouds failed on a bug (see the log)" + (
            f"; {new} clouds dropped since the last report" if new > 0 else "")
    elif new > 0:
        level, message = DiagnosticStatus.WARN, f"{new} clouds dropped since the last report"
    elif idle:
        level = DiagnosticStatus.WARN
        message = "no clouds since the last report" if received else "no clouds yet"
    else:
        level = DiagnosticStatus.OK
        message = f"ok ({bad} clouds dropped before)" if bad else "ok"
    status = DiagnosticStatus(level=level, name=f"{name}: processing",
                              hardware_id=hardware_id, message=message,
                              values=[KeyValue(key=k, value=v) for k, v in values.items()])
    return DiagnosticArray(header=hdr, status=[status])
