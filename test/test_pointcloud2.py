"""PointCloud2 <-> NumPy: round trips over random layouts, malformed clouds, non-finite points.

Every round trip is checked byte for byte against the raw message buffer, for rclpy
messages, rosbags typestore messages and a plain duck-typed object, including CDR
serialization through both libraries.
"""
from __future__ import annotations

import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lidar_obstacles.errors import CloudFormatError
from lidar_obstacles.io.pointcloud2 import (
    FLOAT32,
    FLOAT64,
    INT8,
    INT16,
    UINT8,
    UINT16,
    FieldSpec,
    append_fields,
    cloud_layout,
    dtype_from_fields,
    fields_from_dtype,
    finite_mask,
    make_pointcloud2,
    read_points,
    select_points,
    to_native,
    with_xyz,
    xyz_of,
)

from conftest import REPO, data_file

rclpy_msgs = pytest.importorskip("sensor_msgs.msg")
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402
from std_msgs.msg import Header as RclHeader  # noqa: E402

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
PC2_TYPE = "sensor_msgs/msg/PointCloud2"
BagPointCloud2 = TYPESTORE.types[PC2_TYPE]
BagPointField = TYPESTORE.types["sensor_msgs/msg/PointField"]
BagHeader = TYPESTORE.types["std_msgs/msg/Header"]
BagTime = TYPESTORE.types["builtin_interfaces/msg/Time"]
NBYTES = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}
FLAVOURS = ("rclpy", "rosbags", "plain")
SLOW_SETTINGS = settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)


def classes(flavour: str):
    """(msg_cls, field_cls, header) for building messages of one flavour."""
    if flavour == "rclpy":
        header = RclHeader(frame_id="lidar")
        header.stamp.sec, header.stamp.nanosec = 12, 345
        return rclpy_msgs.PointCloud2, rclpy_msgs.PointField, header
    header = BagHeader(stamp=BagTime(sec=12, nanosec=345), frame_id="lidar")
    return BagPointCloud2, BagPointField, header


