"""End-to-end speed, latency and memory of the pipelines on simulated flights.

- replay: a simulated 10 Hz flight with ~50k points per message through both nodes' stages
  (`lidar-obstacles replay`), as a multiple of real time (target >= 5x).
- live latency: the `obstacle_detector` executable as a subprocess; 50k-point clouds published
  at 10 Hz; time from publishing a cloud to receiving its `obstacles` (target p95 <= 100 ms);
  with Fast DDS's default transports, and with the shipped large-data profile
  (config/fastdds_large_data.xml) in every process, as the README advises for such clouds;
  and beside `dem_builder`, filtering the clouds itself or taking the detector's `ground`.
- DEM update: `dem_builder`'s pipeline on the same clouds, per message (ground filter and
  binning; target p95 <= 50 ms), and per publish (gaps filled at `dem.publish_rate`).
- memory: a long simulated flight through both stages in one process; resident memory after
  the first 10 % of the flight vs at the end (target growth < 10 %). `--minutes 30` is the
  issue's flight; the default is shorter so `make bench` stays reasonable. With
  `--memory-only` only this part runs, and writes pipeline_memory.json instead (the
  30-minute flight takes ~30 minutes on one core).

    python benchmarks/bench_pipeline.py [--quick | --smoke --out DIR] [--minutes M]
    python benchmarks/bench_pipeline.py --memory-only --minutes 30

The live parts use the environment's ROS_DOMAIN_ID (the tests set one per run), else a
random one of 1-101 (above 101, Linux's ephemeral ports may take a domain's). Writes
benchmarks/results/pipeline.json (to --out DIR if given).
"""
from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common import bench_args, per_mode  # (benchmarks/ is on the path)


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def peak_mb() -> float:
    """The process's highest resident size so far (ru_maxrss is in KiB on Linux)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def cpu_seconds(who: int) -> float:
    """User + system CPU seconds of this process (RUSAGE_SELF, all its threads) or of its
    children waited for (RUSAGE_CHILDREN: `replay`'s workers once it has returned)."""
    import resource

    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def bench_replay(seconds: float) -> dict:
    """`replay` of a simulated `mixed` flight: its speed, and its CPU per message over its
    three processes against the same work done in this one (`serial_replay`). The CPU says
    how fast the machine's cores allow: the ceiling is cores x the message period / the
    CPU per message, whatever the layout."""
    import resource

    from lidar_obstacles.ros import offline

    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "flight"
        offline.simulate(bag, scene="mixed", seed=1, duration=seconds, frame="map")
        before = cpu_seconds(resource.RUSAGE_SELF) + cpu_seconds(resource.RUSAGE_CHILDREN)
        out = offline.replay(bag, Path(tmp) / "out")
        cpu = (cpu_seconds(resource.RUSAGE_SELF) + cpu_seconds(resource.RUSAGE_CHILDREN)
               - before)
        serial = serial_replay(bag)
    messages = max(out["messages"], 1)
    cores = len(os.sched_getaffinity(0))
    cpu_ms = 1000.0 * cpu / messages
    period_ms = 1000.0 * seconds / messages
    return {"flight_s": seconds, "messages": out["messages"],
            "points_per_message": out["points"] / messages,
            "wall_s": out["wall_seconds"], "real_time_factor": out["real_time_factor"],
            "latency_p50_ms": out["latency_p50_ms"], "latency_p95_ms": out["latency_p95_ms"],
            "cpu_ms_per_message": round(cpu_ms, 1), "cores": cores,
            # the busy share of the cores while it ran (1: none ever idle)
            "core_utilisation": round(cpu / (cores * out["wall_seconds"]), 3),
            "real_time_factor_ceiling": round(cores * period_ms / cpu_ms, 2),
            "serial": serial}


def serial_replay(bag: Path) -> dict:
    """The work of `replay` on `bag` done in this one process, in order, without writing a
    bag: CPU ms per message of each part (reading and the ground step; the obstacles and
    the detector's messages; the DEM), and the speed as a multiple of real time."""
    from lidar_obstacles.core.arrays import single_threaded_blas
    from lidar_obstacles.io.bags import BagReader
    from lidar_obstacles.ros import offline
    from lidar_obstacles.ros.stages import DemStage, DetectorStage

    single_threaded_blas()  # as replay runs it
    det_cfg, dem_cfg = offline.load_configs(None)
    stats = offline.ReplayStats()
    detector, dem = DetectorStage(det_cfg), DemStage(dem_cfg)
    schedule = offline.DemSchedule(dem)
    parts = {"read_and_ground": 0.0, "obstacles_and_messages": 0.0, "dem": 0.0}
    part_of = {offline.ObstacleWork: "obstacles_and_messages", offline.DemWork: "dem"}
    t0 = time.perf_counter()
    with BagReader(bag) as reader:
        items = offline.run_stages(reader, topic=None, detector=detector, dem=dem,
                                   stats=stats, passthrough=True)
        while True:
            c0 = time.process_time()
            item = next(items, None)
            c1 = time.process_time()
            parts["read_and_ground"] += c1 - c0
            if item is None:
                break
            offline.drain(item, detector=detector, schedule=schedule, stats=stats)
            parts[part_of.get(type(item[2]), "read_and_ground")] += time.process_time() - c1
    wall = time.perf_counter() - t0
    messages = max(stats.messages, 1)
    per = {f"{k}_ms": round(1000.0 * v / messages, 1) for k, v in parts.items()}
    total = sum(parts.values())
    return {**per, "cpu_ms_per_message": round(1000.0 * total / messages, 1),
            "wall_s": round(wall, 3), "real_time_factor": round(stats.bag_seconds / wall, 2)}


def bench_dem_updates(seconds: float) -> dict:
    from lidar_obstacles.config import DemBuilderConfig, replace
    from lidar_obstacles.core.pipeline import DemPipeline
    from lidar_obstacles.core.simulate import SimSettings, simulate_flight

    out = {}
    frames = list(simulate_flight(SimSettings(scene="mixed", seed=2, duration=seconds)))
    for method in ("tin", "idw", "kriging"):
        cfg = replace(DemBuilderConfig(), {"dem.interpolation": method})
        pipe = DemPipeline(cfg)
        every = max(int(round(10 / cfg.dem.publish_rate)), 1)  # 10 Hz clouds
        times, reads = [], []
        for i, f in enumerate(frames):
            xyz = np.column_stack([f.points["x"], f.points["y"], f.points["z"]]).astype(float)
            t0 = time.perf_counter()
            pipe.process(xyz, stamp=f.stamp, vehicle_xyz=f.position,
                         intensity=f.points["intensity"])
            t1 = time.perf_counter()
            times.append(t1 - t0)
            if i % every == every - 1:  # the node publishes the filled grid at publish_rate
                pipe.dem.snapshot()
                reads.append(time.perf_counter() - t1)
        t, r = np.array(times[3:]), np.array(reads[1:] or reads)  # first ones warm caches
        out[method] = {"p50_ms": 1e3 * float(np.percentile(t, 50)),
                       "p95_ms": 1e3 * float(np.percentile(t, 95)),
                       "publish_p95_ms": 1e3 * float(np.percentile(r, 95)) if r.size else None}
    return out


def bench_live_latency(seconds: float, out: Path, with_dem_builder: bool = False,
                       scene: str = "mixed", dem_from_ground: bool = False) -> dict:
    """Publish -> `obstacles` latency of the obstacle_detector executable on a simulated
    `scene`; with `with_dem_builder`, the dem_builder executable runs beside it on the same
    clouds, as on a UAV running both (they share the cores), taking the detector's
    `ground` instead (`dem.ground_source: input`) with `dem_from_ground`. A node that does
    not stop leaves its log in `out`."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from lidar_obstacles.core.simulate import SimSettings, simulate_flight
    from lidar_obstacles.ros import messages

    env = dict(os.environ, ROS_DOMAIN_ID=os.environ.get("ROS_DOMAIN_ID")
               or str(random.randint(1, 101)), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    os.environ.update(env)
    frames = list(simulate_flight(SimSettings(scene=scene, seed=3, duration=seconds)))

    logs = tempfile.TemporaryDirectory()

    def start(name: str, *ros_args: str) -> subprocess.Popen:
        exe = Path(sys.executable).parent / name
        cmd = ([str(exe)] if exe.exists()
               else [sys.executable, "-m", f"lidar_obstacles.scripts.{name}"])
        cmd += ["--ros-args", *ros_args] if ros_args else []
        with open(Path(logs.name) / f"{name}.log", "w") as log:
            return subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)

    dem_args = ("-r", "points:=ground", "-p", "dem.ground_source:=input") \
        if dem_from_ground else ()
    procs = [start("obstacle_detector")] + ([start("dem_builder", *dem_args)]
                                            if with_dem_builder else [])
    rclpy.init()
    node = rclpy.create_node("latency_bench")
    qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(PointCloud2, "points", qos)
    sent: dict[int, float] = {}
    latencies: list[float] = []

    def on_obstacles(msg: PointCloud2) -> None:
        stamp = messages.stamp_ns_of(msg.header)
        if stamp in sent:
            latencies.append(time.perf_counter() - sent.pop(stamp))

    node.create_subscription(PointCloud2, "obstacles", on_obstacles, qos)
    # The node's own processing time (its diagnostics: decode, detect, build the messages),
    # to tell it apart from transport and queueing in the end-to-end figure.
    from diagnostic_msgs.msg import DiagnosticArray

    node_side: dict[str, str] = {}

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.startswith("obstacle_detector"):
                node_side.update({kv.key: kv.value for kv in status.values})

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
    try:
        deadline = time.monotonic() + 60
        on_points = 1 if dem_from_ground else len(procs)  # (that dem_builder takes `ground`)
        while pub.get_subscription_count() < on_points and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
        time.sleep(2.0)  # the node switches its subscription to reliable within 1 s
        msgs = [messages.cloud(f.points, messages.header(int(f.stamp * 1e9) + 1, "map"))
                for f in frames]
        next_t = time.perf_counter()
        for msg in msgs:
            while time.perf_counter() < next_t:
                rclpy.spin_once(node, timeout_sec=max(0.0, next_t - time.perf_counter()))
            sent[messages.stamp_ns_of(msg.header)] = time.perf_counter()
            pub.publish(msg)
            next_t += 0.1
        end = time.monotonic() + 5
        while sent and time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
        end = time.monotonic() + 1.5  # one more diagnostics message, with the last clouds
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        for proc in procs:
            proc.send_signal(signal.SIGINT)
        slow_exits = stopped_nodes(procs, Path(logs.name), out)
        logs.cleanup()
    lat = np.array(latencies[5:]) if len(latencies) > 10 else np.array(latencies)
    return {"published": len(frames), "received": len(latencies),
            "p50_ms": 1e3 * float(np.percentile(lat, 50)) if lat.size else None,
            "p95_ms": 1e3 * float(np.percentile(lat, 95)) if lat.size else None,
            "node_processing_p50_ms": float(node_side.get("latency_p50_ms", "nan")),
            "node_processing_p95_ms": float(node_side.get("latency_p95_ms", "nan")),
            "nodes_not_stopped_in_20_s": slow_exits}


LARGE_DATA_PROFILE = Path(__file__).resolve().parents[1] / "config" / "fastdds_large_data.xml"
PROFILE_VARIABLE = "FASTRTPS_DEFAULT_PROFILES_FILE"


def live_latency(seconds: float, out: Path, *, large_data: bool = False, **kwargs) -> dict:
    """`bench_live_latency` in a process of its own, which it and the nodes it starts run
    with Fast DDS's default transports (a 1.6 MB cloud goes by UDP: over the default 512 kB
    shared-memory segment) or, with `large_data`, the shipped profile's 64 MB segment.
    Fast DDS reads its profile once per process, hence the fresh one (spawned: it starts
    from nothing, as the nodes do)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    saved = os.environ.pop(PROFILE_VARIABLE, None)
    if large_data:
        os.environ[PROFILE_VARIABLE] = str(LARGE_DATA_PROFILE)
    try:
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            result = pool.submit(bench_live_latency, seconds, out, **kwargs).result()
    finally:
        os.environ.pop(PROFILE_VARIABLE, None)
        if saved is not None:
            os.environ[PROFILE_VARIABLE] = saved
    return {**result, "fastdds_profile": str(LARGE_DATA_PROFILE) if large_data else None}


