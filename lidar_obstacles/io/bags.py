"""Bag containers through `rosbags`: read rosbag2 (mcap, sqlite3) and ROS 1 bags, write rosbag2.

Only the container lives here; messages travel as serialized bytes. Reading hands out raw
records, and :meth:`BagReader.deserialize` turns one into a rosbags message (pure Python,
no ROS install needed). Writing takes CDR bytes, so the ROS layer can serialize with rclpy and
the bag holds exactly what a live node would publish.

Outputs are written to a temporary name beside the target and renamed only when complete,
so an interrupted run never leaves a half-written bag under the requested name.
"""
from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Sequence

from lidar_obstacles.errors import BagError, CloudFormatError
from lidar_obstacles.io.atomic import partial_prefix, remove_stale_partials, swap_in

log = logging.getLogger(__name__)

if TYPE_CHECKING:  # rosbags is imported on first use
    from rosbags.typesys.store import Typestore

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
# The clouds the package's nodes publish (and `replay` writes), by topic name
OUTPUT_CLOUDS = ("ground", "obstacles", "dem", "obstacle_edges")
ODOMETRY = "nav_msgs/msg/Odometry"
CRS_TOPIC = "/survey_crs"  # std_msgs/String, "EPSG:nnnn" or WKT, written by las2bag
STRING = "std_msgs/msg/String"


def typestore() -> Typestore:
    """The ROS 2 Jazzy typestore of rosbags (cached)."""
    global _TYPESTORE
    if _TYPESTORE is None:
        from rosbags.typesys import Stores, get_typestore

        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


_TYPESTORE: Typestore | None = None


