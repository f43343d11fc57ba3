"""Bag containers: round trips in every storage, ROS 1 reading, atomic writes, clear errors."""
from __future__ import annotations

import numpy as np
import pytest

from lidar_obstacles.errors import BagError
from lidar_obstacles.io.bags import POINTCLOUD2, BagReader, BagWriter, typestore
from lidar_obstacles.io.pointcloud2 import make_pointcloud2, read_points


def _points(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                             ("classification", "u1")])
    for name in ("x", "y", "z", "intensity"):
        pts[name] = rng.normal(size=n)
    pts["classification"] = rng.integers(0, 20, n)
    return pts


def _rosbags_cloud(points: np.ndarray, stamp_ns: int = 0):
    ts = typestore()
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    hdr = Header(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id="map")
    return make_pointcloud2(points, header=hdr, msg_cls=ts.types[POINTCLOUD2],
                            field_cls=ts.types["sensor_msgs/msg/PointField"])


def _write(path, clouds, storage="mcap"):
    with BagWriter(path, storage=storage) as bag:
        bag.add_topic("/points", POINTCLOUD2)
        for i, pts in enumerate(clouds):
            raw = typestore().serialize_cdr(_rosbags_cloud(pts, i * 10**8), POINTCLOUD2)
            bag.write("/points", i * 10**8, bytes(raw))


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_rosbag2_round_trip(tmp_path, storage):
    clouds = [_points(100 + i, seed=i) for i in range(3)]
    _write(tmp_path / "bag", clouds, storage)
    assert not list(tmp_path.glob(".bag.partial*"))
    with BagReader(tmp_path / "bag") as reader:
        assert reader.pointcloud_topic() == "/points"
        got = [read_points(reader.deserialize(r)) for r in reader.records()]
    assert len(got) == 3
    for a, b in zip(clouds, got):
        assert a.tobytes() == np.ascontiguousarray(b).tobytes()
    with BagReader(tmp_path / "bag") as reader:  # a topic the bag lacks has no records
        assert list(reader.records(["/elsewhere"])) == [] and reader.count(["/elsewhere"]) == 0


def test_ros1_bag_is_read(tmp_path):
    from rosbags.rosbag1 import Writer as Ros1Writer
    from rosbags.typesys import Stores, get_typestore

    ros1 = get_typestore(Stores.ROS1_NOETIC)
    pts = _points(50)
    Header = ros1.types["std_msgs/msg/Header"]
    Time = ros1.types["builtin_interfaces/msg/Time"]
    msg = make_pointcloud2(pts, header=Header(seq=0, stamp=Time(sec=1, nanosec=0), frame_id="map"),
                           msg_cls=ros1.types[POINTCLOUD2],
                           field_cls=ros1.types["sensor_msgs/msg/PointField"])
    path = tmp_path / "old.bag"
    with Ros1Writer(path) as w:
        conn = w.add_connection("/velodyne_points", POINTCLOUD2, typestore=ros1)
        w.write(conn, 10**9, ros1.serialize_ros1(msg, POINTCLOUD2))
    with BagReader(path) as reader:
        assert reader.pointcloud_topic() == "/velodyne_points"
        (record,) = list(reader.records())
        assert record.ros1
        assert read_points(reader.deserialize(record)).tobytes() == pts.tobytes()


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_rosbag2_folder_named_like_a_ros1_bag_is_read(tmp_path, storage):
    # `las2bag survey.laz survey.bag` writes such a folder, and rosbags takes any path
    # ending in .bag for a ROS 1 file ("Is a directory")
    pts = _points(40)
    _write(tmp_path / "survey.bag", [pts], storage)
    with BagReader(tmp_path / "survey.bag") as reader:
        assert not reader.is_ros1
        (record,) = list(reader.records())
        assert read_points(reader.deserialize(record)).tobytes() == pts.tobytes()


@pytest.mark.parametrize("storage, says", [
    ("mcap", "not a ROS 1 bag but a rosbag2 mcap file: name it flight.mcap to read it"),
    ("sqlite3", "not a ROS 1 bag but a rosbag2 sqlite3 file: name it flight.db3 to read it"),
    (None, "not a ROS 1 bag (no '#ROSBAG V2.0' at its start)")])
def test_a_file_named_bag_that_is_no_ros1_bag_is_said_to_be_what_it_is(
        tmp_path, storage, says):
    """rosbags said "'utf-8' codec can't decode byte 0x89 in position 0" of an mcap."""
    flight = tmp_path / "flight.bag"
    if storage is None:
        flight.write_bytes(b"a text file\n" * 20)
    else:
        _write(tmp_path / "rosbag2", [_points(10)], storage)
        (storage_file,) = (tmp_path / "rosbag2").glob("rosbag2_0.*")
        storage_file.rename(flight)
    with pytest.raises(BagError) as err:
        BagReader(flight).__enter__()
    assert str(err.value) == f"cannot open bag {flight}: {says}"