def _p50_p95(res: dict) -> str:
    return "-" if res["p50_ms"] is None else f"{res['p50_ms']:.0f} / {res['p95_ms']:.0f}"


def stopped_nodes(procs: list[subprocess.Popen], logs: Path, out: Path) -> list[str]:
    """Wait up to 20 s for the nodes sent SIGINT to exit; one that has not is asked for its
    threads' stacks (SIGUSR1, see run_node), which go to out/stuck_<node>.log, and
    killed. Returns the names of those nodes."""
    stuck = []
    for proc in procs:
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            name = Path(proc.args[-1]).name.split(".")[-1]
            proc.send_signal(signal.SIGUSR1)
            time.sleep(1.0)
            proc.kill()
            proc.wait()
            log = logs / f"{name}.log"
            (out / f"stuck_{name}.log").write_text(log.read_text() if log.exists() else "")
            print(f"warning: {name} did not stop within 20 s of SIGINT (stacks: "
                  f"{out / f'stuck_{name}.log'})", file=sys.stderr)
            stuck.append(name)
    return stuck


def bench_memory(minutes: float, every: int) -> dict:
    """Resident memory sampled every `every` messages (when the nodes trim it: 100)."""
    from lidar_obstacles.config import DemBuilderConfig, ObstacleDetectorConfig
    from lidar_obstacles.core.arrays import release_free_memory
    from lidar_obstacles.core.pipeline import DemPipeline, ObstacleDetector
    from lidar_obstacles.core.simulate import SimSettings, simulate_flight

    det, dem = ObstacleDetector(ObstacleDetectorConfig()), DemPipeline(DemBuilderConfig())
    settings = SimSettings(scene="mixed", seed=4, duration=minutes * 60)
    n = int(minutes * 60 * settings.rate)
    samples = []
    from tqdm import tqdm

    for i, f in enumerate(tqdm(simulate_flight(settings), total=n, desc="memory", disable=None)):
        xyz = np.column_stack([f.points["x"], f.points["y"], f.points["z"]]).astype(float)
        det.process(xyz, stamp=f.stamp, vehicle_xyz=f.position)
        dem.process(xyz, stamp=f.stamp, vehicle_xyz=f.position, intensity=f.points["intensity"])
        if i % 10 == 0:
            dem.dem.snapshot()  # the DEM is published once a second
        if i % every == 0:
            # The nodes hand freed pages back every 10 s: resident size right after, and
            # the peak (what the machine must have), over the flight.
            release_free_memory()
            samples.append((i, rss_mb(), peak_mb()))
    ref = next(s for s in samples if s[0] >= n // 10)
    return {"minutes": minutes, "messages": n, "rss_after_10pct_mb": round(ref[1], 1),
            "rss_end_mb": round(samples[-1][1], 1),
            "growth": round(samples[-1][1] / ref[1] - 1.0, 4),
            "peak_after_10pct_mb": round(ref[2], 1), "peak_end_mb": round(samples[-1][2], 1),
            "peak_growth": round(samples[-1][2] / ref[2] - 1.0, 4),
            # the trend: a leak climbs steadily, one heavy message steps the peak once
            "samples": [{"message": i, "rss_mb": round(r, 1), "peak_mb": round(pk, 1)}
                        for i, r, pk in samples]}


def main() -> None:
    from lidar_obstacles.core.arrays import reuse_freed_memory, single_threaded_blas

    single_threaded_blas()  # as the nodes and the CLI run
    reuse_freed_memory()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=None, help="memory-test flight length")
    ap.add_argument("--memory-only", action="store_true",
                    help="only the memory test; writes pipeline_memory.json")
    args = bench_args(__doc__, "short flights",
                      "2 s flights, memory sampled every 2 messages", ap)
    seconds = per_mode(args, 30.0, 10.0, 2.0)
    minutes = args.minutes if args.minutes is not None else per_mode(args, 5.0, 1.0, 2 / 60)
    # memory first: its peak is the process's, and the other parts hold whole flights
    memory = bench_memory(minutes, every=per_mode(args, 100, 100, 2))
    if args.memory_only:
        print(f"| measure | value | target |\n|---|---|---|\n"
              f"| memory growth over {minutes:g} min (after the 10 s trims) | "
              f"{memory['growth']:.3g} ({memory['rss_after_10pct_mb']} -> "
              f"{memory['rss_end_mb']} MB) | < 0.10 |\n"
              f"| peak memory growth over {minutes:g} min | {memory['peak_growth']:.3g} | - |")
        (args.out / "pipeline_memory.json").write_text(json.dumps(memory, indent=2))
        return
    live = seconds / 2
    res = {"replay": bench_replay(seconds), "dem_update": bench_dem_updates(seconds / 2),
           "live_latency": live_latency(live, args.out),
           "live_latency_large_data": live_latency(live, args.out, large_data=True),
           "live_latency_with_dem_builder": live_latency(live, args.out, with_dem_builder=True),
           "live_latency_with_dem_builder_from_ground": live_latency(
               live, args.out, with_dem_builder=True, dem_from_ground=True),
           "live_latency_forest": live_latency(live, args.out, scene="forest"),
           "live_latency_forest_large_data": live_latency(live, args.out, scene="forest",
                                                          large_data=True),
           "memory": memory}
    rep, serial = res["replay"], res["replay"]["serial"]
    targets = [
        ("replay, x real time", rep["real_time_factor"], ">= 5"),
        (f"  its CPU per message over its three processes, ms (cores busy "
         f"{100 * rep['core_utilisation']:.0f} %)", rep["cpu_ms_per_message"], "-"),
        ("  the same work in one process, ms (read + ground / obstacles + messages / DEM)",
         f"{serial['cpu_ms_per_message']:.1f} ({serial['read_and_ground_ms']:.1f} / "
         f"{serial['obstacles_and_messages_ms']:.1f} / {serial['dem_ms']:.1f})", "-"),
        (f"  the ceiling the CPU allows on {rep['cores']} cores, x real time",
         rep["real_time_factor_ceiling"], "-"),
        ("  in one process, x real time", serial["real_time_factor"], "-"),
        ("live obstacles latency p95, ms", res["live_latency"]["p95_ms"], "<= 100"),
        ("  of which in the node (p95 of its processing), ms",
         res["live_latency"]["node_processing_p95_ms"], "-"),
        ("  the same with the large-data profile, ms", res["live_latency_large_data"]["p95_ms"],
         "<= 100"),
        ("live obstacles latency p95 with dem_builder running beside it, ms",
         res["live_latency_with_dem_builder"]["p95_ms"], "-"),
        ("  the same, dem_builder taking the detector's ground (dem.ground_source: input), ms",
         res["live_latency_with_dem_builder_from_ground"]["p95_ms"], "-"),
        ("live obstacles latency p50 / p95 over the forest scene, ms",
         _p50_p95(res["live_latency_forest"]), "-"),
        ("  the same with the large-data profile, ms",
         _p50_p95(res["live_latency_forest_large_data"]), "-"),
        ("DEM update p95 (tin), ms", res["dem_update"]["tin"]["p95_ms"], "<= 50"),
        ("DEM update p95 (idw), ms", res["dem_update"]["idw"]["p95_ms"], "<= 50"),
        ("DEM publish p95 (tin / idw / kriging), ms",
         " / ".join(f"{res['dem_update'][m]['publish_p95_ms']:.0f}"
                    for m in ("tin", "idw", "kriging")), "-"),
        (f"memory growth over {minutes:g} min (after the 10 s trims)", res["memory"]["growth"],
         "< 0.10"),
        (f"peak memory growth over {minutes:g} min", res["memory"]["peak_growth"], "-"),
    ]
    print("| measure | value | target |\n|---|---|---|")
    for name, value, target in targets:
        shown = f"{value:.3g}" if isinstance(value, float) else str(value)
        print(f"| {name} | {shown} | {target} |")
    (args.out / "pipeline.json").write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