@dataclass(frozen=True)
class BagRecord:
    """One message of a bag, still serialized.

    stamp_ns: the bag's receive time in nanoseconds. raw: the serialized bytes (CDR for
    rosbag2, ROS 1 serialization for ``.bag``), ``ros1`` tells which.
    """

    topic: str
    msgtype: str
    stamp_ns: int
    raw: bytes
    ros1: bool


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag: its name, message type and message count."""

    topic: str
    msgtype: str
    count: int


class BagReader:
    """Read a rosbag2 directory / .mcap / .db3, or a ROS 1 .bag.

    Use as a context manager. Every failure to open becomes a BagError with one line.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._reader: Any = None

    def __enter__(self) -> "BagReader":
        from rosbags.highlevel import AnyReader

        path = self.path
        if not path.exists():
            raise BagError(f"bag not found: {path}")
        if _is_las_file(path):  # (rosbags: "Unrecognized storage format '.laz'")
            named = "" if path.suffix.lower() in (".las", ".laz") else (
                " (`evaluate`, `tune`, `simplify` and `features` read it named .las or .laz)")
            raise BagError(f"{path} is a LAS/LAZ file, not a bag: `lidar-obstacles las2bag` "
                           f"turns it into one{named}")
        # A bare .mcap/.db3 file without metadata.yaml: open its folder when that folder is the bag.
        if path.is_file() and path.suffix in (".mcap", ".db3"):
            if (path.parent / "metadata.yaml").is_file():
                path = path.parent
        try:
            self._reader = AnyReader([path], default_typestore=typestore())
            if path.is_dir() and not self._reader.is2:
                # rosbags takes any path ending in .bag for a ROS 1 file, also a rosbag2
                # folder so named (`las2bag survey.laz survey.bag` writes one): a folder
                # is rosbag2, whatever its name
                from rosbags.rosbag2 import Reader as Rosbag2Reader

                self._reader.is2, self._reader.readers = True, [Rosbag2Reader(path)]
            self._reader.open()
        except Exception as exc:  # rosbags raises several types for corrupt or foreign files
            self._reader = None
            text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            if "end magic" in text.lower():  # an mcap whose recording never finished
                text = ("the mcap file ends early (a recording stopped before it was "
                        f"closed: {text.rstrip('.')}); `mcap recover` rebuilds what it holds")
            elif "expected metadata file" in text.lower():
                text = "not a bag: neither a rosbag2 folder (no metadata.yaml) nor a ROS 1 .bag"
            elif "invalid bag metadata" in text.lower():
                # (rosbags adds what its parser met: "string indices must be integers")
                text = ("its metadata.yaml is not rosbag2 metadata (a bag's index of its "
                        "topics and files)")
            elif path.is_file() and path.suffix == ".bag":
                text = _ros1_misnamed(path) or text
            raise BagError(f"cannot open bag {self.path}: {text}") from None
        return self

    def __exit__(self, *exc: object) -> None:
        if self._reader is not None:
            try:
                self._reader.close()
            finally:
                self._reader = None

    @property
    def is_ros1(self) -> bool:
        """True for a ROS 1 .bag, False for rosbag2 (the bag must be open)."""
        return bool(self._reader.is2 is False)

    def topics(self) -> list[TopicInfo]:
        """Topics with their type and message count, sorted by name."""
        counts: dict[tuple[str, str], int] = {}
        for conn in self._reader.connections:
            key = (conn.topic, conn.msgtype)
            counts[key] = counts.get(key, 0) + int(conn.msgcount)
        return [TopicInfo(t, m, c) for (t, m), c in sorted(counts.items())]

    def latched_depth(self, topic: str) -> int | None:
        """The depth a recorder offered `topic` with when it published it transient-local
        (rosbag2's offered QoS; a ROS 1 bag's latching: 1), else None."""
        depths = []
        for conn in self._reader.connections:
            if conn.topic != topic:
                continue
            if getattr(conn.ext, "latching", 0):
                depths.append(1)
            for qos in getattr(conn.ext, "offered_qos_profiles", None) or ():
                if getattr(getattr(qos, "durability", None), "name", "") == "TRANSIENT_LOCAL":
                    depths.append(max(int(getattr(qos, "depth", 1) or 1), 1))
        return max(depths) if depths else None

    def pointcloud_topic(self, topic: str | None = None) -> str:
        """The PointCloud2 topic to process: `topic` when given (checked), else the one
        with the most messages that is not one of the package's own outputs
        (OUTPUT_CLOUDS: a replay's /ground and /obstacles hold as many messages as its
        scans did, and taking one of them for the scan was silent). BagError when there
        is none."""
        clouds = [t for t in self.topics() if t.msgtype == POINTCLOUD2]
        if topic is not None:
            names = [t.topic for t in clouds]
            if topic not in names:
                raise BagError(f"bag {self.path} has no PointCloud2 topic '{topic}' "
                               f"(it has: {', '.join(names) or 'none'})")
            return topic
        clouds = [t for t in clouds if t.count > 0]
        if not clouds:
            raise BagError(f"bag {self.path} has no PointCloud2 messages")
        scans = [t for t in clouds if t.topic.rsplit("/", 1)[-1] not in OUTPUT_CLOUDS]
        if not scans:
            raise BagError(f"bag {self.path} holds only this package's outputs "
                           f"({', '.join(t.topic for t in clouds)}): pass --topic to "
                           "process one of them")
        return max(scans, key=lambda t: t.count).topic

    def deserialize(self, record: BagRecord) -> Any:
        """A rosbags message object of a record, with the bag's own type definitions (ROS 1
        bags carry theirs). BagError when the bytes do not decode."""
        try:
            return self._reader.deserialize(record.raw, record.msgtype)
        except Exception as exc:
            text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise BagError(f"cannot decode a {record.msgtype} message on {record.topic}: "
                           f"{text}") from None

    def deserialize_cloud(self, record: BagRecord) -> Any:
        """`deserialize` of a record of the cloud topic. Bytes that do not decode make it a
        malformed cloud (CloudFormatError, which the offline commands name by its number
        and skip with --skip-malformed), not a broken bag: one damaged message of a long
        flight stopped the whole replay, skip or not."""
        try:
            return self.deserialize(record)
        except BagError as exc:
            raise CloudFormatError(str(exc)) from None

    def count(self, topics: Sequence[str]) -> int:
        """The number of messages on the given topics."""
        return sum(t.count for t in self.topics() if t.topic in topics)

    def records(self, topics: Sequence[str] | None = None) -> Iterator[BagRecord]:
        """Messages of the given topics (all when None) in time order."""
        conns = [c for c in self._reader.connections if topics is None or c.topic in topics]
        if topics is not None and not conns:
            return  # (rosbags reads every connection when given none)
        ros1 = self.is_ros1
        try:
            for conn, stamp, raw in self._reader.messages(connections=conns):
                yield BagRecord(conn.topic, conn.msgtype, int(stamp), bytes(raw), ros1)
        except BagError:
            raise
        except Exception as exc:
            text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            if isinstance(exc, (OverflowError, MemoryError)):  # Python's, not the reader's
                text = "a record's length is out of range"
            raise BagError(f"bag {self.path} is truncated or corrupt: {text}") from None


def _empty(path: Path) -> bool:
    """An empty folder, or a file of no bytes."""
    try:
        return not any(path.iterdir()) if path.is_dir() else path.stat().st_size == 0
    except OSError:
        return False