def test_a_ros1_bag_with_a_topic_without_header_replays(tmp_path):
    # real ROS 1 bags carry /tf (tf2_msgs/TFMessage) and strings: no header to read
    from rosbags.rosbag1 import Writer as Ros1Writer
    from rosbags.typesys import Stores, get_typestore

    from lidar_obstacles.ros.offline import replay

    ros1 = get_typestore(Stores.ROS1_NOETIC)
    Header = ros1.types["std_msgs/msg/Header"]
    Time = ros1.types["builtin_interfaces/msg/Time"]
    String = ros1.types["std_msgs/msg/String"]
    path = tmp_path / "survey.bag"
    with Ros1Writer(path) as w:
        clouds = w.add_connection("/points", POINTCLOUD2, typestore=ros1)
        note = w.add_connection("/note", "std_msgs/msg/String", typestore=ros1)
        w.write(note, 5 * 10**8, ros1.serialize_ros1(String(data="hello"), "std_msgs/msg/String"))
        for i in range(3):
            pts = _points(3000, seed=i)
            pts["x"], pts["y"] = pts["x"] * 10 + 20 * i, pts["y"] * 10
            pts["z"] *= 0.02
            msg = make_pointcloud2(
                pts, header=Header(seq=i, stamp=Time(sec=1 + i, nanosec=0), frame_id="map"),
                msg_cls=ros1.types[POINTCLOUD2], field_cls=ros1.types["sensor_msgs/msg/PointField"])
            w.write(clouds, (1 + i) * 10**9, ros1.serialize_ros1(msg, POINTCLOUD2))
    summary = replay(path, tmp_path / "out", with_dem=False)
    assert summary["messages"] == 3
    with BagReader(tmp_path / "out") as reader:
        assert reader.count(["/obstacles"]) == reader.count(["/ground"]) == 3


def test_only_a_bag_is_ever_overwritten(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "holiday.jpg").write_bytes(b"precious")
    (tmp_path / "notes.txt").write_text("precious")
    for target in (folder, tmp_path / "notes.txt"):
        with pytest.raises(BagError, match="exists and is not a bag: not overwriting"):
            _write(target, [_points(10)])
    assert (folder / "holiday.jpg").read_bytes() == b"precious"
    assert (tmp_path / "notes.txt").read_text() == "precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "photos"]


@pytest.mark.parametrize("kind", ["folder", "file"])
def test_an_empty_folder_or_file_becomes_the_bag(tmp_path, kind):
    """`mkdir out/flight; las2bag ... out/flight`: nothing is lost by replacing nothing (it
    was refused as "not a bag")."""
    target = tmp_path / "out"
    target.mkdir() if kind == "folder" else target.touch()
    _write(target, [_points(10)])
    with BagReader(target) as reader:
        assert reader.count(["/points"]) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_failed_write_leaves_nothing_and_keeps_the_old_bag(tmp_path):
    _write(tmp_path / "bag", [_points(10)])
    before = sorted(p.name for p in (tmp_path / "bag").iterdir())
    with pytest.raises(RuntimeError):
        with BagWriter(tmp_path / "bag") as bag:
            bag.add_topic("/points", POINTCLOUD2)
            raise RuntimeError("interrupted")
    assert sorted(p.name for p in (tmp_path / "bag").iterdir()) == before
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]
    with BagReader(tmp_path / "bag") as reader:
        assert reader.count(["/points"]) == 1


def test_bad_bags_raise_one_clear_error(tmp_path):
    with pytest.raises(BagError, match="not found"):
        BagReader(tmp_path / "missing").__enter__()
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match="cannot open bag .*: not a bag: neither a rosbag2"):
        BagReader(tmp_path / "empty").__enter__()
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not a bag" * 100)
    with pytest.raises(BagError, match="cannot open bag"):
        BagReader(junk).__enter__()
    # Truncated: cut a valid mcap in half.
    _write(tmp_path / "full", [_points(2000, seed=i) for i in range(5)])
    mcap = next((tmp_path / "full").glob("*.mcap"))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    with pytest.raises(BagError):
        with BagReader(cut) as reader:
            list(reader.records())
    # An unfinished recording: the folder's mcap cut short, its footer gone.
    import shutil

    shutil.copytree(tmp_path / "full", tmp_path / "unfinished")
    short = tmp_path / "unfinished" / mcap.name
    short.write_bytes(mcap.read_bytes()[: mcap.stat().st_size * 2 // 3])
    with pytest.raises(BagError, match="mcap file ends early .*mcap recover"):
        BagReader(tmp_path / "unfinished").__enter__()
    # A metadata.yaml that is not rosbag2's: said so, without the YAML parser's internals
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "metadata.yaml").write_text("junk\n")
    with pytest.raises(BagError) as err:
        BagReader(tmp_path / "foreign").__enter__()
    assert str(err.value) == (f"cannot open bag {tmp_path / 'foreign'}: its metadata.yaml is "
                              "not rosbag2 metadata (a bag's index of its topics and files)")
    # A bag without clouds.
    with BagWriter(tmp_path / "odom_only") as bag:
        bag.add_topic("/odom", "nav_msgs/msg/Odometry")
    with BagReader(tmp_path / "odom_only") as reader:
        with pytest.raises(BagError, match="no PointCloud2"):
            reader.pointcloud_topic()
    with BagReader(tmp_path / "full") as reader:
        with pytest.raises(BagError, match="no PointCloud2 topic '/nope'"):
            reader.pointcloud_topic("/nope")
