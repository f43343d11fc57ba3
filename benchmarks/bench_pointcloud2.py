"""Speed of PointCloud2 <-> NumPy conversion for rclpy and rosbags messages.

A 100k-point cloud in a typical spinning-LiDAR layout (x y z intensity FLOAT32, ring
UINT16, time FLOAT64; point_step 32 with padding) is converted both ways:

* message -> array: ``read_points`` (zero-copy view; non-finite check) and ``xyz_of``;
* array + ``class`` UINT8 + ``height_above_ground`` FLOAT32 -> message: ``append_fields``
  then ``make_pointcloud2``.

The anchor, measured in the same run, is one plain copy of the cloud's bytes (what any
conversion that touches every byte must pay); the target is "well under 5 ms" each way,
reported both in milliseconds and as a ratio to the anchor. Naive ways (NumPy's
``recfunctions.append_fields``, rclpy's ``PointCloud2(data=arr.tobytes())``) are timed
alongside to show what the chosen ones save.

Usage: .venv/bin/python benchmarks/bench_pointcloud2.py [--quick | --smoke --out DIR]
Writes benchmarks/results/pointcloud2.json (to --out DIR if given).
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import numpy.lib.recfunctions as rfn

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lidar_obstacles.io.pointcloud2 import (  # noqa: E402
    append_fields,
    make_pointcloud2,
    read_points,
    select_points,
    xyz_of,
)
from common import bench_args, per_mode  # noqa: E402 (benchmarks/ is on the path)

TARGET_MS = 5.0
POINT_DTYPE = np.dtype({
    "names": ["x", "y", "z", "intensity", "ring", "time"],
    "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f8"],
    "offsets": [0, 4, 8, 16, 20, 24],
    "itemsize": 32,
})


def make_cloud(n: int, nan_fraction: float, rng: np.random.Generator) -> np.ndarray:
    points = np.zeros(n, POINT_DTYPE)
    for axis in "xyz":
        points[axis] = rng.uniform(-50, 50, n)
    points["intensity"] = rng.uniform(0, 255, n)
    points["ring"] = np.arange(n) % 32
    points["time"] = 1.7e9 + np.arange(n) * 1e-6
    if nan_fraction:
        points["x"][rng.random(n) < nan_fraction] = np.nan
    return points


def timed(fn, repeat: int) -> dict[str, float]:
    fn()  # warm-up: imports, first-touch allocations
    samples = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - start) * 1e3)
    return {"median_ms": statistics.median(samples), "min_ms": min(samples)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, help="points per cloud (100 000; 1 000 with "
                        "--smoke)")
    args = bench_args(__doc__, "fewer repeats", "1 000 points, one repeat", parser)
    repeat = per_mode(args, 40, 10, 1)
    n = args.points or per_mode(args, 100_000, 100_000, 1_000)

    from rclpy.serialization import deserialize_message, serialize_message
    from rosbags.typesys import Stores, get_typestore
    from sensor_msgs.msg import PointCloud2, PointField
    from std_msgs.msg import Header

    store = get_typestore(Stores.ROS2_JAZZY)
    bag_types = (store.types["sensor_msgs/msg/PointCloud2"],
                 store.types["sensor_msgs/msg/PointField"])
    bag_header = store.types["std_msgs/msg/Header"](
        stamp=store.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="lidar")
    flavours = {
        "rclpy": (PointCloud2, PointField, Header(frame_id="lidar")),
        "rosbags": (*bag_types, bag_header),
    }

    rng = np.random.default_rng(0)
    clouds = {"dense": make_cloud(n, 0.0, rng), "5% NaN": make_cloud(n, 0.05, rng)}
    raw = clouds["dense"].view(np.uint8)
    rows: list[dict] = []

    def add(direction: str, flavour: str, case: str, fn, *, counted: bool = True) -> None:
        row = {"direction": direction, "flavour": flavour, "case": case, **timed(fn, repeat),
               "counted_for_target": counted}
        rows.append(row)

    add("anchor", "-", f"copy of the cloud's {raw.nbytes} bytes", raw.copy, counted=False)

    for flavour, (msg_cls, field_cls, header) in flavours.items():
        for label, cloud in clouds.items():
            built = make_pointcloud2(cloud, header=header, msg_cls=msg_cls, field_cls=field_cls)
            # Messages as a subscriber or bag reader hands them over (deserialized).
            if flavour == "rclpy":
                msg = deserialize_message(serialize_message(built), msg_cls)
            else:
                typename = "sensor_msgs/msg/PointCloud2"
                msg = store.deserialize_cdr(store.serialize_cdr(built, typename), typename)
            add("msg->array", flavour, f"read_points, {label}", lambda m=msg: read_points(m))
            add("msg->array", flavour, f"read_points + xyz_of, {label}",
                lambda m=msg: xyz_of(read_points(m)))
            add("msg->array", flavour, f"read_points keep_non_finite, {label}",
                lambda m=msg: read_points(m, keep_non_finite=True))

            points = read_points(msg)
            cls = rng.integers(0, 16, len(points)).astype(np.uint8)
            hag = rng.uniform(0, 30, len(points)).astype(np.float32)

            def to_msg(p=points, c=cls, h=hag, mc=msg_cls, fc=field_cls, hd=header):
                out = append_fields(p, {"class": c, "height_above_ground": h})
                return make_pointcloud2(out, header=hd, msg_cls=mc, field_cls=fc)

            add("array->msg", flavour, f"append_fields + make_pointcloud2, {label}", to_msg)

        dense = read_points(msg)
        new = {"class": np.zeros(len(dense), np.uint8),
               "height_above_ground": np.zeros(len(dense), np.float32)}
        add("array->msg", flavour, "  part: append_fields only",
            lambda p=dense: append_fields(p, new), counted=False)
        add("array->msg", flavour, "  naive: numpy recfunctions.append_fields",
            lambda p=dense: rfn.append_fields(p, list(new), list(new.values()),
                                              usemask=False),
            counted=False)

    packed = append_fields(read_points(msg), new)
    header = flavours["rclpy"][2]

    def rclpy_kwargs_tobytes():
        PointCloud2(header=header, height=1, width=len(packed), fields=[],
                    point_step=packed.dtype.itemsize, row_step=packed.nbytes,
                    data=packed.tobytes())

    def rclpy_assign_bytes():
        msg = PointCloud2()
        msg.data = packed.tobytes()

    add("array->msg", "rclpy", "  naive: PointCloud2(data=arr.tobytes())", rclpy_kwargs_tobytes,
        counted=False)
    add("array->msg", "rclpy", "  naive: msg.data = arr.tobytes()", rclpy_assign_bytes,
        counted=False)

    def rclpy_frombytes():
        msg = PointCloud2()
        msg.data.frombytes(packed.view(np.uint8))

    add("array->msg", "rclpy", "  chosen: msg.data.frombytes(arr)", rclpy_frombytes,
        counted=False)
    add("array->msg", "rclpy", "  make_pointcloud2(dense=True), all included",
        lambda: make_pointcloud2(packed, header=header, msg_cls=PointCloud2,
                                 field_cls=PointField, dense=True),
        counted=False)

    mask = np.random.default_rng(1).random(len(packed)) < 0.5  # a ground/obstacle split
    add("split", "-", "  naive: points[mask] (structured copy)", lambda: packed[mask],
        counted=False)
    add("split", "-", "  select_points(points, mask)", lambda: select_points(packed, mask),
        counted=False)

    anchor = rows[0]["median_ms"]
    for row in rows:
        row["ratio_to_anchor"] = row["median_ms"] / anchor
    counted = [r for r in rows if r["counted_for_target"]]
    worst = {d: max(r["median_ms"] for r in counted if r["direction"] == d)
             for d in ("msg->array", "array->msg")}
    passed = all(v < TARGET_MS for v in worst.values())

    print(f"\nPointCloud2 conversion, {n} points, point_step {POINT_DTYPE.itemsize}, "
          f"{repeat} repeats (median / min ms)\n")
    print("| direction | flavour | case | median ms | min ms | x anchor |")
    print("|---|---|---|---:|---:|---:|")
    for r in rows:
        print(f"| {r['direction']} | {r['flavour']} | {r['case']} | {r['median_ms']:.3f} "
              f"| {r['min_ms']:.3f} | {r['ratio_to_anchor']:.1f} |")
    print(f"\nworst median: msg->array {worst['msg->array']:.3f} ms, array->msg "
          f"{worst['array->msg']:.3f} ms; target < {TARGET_MS} ms each way: "
          f"{'PASS' if passed else 'FAIL'}")

    result = {
        "benchmark": "pointcloud2",
        "points": n,
        "point_step": POINT_DTYPE.itemsize,
        "repeats": repeat,
        "anchor": rows[0]["case"],
        "anchor_median_ms": anchor,
        "target_ms": TARGET_MS,
        "worst_median_ms": worst,
        "passed": passed,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "rows": rows,
    }
    (args.out / "pointcloud2.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out / 'pointcloud2.json'}")


if __name__ == "__main__":
    main()