class BagWriter:
    """Write a rosbag2 (mcap by default, sqlite3 on request) atomically.

    Messages are written to a hidden ``.<name>.partial-<pid>`` folder beside ``out`` and the
    folder is renamed to ``out`` on a clean exit of the context; on an exception the
    partial folder is removed. An existing ``out`` is replaced only when the new bag is
    complete: renamed away to ``.<name>.old-<pid>``, the new bag renamed to ``out``, the old
    one removed. What a writer killed outright left of ``out`` is tidied when the next one
    starts (:func:`~lidar_obstacles.io.atomic.remove_stale_partials`): its partial folder
    removed, and its old bag too, or renamed back to ``out`` when it was killed between the
    renames (then the only copy).
    """

    def __init__(self, path: str | Path, *, storage: str = "mcap") -> None:
        if storage not in ("mcap", "sqlite3"):
            raise BagError(f"unknown bag storage '{storage}' (use mcap or sqlite3)")
        self.path = Path(path)
        self.storage = storage
        self._tmp = self.path.with_name(partial_prefix(self.path))
        self._writer: Any = None
        self._conns: dict[str, Any] = {}

    def __enter__(self) -> "BagWriter":
        from rosbags.rosbag2 import StoragePlugin, Writer, WriterError

        if not self.path.parent.is_dir():
            raise BagError(f"output folder does not exist: {self.path.parent}")
        # Only a bag, or nothing (an empty folder or file), is replaced: a folder of
        # something else, or a file with content, is the user's data.
        if self.path.exists() and not (self.path / "metadata.yaml").is_file() \
                and not _empty(self.path):
            raise BagError(f"{self.path} exists and is not a bag: not overwriting it")
        remove_stale_partials(self.path)
        try:
            if self._tmp.exists():
                shutil.rmtree(self._tmp)
            plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
            self._writer = Writer(self._tmp, version=9, storage_plugin=plugin)
            self._writer.open()
        except (OSError, WriterError) as exc:
            raise BagError(f"cannot write a bag at {self.path}: {exc}") from None
        return self

    def add_topic(self, topic: str, msgtype: str, *, transient_local: bool = False) -> None:
        """Declare a topic before writing to it (idempotent)."""
        if topic in self._conns:
            return
        qos = _offered_qos(transient_local)
        self._conns[topic] = self._writer.add_connection(
            topic, msgtype, typestore=typestore(), offered_qos_profiles=qos)

    def write(self, topic: str, stamp_ns: int, raw: bytes) -> None:
        """Write one serialized (CDR) message."""
        self._writer.write(self._conns[topic], int(stamp_ns), raw)

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        try:
            self._writer.close()
        except Exception:
            if exc_type is None:
                raise
        if exc_type is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            return
        # Name the storage file after the final folder, as ros2 bag does.
        self._rename_storage_file()
        swap_in(self._tmp, self.path, self.path.with_name(f".{self.path.name}.old-{os.getpid()}"))

    def _rename_storage_file(self) -> None:
        meta = self._tmp / "metadata.yaml"
        text = meta.read_text()
        for f in self._tmp.iterdir():
            if f.suffix in (".mcap", ".db3"):
                new = f"{self.path.name}_0{f.suffix}"
                f.rename(self._tmp / new)
                text = text.replace(f.name, new)
        meta.write_text(text)


def _is_las_file(path: Path) -> bool:
    """Whether `path` is a file that starts as a LAS or LAZ file does ("LASF")."""
    if not path.is_file():
        return False
    try:
        with open(path, "rb") as file:
            return file.read(4) == b"LASF"
    except OSError:
        return False  # (rosbags will say what is wrong with it)


def _ros1_misnamed(path: Path) -> str:
    """What a file named .bag that rosbags cannot read as ROS 1 is, when its first bytes
    tell (rosbags said "'utf-8' codec can't decode byte 0x89" of an mcap), else ""."""
    with open(path, "rb") as file:
        head = file.read(16)
    if head.startswith(b"#ROSBAG V2.0"):
        return ""  # a ROS 1 bag, damaged: rosbags' own words say how
    for magic, kind, suffix in ((b"\x89MCAP", "a rosbag2 mcap file", ".mcap"),
                                (b"SQLite format 3", "a rosbag2 sqlite3 file", ".db3")):
        if head.startswith(magic):
            return f"not a ROS 1 bag but {kind}: name it {path.stem}{suffix} to read it"
    return "not a ROS 1 bag (no '#ROSBAG V2.0' at its start)"


def _offered_qos(transient_local: bool) -> list:
    """Reliable keep-last QoS, as the nodes publish (transient-local for the DEM topics)."""
    from rosbags.interfaces import (
        Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime)

    infinite = QosTime(sec=0, nsec=0)  # rosbag2 writes 0 for "default / infinite"
    return [Qos(
        history=QosHistory.KEEP_LAST, depth=1, reliability=QosReliability.RELIABLE,
        durability=QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
        deadline=infinite, lifespan=infinite, liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=infinite, avoid_ros_namespace_conventions=False)]


def read_crs(reader: BagReader) -> str:
    """The survey CRS that las2bag recorded on CRS_TOPIC, or "" when the bag has none, or
    has the topic with another type than las2bag's (said in a warning: its data was read
    as the CRS, and a uint8 array printed as one)."""
    crs_topics = [t for t in reader.topics() if t.topic == CRS_TOPIC]
    if not crs_topics:
        return ""
    if crs_topics[0].msgtype != STRING:
        log.warning("warning: %s of %s is a %s, not the %s that las2bag writes: no survey "
                    "CRS taken from it", CRS_TOPIC, reader.path, crs_topics[0].msgtype, STRING)
        return ""
    for record in reader.records([CRS_TOPIC]):
        return str(reader.deserialize(record).data)
    return ""