def raw_message(flavour: str, *, fields, height, width, point_step, row_step, data: bytes,
                is_bigendian=False, is_dense=False):
    """A message built directly from its parts (not through the code under test)."""
    if flavour == "plain":
        return SimpleNamespace(
            height=height, width=width, point_step=point_step, row_step=row_step,
            is_bigendian=is_bigendian, is_dense=is_dense, data=data,
            fields=[SimpleNamespace(name=n, offset=o, datatype=d, count=c)
                    for n, o, d, c in fields],
        )
    msg_cls, field_cls, header = classes(flavour)
    field_objs = [field_cls(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields]
    if flavour == "rosbags":
        return msg_cls(header=header, height=height, width=width, fields=field_objs,
                       is_bigendian=is_bigendian, point_step=point_step, row_step=row_step,
                       data=np.frombuffer(data, np.uint8), is_dense=is_dense)
    msg = msg_cls(header=header, height=height, width=width, fields=field_objs,
                  is_bigendian=is_bigendian, point_step=point_step, row_step=row_step,
                  is_dense=is_dense)
    msg.data = data
    return msg


def cdr_round_trip(msg):
    """The message after serializing and deserializing it with its own library."""
    if isinstance(msg, rclpy_msgs.PointCloud2):
        return deserialize_message(serialize_message(msg), rclpy_msgs.PointCloud2)
    return TYPESTORE.deserialize_cdr(TYPESTORE.serialize_cdr(msg, PC2_TYPE), PC2_TYPE)


def build(points, flavour, **kwargs):
    msg_cls, field_cls, header = classes(flavour if flavour != "plain" else "rosbags")
    return make_pointcloud2(points, header=header, msg_cls=msg_cls, field_cls=field_cls,
                            **kwargs)


def msg_bytes(msg) -> bytes:
    return np.frombuffer(msg.data, np.uint8).tobytes()


def point_bytes(data: bytes, height: int, width: int, point_step: int,
                row_step: int) -> np.ndarray:
    """(height, width, point_step) uint8: the point bytes of a raw buffer, row padding cut."""
    rows = np.frombuffer(data, np.uint8).reshape(height, row_step)
    return rows[:, : width * point_step].reshape(height, width, point_step)


def field_bytes(points: np.ndarray, name: str) -> np.ndarray:
    """(..., nbytes) uint8: the bytes of one field of every point, as stored."""
    values = np.ascontiguousarray(points[name])
    nbytes = points.dtype.fields[name][0].itemsize
    return values.view(np.uint8).reshape(points.shape + (nbytes,))


@st.composite
def layouts(draw):
    """A random valid layout: fields of every type and count, padding, row padding."""
    extra = draw(st.lists(st.tuples(st.integers(1, 8), st.integers(1, 3)), max_size=4))
    specs = [("x", draw(st.sampled_from([FLOAT32, FLOAT64])), 1),
             ("y", draw(st.sampled_from([FLOAT32, FLOAT64])), 1),
             ("z", draw(st.sampled_from([FLOAT32, FLOAT64])), 1)]
    specs += [(f"f{i}", datatype, count) for i, (datatype, count) in enumerate(extra)]
    specs = draw(st.permutations(specs))  # position in the point
    fields, offset = [], 0
    for name, datatype, count in specs:
        offset += draw(st.integers(0, 5))  # padding, unaligned on purpose
        fields.append((name, offset, datatype, count))
        offset += NBYTES[datatype] * count
    point_step = offset + draw(st.integers(0, 6))
    height = draw(st.integers(1, 4))
    width = draw(st.integers(0 if height == 1 else 1, 6))
    row_step = width * point_step + draw(st.integers(0, 9))
    seed = draw(st.integers(0, 2**32 - 1))
    data = np.random.default_rng(seed).integers(0, 256, row_step * height, np.uint8).tobytes()
    return dict(
        fields=draw(st.permutations(fields)),  # order in msg.fields, unrelated to offsets
        height=height, width=width, point_step=point_step, row_step=row_step, data=data,
        is_bigendian=draw(st.booleans()),
    )


def check_view(points: np.ndarray, layout: dict) -> None:
    """Every field of every point equals the message bytes, shape and byte order right."""
    h, w = layout["height"], layout["width"]
    expected = point_bytes(layout["data"], h, w, layout["point_step"], layout["row_step"])
    assert points.shape == ((h, w) if h > 1 else (w,))
    assert points.dtype.itemsize == layout["point_step"]
    assert list(points.dtype.names) == [f[0] for f in layout["fields"]]
    order = ">" if layout["is_bigendian"] else "<"
    for name, offset, datatype, count in layout["fields"]:
        base = points.dtype.fields[name][0]
        base = base.subdtype[0] if base.subdtype else base
        assert base.byteorder in ("|", order, "=" if order == "<" else "")
        got = field_bytes(points, name).reshape(h, w, NBYTES[datatype] * count)
        assert np.array_equal(got, expected[..., offset: offset + NBYTES[datatype] * count])


@pytest.mark.parametrize("flavour", FLAVOURS)
@SLOW_SETTINGS
@given(layout=layouts())
def test_round_trip_random_layouts(flavour, layout):
    msg = raw_message(flavour, **layout)
    points = read_points(msg, keep_non_finite=True)
    check_view(points, layout)
    if points.size:
        assert np.shares_memory(points, np.frombuffer(msg.data, np.uint8))
        assert not points.flags.writeable

    rebuilt = build(points, flavour)
    h, w, step = layout["height"], layout["width"], layout["point_step"]
    packed = point_bytes(layout["data"], h, w, step, layout["row_step"]).tobytes()
    assert msg_bytes(rebuilt) == packed  # every byte, point padding included
    assert (rebuilt.height, rebuilt.width) == ((h, w) if h > 1 else (1, w))
    assert (rebuilt.point_step, rebuilt.row_step) == (step, w * step)
    assert bool(rebuilt.is_bigendian) == layout["is_bigendian"]
    assert [(f.name, f.offset, f.datatype, f.count) for f in rebuilt.fields] == list(
        layout["fields"])

    if flavour != "plain":
        again = read_points(cdr_round_trip(rebuilt), keep_non_finite=True)
        check_view(again, dict(layout, row_step=w * step, data=packed))


@pytest.mark.parametrize("flavour", ["rclpy", "rosbags"])
@SLOW_SETTINGS
@given(layout=layouts(), seed=st.integers(0, 1000))
def test_append_fields_keeps_every_input_byte(flavour, layout, seed):
    msg = cdr_round_trip(raw_message(flavour, **layout))
    points = read_points(msg, keep_non_finite=True)
    rng = np.random.default_rng(seed)
    cls = rng.integers(0, 16, points.shape).astype(np.uint8)
    hag = rng.normal(size=points.shape).astype(np.float32)
    out = append_fields(points, {"class": cls, "height_above_ground": hag})
    assert out.shape == points.shape
    names = sorted(points.dtype.names, key=lambda n: points.dtype.fields[n][1])
    assert list(out.dtype.names) == names + ["class", "height_above_ground"]
    # every field aligned to its element's size (at most 8), the point to the largest, and
    # no more padding than that takes
    sizes = {n: min(out.dtype.fields[n][0].base.itemsize, 8) for n in out.dtype.names}
    assert all(out.dtype.fields[n][1] % sizes[n] == 0 for n in out.dtype.names)
    assert out.dtype.itemsize % max(sizes.values()) == 0
    packed = sum(points.dtype.fields[n][0].itemsize for n in names) + 5
    assert packed <= out.dtype.itemsize < packed + 8 * len(sizes)
    assert out.dtype.fields["height_above_ground"][1] % 4 == 0
    for name in names:
        assert out.dtype.fields[name][0] == points.dtype.fields[name][0]
        assert np.array_equal(field_bytes(out, name), field_bytes(points, name))

    back = read_points(cdr_round_trip(build(out, flavour)), keep_non_finite=True)
    assert back.dtype == out.dtype
    assert back.tobytes() == out.tobytes()
    assert np.array_equal(back["class"], cls)
    assert np.array_equal(back["height_above_ground"], hag)  # converted to the cloud's order
    assert bool(build(out, flavour).is_bigendian) == layout["is_bigendian"]


def simple_points(n=6, *, big=False, padded=True):
    order = ">" if big else "<"
    dtype = np.dtype({
        "names": ["x", "y", "z", "intensity", "ring", "time"],
        "formats": [order + "f4"] * 4 + [order + "u2", order + "f8"],
        "offsets": [0, 4, 8, 16, 20, 24] if padded else [0, 4, 8, 12, 16, 18],
        "itemsize": 32 if padded else 26,
    })
    points = np.zeros(n, dtype)
    points["x"] = np.arange(n)
    points["y"] = 10 + np.arange(n)
    points["z"] = 0.5
    points["intensity"] = 7
    points["ring"] = np.arange(n) % 3
    points["time"] = 1e9 + np.arange(n) * 1e-5
    return points


def test_known_layout_values_and_fields():
    msg = build(simple_points(4), "rclpy")
    assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [
        ("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("ring", 20, 4),
        ("time", 24, 8)]
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, 4, 32, 128)
    assert msg.is_dense and not msg.is_bigendian
    assert msg.header.frame_id == "lidar" and msg.header.stamp.nanosec == 345
    assert np.array_equal(xyz_of(read_points(msg)),
                          [[0, 10, 0.5], [1, 11, 0.5], [2, 12, 0.5], [3, 13, 0.5]])


def test_big_endian_view_never_touches_the_message():
    points = simple_points(5, big=True)
    msg = build(points, "rosbags")
    assert msg.is_bigendian
    before = msg_bytes(msg)
    assert before[:4] == np.array([0], ">f4").tobytes()
    assert before[32:36] == np.array([1], ">f4").tobytes() == b"\x3f\x80\x00\x00"
    view = read_points(msg)
    assert view.dtype["x"] == np.dtype(">f4")
    with pytest.raises(ValueError):
        view["x"][0] = 3  # read-only: nobody can scribble on the message
    native = to_native(view)
    assert native.dtype["x"].isnative and native.dtype.itemsize == 32
    assert not np.shares_memory(native, view)
    assert np.array_equal(native["time"], points["time"])
    assert np.array_equal(xyz_of(view), xyz_of(native))
    assert msg_bytes(msg) == before
    assert to_native(native) is native  # already native: no copy


def test_organized_cloud_with_row_padding():
    h, w, step, row_step = 3, 4, 16, 4 * 16 + 8
    raw = np.full((h, row_step), 0xAB, np.uint8)
    xyz = np.arange(h * w * 3, dtype=np.float32).reshape(h, w, 3)
    xyz[1, 2, 0] = np.nan
    xyz[2, 0, 2] = -np.inf
    pts = raw[:, : w * step].reshape(h, w, step)
    pts[..., :12] = xyz.view(np.uint8).reshape(h, w, 12)
    pts[..., 12] = np.arange(h * w).reshape(h, w)
    fields = [("x", 0, FLOAT32, 1), ("y", 4, FLOAT32, 1), ("z", 8, FLOAT32, 1),
              ("label", 12, UINT8, 1)]
    msg = raw_message("rclpy", fields=fields, height=h, width=w, point_step=step,
                      row_step=row_step, data=raw.tobytes())
    organized = read_points(msg, keep_non_finite=True)
    assert organized.shape == (h, w)
    assert organized.strides == (row_step, step)
    assert np.array_equal(organized["label"], np.arange(12).reshape(h, w))
    assert np.array_equal(finite_mask(organized).sum(), 10)
    flat = read_points(msg, keep_non_finite=True, reshape_organized=False)
    assert flat.shape == (12,) and np.array_equal(flat["label"], np.arange(12))
    dropped = read_points(msg)
    assert dropped.shape == (10,)
    assert np.array_equal(dropped["label"], [0, 1, 2, 3, 4, 5, 7, 9, 10, 11])
    assert np.isfinite(xyz_of(dropped)).all()
    assert xyz_of(organized).shape == (h, w, 3)

    out = build(organized, "rclpy")  # organized in, organized out, row padding gone
    assert (out.height, out.width, out.row_step, out.is_dense) == (h, w, w * step, False)
    assert msg_bytes(out) == pts.tobytes()
    assert build(organized, "rclpy", dense=True).is_dense


def test_dense_cloud_drop_is_a_zero_copy_view():
    msg = build(simple_points(8), "rosbags")
    points = read_points(msg)
    assert points.shape == (8,)
    assert np.shares_memory(points, msg.data)


def test_non_finite_dropped_or_kept():
    points = simple_points(6)
    points["x"][1] = np.nan
    points["z"][4] = np.inf
    points["intensity"][2] = np.nan  # not a coordinate: kept
    msg = build(points, "rclpy")
    assert not msg.is_dense
    assert np.array_equal(read_points(msg)["ring"], points["ring"][[0, 2, 3, 5]])
    kept = read_points(msg, keep_non_finite=True)
    assert kept.shape == (6,) and np.isnan(kept["x"][1])
    assert np.isposinf(kept["z"][4])


def test_empty_clouds_are_not_errors():
    fields = [("x", 0, FLOAT32, 1), ("y", 4, FLOAT32, 1), ("z", 8, FLOAT32, 1)]
    for height, width in ((1, 0), (0, 0), (0, 5), (3, 0)):
        msg = raw_message("rosbags", fields=fields, height=height, width=width, point_step=12,
                          row_step=12 * width, data=bytes(12 * width * height))
        points = read_points(msg, keep_non_finite=True)
        assert points.shape == (0,) and points.dtype.names == ("x", "y", "z")
    empty = build(np.empty(0, dtype_from_fields([FieldSpec(*f) for f in fields], 12, False)),
                  "rclpy")
    assert (empty.width, empty.height, len(empty.data), empty.is_dense) == (0, 1, 0, True)
    assert read_points(cdr_round_trip(empty)).shape == (0,)


def test_rclpy_data_is_one_owned_copy():
    points = simple_points(4)
    msg = build(points, "rclpy")
    assert msg.data.typecode == "B" and len(msg.data) == 4 * 32
    bag = build(points, "rosbags")
    points["x"][:] = 99  # later changes of the array never reach the messages
    assert msg_bytes(msg) == msg_bytes(bag) == simple_points(4).tobytes()


def test_append_fields_details():
    points = simple_points(3)
    out = append_fields(points, {"class": np.array([1, 2, 6], np.uint8),
                                 "normal": np.ones((3, 3), np.float32)})
    # each field at a multiple of its element's size: `time` (FLOAT64) 18 -> 24, `normal`
    # 36 after `class` at 32; the point a multiple of 8
    assert [out.dtype.fields[n][1] for n in out.dtype.names] == [0, 4, 8, 12, 16, 24, 32, 36]
    assert out.dtype.itemsize == 48
    assert out.dtype.fields["normal"][0] == np.dtype(("<f4", (3,)))
    assert fields_from_dtype(out.dtype)[-1] == FieldSpec("normal", 36, FLOAT32, 3)
    with pytest.raises(CloudFormatError, match="already present"):
        append_fields(out, {"class": np.zeros(3, np.uint8)})
    again = append_fields(out, {"class": np.zeros(3, np.uint8)}, overwrite=True)
    assert list(again.dtype.names)[-2:] == ["normal", "class"] and not again["class"].any()
    with pytest.raises(CloudFormatError, match="shape"):
        append_fields(points, {"class": np.zeros(4, np.uint8)})
    with pytest.raises(CloudFormatError, match="bool"):
        append_fields(points, {"flag": np.zeros(3, bool)})


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("coord", ["f4", "f8"])
def test_with_xyz_carries_utm_coordinates_and_keeps_the_other_fields(order, coord):
    pts = np.zeros(4, dtype=[("intensity", order + "u2"), ("x", order + coord),
                             ("y", order + coord), ("z", order + coord),
                             ("classification", "u1"), ("gps_time", order + "f8")])
    pts["intensity"], pts["classification"] = [1, 2, 3, 65535], [2, 5, 6, 14]
    pts["gps_time"] = [1.5, 2.5, 3.5, 4.5]
    xyz = np.array([[512345.678, 5712345.678, 345.61]] * 4) + np.arange(4)[:, None] * 0.01
    out = with_xyz(pts, xyz, widen=True)
    assert out.dtype.names == pts.dtype.names
    assert np.array_equal(xyz_of(out), xyz)  # FLOAT32 held the northing to 0.5 m
    for name in ("x", "y", "z"):
        assert out.dtype[name] == np.dtype(order + "f8")
    for name in ("intensity", "classification", "gps_time"):
        assert out[name].tobytes() == pts[name].tobytes()
    assert fields_from_dtype(out.dtype)  # publishable
    assert np.array_equal(xyz_of(pts), np.zeros((4, 3)))  # the input untouched
    # not widened: the layout is the input's, byte for byte, the values rounded to it
    kept = with_xyz(pts, xyz)
    assert kept.dtype == pts.dtype
    assert np.array_equal(xyz_of(kept), xyz.astype(coord).astype(float))
    for name in ("intensity", "classification", "gps_time"):
        assert kept[name].tobytes() == pts[name].tobytes()


def test_select_points_keeps_every_byte():
    raw = np.random.default_rng(3).integers(0, 256, 2 * 5 * 32, np.uint8)
    organized = raw.view(simple_points(1).dtype).reshape(2, 5)
    mask = np.zeros((2, 5), bool)
    mask[0, 1] = mask[1, 3] = mask[1, 4] = True
    picked = select_points(organized, mask)
    assert picked.shape == (3,) and picked.dtype == organized.dtype
    assert picked.tobytes() == raw.reshape(10, 32)[[1, 8, 9]].tobytes()  # padding too
    assert np.array_equal(picked["ring"], organized["ring"][mask])
    by_index = select_points(organized, np.array([9, 1]))
    assert by_index.tobytes() == raw.reshape(10, 32)[[9, 1]].tobytes()
    assert select_points(organized, np.zeros((2, 5), bool)).shape == (0,)


def test_fields_and_dtype_are_inverse():
    fields = [FieldSpec("z", 9, FLOAT64, 1), FieldSpec("x", 0, FLOAT32, 1),
              FieldSpec("y", 4, FLOAT32, 1), FieldSpec("rgb", 17, UINT8, 3),
              FieldSpec("t", 20, INT16, 2), FieldSpec("c", 8, INT8, 1)]
    dtype = dtype_from_fields(fields, 30, True)
    assert dtype.itemsize == 30 and dtype.names == ("z", "x", "y", "rgb", "t", "c")
    assert dtype.fields["t"][0] == np.dtype((">i2", (2,)))
    assert fields_from_dtype(dtype) == fields


GOOD = [("x", 0, FLOAT32, 1), ("y", 4, FLOAT32, 1), ("z", 8, FLOAT32, 1),
        ("ring", 12, UINT16, 1)]


def bad(**changes):
    layout = dict(fields=GOOD, height=2, width=3, point_step=16, row_step=48)
    layout.update(changes)
    if "data" not in layout:
        layout["data"] = bytes(layout["row_step"] * layout["height"])
    return layout


MALFORMED = {
    "short data": (bad(data=bytes(95)), r"data has 95 bytes, expected row_step 48 \* height 2"),
    "long data": (bad(data=bytes(97)), "data has 97 bytes"),
    "row_step too small": (bad(row_step=47), r"row_step 47 < width 3 \* point_step 16"),
    "field outside point_step": (bad(point_step=13, row_step=39), "'ring'.*outside point_step 13"),
    "count pushes field out": (bad(fields=GOOD[:3] + [("ring", 12, UINT16, 3)]), "outside"),
    "overlap": (bad(fields=GOOD[:3] + [("ring", 10, UINT16, 1)]), "'z'.*'ring'.*overlap"),
    # z is bytes 8..11: a field from byte 11 shares one byte with it (from 12, as in GOOD,
    # it only touches it)
    "overlap by one byte": (bad(fields=GOOD[:3] + [("ring", 11, UINT16, 1)]),
                            r"'z' \(bytes 8..11\) and 'ring' \(from byte 11\) overlap"),
    "missing z": (bad(fields=GOOD[:2] + GOOD[3:]), "no 'z' field"),
    "unknown datatype 0": (bad(fields=GOOD[:3] + [("ring", 12, 0, 1)]), "unknown datatype 0"),
    "unknown datatype 9": (bad(fields=GOOD[:3] + [("ring", 12, 9, 1)]), "unknown datatype 9"),
    "count 0": (bad(fields=GOOD[:3] + [("ring", 12, UINT16, 0)]), "'ring' has bad count 0"),
    "duplicate name": (bad(fields=GOOD + [("y", 14, UINT16, 1)]), "'y' appears more than once"),
    "integer x": (bad(fields=[("x", 0, 5, 1)] + GOOD[1:]), "'x' must be a single FLOAT32"),
    "y with count 2": (bad(fields=[("x", 0, FLOAT32, 1), ("y", 4, FLOAT32, 2),
                                   ("z", 12, FLOAT32, 1)]), "'y' must be a single"),
    "empty cloud with stray data": (bad(width=0, row_step=0, data=bytes(5)), "empty cloud"),
}


@pytest.mark.parametrize("flavour", ["rclpy", "rosbags"])
@pytest.mark.parametrize("case", MALFORMED)
def test_malformed_clouds_raise(case, flavour):
    layout, message = MALFORMED[case]
    with pytest.raises(CloudFormatError, match=message):
        read_points(raw_message(flavour, **layout))


@pytest.mark.parametrize("changes, message", [
    (dict(height=-1, data=b""), "height must be a non-negative integer"),
    (dict(point_step=1.5), "point_step must be a non-negative integer"),
    (dict(fields=GOOD[:3] + [("ring", -2, UINT16, 1)]), "offset of field 'ring'"),
    (dict(fields=GOOD[:3] + [("", 12, UINT16, 1)]), "no usable name"),
    (dict(data="not bytes"), "not a byte buffer"),
])
def test_malformed_duck_typed_values_raise(changes, message):
    with pytest.raises(CloudFormatError, match=message):
        read_points(raw_message("plain", **bad(**changes)))


@pytest.mark.parametrize("points, message", [
    (np.zeros((2, 2, 2), simple_points(1).dtype), "1-D or 2-D"),
    (np.zeros(3, np.float32), "structured"),
    (np.zeros(3, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("ok", "?")]), "'ok'.*bool"),
    (np.zeros(3, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("n", "<i8")]), "'n'"),
    (np.zeros(3, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("m", "f4", (2, 2))]), "2-D subarray"),
    (np.zeros(3, [("x", "f4"), ("y", "f4")]), "no 'z'"),
    (np.zeros(3, [("x", "<f4"), ("y", "<f4"), ("z", ">f4")]), "mix byte orders"),
    (np.zeros(3, np.dtype({"names": ["x", "y", "z", "w"], "formats": ["f4"] * 4,
                           "offsets": [0, 4, 8, 6]})), "overlap"),
])
def test_make_pointcloud2_rejects_bad_points(points, message):
    with pytest.raises(CloudFormatError, match=message):
        build(points, "rosbags")


def test_cloud_layout_reports_the_header():
    msg = raw_message("rosbags", **bad())
    layout = cloud_layout(msg)
    assert (layout.num_points, layout.data_size, layout.fields[3]) == (
        6, 96, FieldSpec("ring", 12, UINT16, 1))


def test_real_survey_through_a_bag_message():
    from lidar_obstacles.io.las import read_las

    cloud = read_las(data_file("isprs/samp11-utm.laz"))
    msg = cdr_round_trip(build(cloud.points, "rosbags"))
    points = read_points(msg)
    assert points.shape == cloud.points.shape
    assert points.tobytes() == cloud.points.tobytes()
    assert np.array_equal(xyz_of(points), cloud.xyz)
    labelled = append_fields(points, {"class": points["classification"]})
    rcl = cdr_round_trip(build(labelled, "rclpy"))
    assert np.array_equal(read_points(rcl)["class"], cloud.points["classification"])


def test_module_imports_without_ros():
    code = (
        "import sys\n"
        "for name in ('rclpy', 'sensor_msgs', 'std_msgs', 'rosbags'):\n"
        "    sys.modules[name] = None\n"
        "import lidar_obstacles.io.pointcloud2\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)
