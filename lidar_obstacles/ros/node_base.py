"""The frame the three nodes (obstacle_detector, dem_builder, cloud_simplifier) share:
parameters from the schema, input QoS that follows the publishers, optional odometry,
an inbox of `input.depth` clouds worked on by its own thread (a cloud pushed out of it by
newer ones while the node was busy is counted, not lost without a trace),
diagnostics, throttled warnings for rejected clouds, and the Jazzy-style main with clean
shutdown."""
from __future__ import annotations

import bisect
import collections
import faulthandler
import os
import signal
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import Any, Callable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.executors import (Executor, ExternalShutdownException,
                             MultiThreadedExecutor, SingleThreadedExecutor)
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSPolicyKind,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import PointCloud2

from lidar_obstacles.core.arrays import (release_free_memory, reuse_freed_memory,
                                         single_threaded_blas)
from lidar_obstacles.core.pipeline import RESTART_AFTER_S
from lidar_obstacles.errors import ConfigError, LidarObstaclesError, count_reason
from lidar_obstacles.ros import messages
from lidar_obstacles.ros.params import declare_config, on_parameter_change
from lidar_obstacles.ros.stages import (Pose, coarse_xyz_warning, missing_frame_warning,
                                        moving_frame_warning, pose_of_odometry, pose_problem)

WARN_THROTTLE_S = 5.0


def output_qos(depth: int = 2, transient_local: bool = False) -> QoSProfile:
    """Outputs: reliable (both kinds of subscriber connect), keep-last, small depth."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if transient_local
                                  else DurabilityPolicy.VOLATILE))


def create_output(node: Node, msg_type, topic: str, *, depth: int = 2,
                  transient_local: bool = False):
    """A publisher of an output (`output_qos`), whose QoS the user may override at start
    the ROS 2 way, `-p qos_overrides./ns/clearance.publisher.durability:=transient_local`
    (a Nav2 costmap layer subscribes transient-local); such parameters were accepted and
    did nothing. Each publisher gets a profile of its own: rclpy writes a topic's overrides
    into the profile it is given, and one profile shared by a node's outputs carried them
    to every output made after it (`/dem`'s durability made `/dem_image` volatile too)."""
    overridable = QoSOverridingOptions([QoSPolicyKind.HISTORY, QoSPolicyKind.DEPTH,
                                        QoSPolicyKind.RELIABILITY, QoSPolicyKind.DURABILITY])
    return node.create_publisher(msg_type, topic, output_qos(depth, transient_local),
                                 qos_overriding_options=overridable)


# Odometry kept in the subscription's queue: a few seconds of 20-50 Hz poses, so that a
# busy executor drops none (they are small).
ODOMETRY_DEPTH = 50


class _FollowingInput:
    """A node's subscription to one input topic, keep-last `depth`, made anew when the
    reliability it should have changes (`PipelineNode._update_inputs`); `on_lost` counts
    the messages the middleware reports lost."""

    def __init__(self, topic: str, msg_type: Any, callback: Callable[[Any], None], depth: int,
                 on_lost: Callable[[Any], None] | None = None) -> None:
        self.topic, self.msg_type, self.callback = topic, msg_type, callback
        self.depth, self.on_lost = depth, on_lost
        self.subscription: Any = None
        self.reliability: ReliabilityPolicy | None = None

    def subscribe(self, node: Node, reliability: ReliabilityPolicy) -> bool:
        """Subscribed with `reliability`: whether that took a new subscription."""
        if reliability == self.reliability:
            return False
        if self.subscription is not None:
            node.destroy_subscription(self.subscription)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.depth,
                         reliability=reliability)
        events = (SubscriptionEventCallbacks(message_lost=self.on_lost)
                  if self.on_lost is not None else None)
        self.subscription = node.create_subscription(self.msg_type, self.topic, self.callback,
                                                     qos, event_callbacks=events)
        self.reliability = reliability
        return True


# Poses in a row stamped more than RESTART_AFTER_S before the newest held that tell the
# clock went back; fewer are a glitch (one pose of another clock). As many or more held
# after them are an earlier run's; fewer, a glitch ahead.
CLOCK_JUMP_POSES = 3


class PoseBuffer:
    """Odometry poses of the last few seconds, looked up by nearest stamp. Thread-safe:
    the executor adds poses while the worker thread looks them up, and may wait for them."""

    def __init__(self, horizon_s: float = 10.0) -> None:
        self.horizon_ns = int(horizon_s * 1e9)
        self._stamps: collections.deque[int] = collections.deque()
        self._poses: collections.deque[Pose] = collections.deque()
        self._jumped: list[Pose] = []  # poses in a row from before the newest (`_add`)
        self._lock = threading.Condition()

    def add(self, pose: Pose) -> str | None:
        """Hold `pose`; or, when it cannot place a cloud, not, and say why."""
        problem = pose_problem(pose)
        if problem is not None:
            return problem
        with self._lock:
            self._add(pose)
            self._lock.notify_all()
        return None

    def _add(self, pose: Pose) -> None:
        newest = self._stamps[-1] if self._stamps else None
        if newest is not None and pose.stamp_ns < newest - RESTART_AFTER_S * 1e9:
            # Stamped more than a second before the newest held: the clock went back (a
            # bag played again) once CLOCK_JUMP_POSES in a row say so; fewer are a glitch,
            # left out. One such pose emptied the buffer, and the clouds then waiting for
            # their poses were dropped.
            self._jumped.append(pose)
            if len(self._jumped) < CLOCK_JUMP_POSES:
                return
            after = bisect.bisect_right(self._stamps, max(p.stamp_ns for p in self._jumped)
                                        + RESTART_AFTER_S * 1e9)
            if len(self._stamps) - after < CLOCK_JUMP_POSES:
                keep = after  # a glitch ahead (a pose or two stamped far later): it goes
            else:
                keep = 0  # the clock went back: all that is held is of the earlier run
            while len(self._stamps) > keep:
                self._stamps.pop()
                self._poses.pop()
            jumped, self._jumped = self._jumped, []
            for p in jumped:
                self._insert(p)
            return
        self._jumped.clear()
        # a pose far ahead of the newest (odometry back after a gap, or a glitch) does not
        # age the others out: the poses after it do, by their own stamps
        self._insert(pose, age_out=newest is None
                     or pose.stamp_ns <= newest + RESTART_AFTER_S * 1e9)

    def _insert(self, pose: Pose, age_out: bool = True) -> None:
        # a pose a little late (best-effort odometry reordered, two publishers) goes in
        # its place: it emptied the buffer, and the clouds waited or were dropped
        at = bisect.bisect_right(self._stamps, pose.stamp_ns)
        self._stamps.insert(at, pose.stamp_ns)
        self._poses.insert(at, pose)
        while age_out and self._stamps and self._stamps[0] < pose.stamp_ns - self.horizon_ns:
            self._stamps.popleft()
            self._poses.popleft()

    def nearest(self, stamp_ns: int, max_age_s: float, wait_s: float = 0.0) -> Pose | None:
        """The pose nearest to stamp_ns among those held, if no more than max_age_s away
        (before or after it: odometry's `odometry_max_age` is a tolerance either side);
        else None. With wait_s > 0, a pose that is not there yet is waited for, up to
        wait_s seconds (wall clock), unless later poses show none will come close: live,
        odometry may arrive after the cloud it belongs to (a busy executor, a lost
        best-effort message), and the cloud would be dropped for no fault of its own."""
        deadline = time.monotonic() + wait_s
        with self._lock:
            while True:
                pose = self._nearest(stamp_ns, max_age_s)
                left = deadline - time.monotonic()
                past = self._stamps and self._stamps[-1] > stamp_ns + max_age_s * 1e9
                if pose is not None or past or left <= 0:
                    return pose
                self._lock.wait(left)

    def _nearest(self, stamp_ns: int, max_age_s: float) -> Pose | None:
        if not self._stamps:
            return None
        stamps = list(self._stamps)
        i = bisect.bisect_left(stamps, stamp_ns)
        best = min((j for j in (i - 1, i) if 0 <= j < len(stamps)),
                   key=lambda j: abs(stamps[j] - stamp_ns))
        if abs(stamps[best] - stamp_ns) > max_age_s * 1e9:
            return None
        return self._poses[best]


class PipelineNode(Node):
    """Base of `obstacle_detector`, `dem_builder` and `cloud_simplifier`.

    Subclasses give the config class, make their stage (`self.stage`) and its publishers
    (`self.pubs`, by topic). The stage is used on the worker thread; anything else that
    touches it (a timer, a service) holds `self.stage_lock`. Parameter changes reach the
    stage on the worker thread, before the next cloud (`reconfigure`).

    Clouds: the subscription's callback only puts each cloud in an inbox of `input.depth`
    clouds (keep-last, as the subscription); the worker thread takes them from there, the
    oldest first. A cloud pushed out of a full inbox before the worker took it is counted
    (`dropped_superseded`): the node was busy, and the newest scans are what a flight
    stack needs. Clouds the middleware reports lost are counted (`lost`).
    """

    config_cls: type
    out_key: str = "points_out"  # the stage's stats entry counted as points out
    # what a cloud that starts the stream over makes the node forget (`note_restart`)
    remembers: str = "nothing"
    stage: Any  # made by the subclass: DetectorStage, DemStage or SimplifierStage
    pubs: dict[str, Any]  # its publishers, by topic

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.cfg = declare_config(self, self.config_cls)
        self.stage_lock = threading.Lock()
        self._config_lock = threading.Lock()
        self._new_cfg: Any = None  # accepted, not yet given to the stage
        self._stage_cfg = self.cfg  # the stage's
        on_parameter_change(self, lambda: self.cfg, self._apply_config)
        self.poses = PoseBuffer()
        self._warned: set[int | str] = set()  # the kinds of warning about the clouds said
        # The inputs, each subscribed with the reliability of its publishers (re-checked
        # every second): `points` as `input.reliability` says; `odom` always so. Odometry
        # was best effort, and beside a reliable player's big clouds it lost 8-22 of 80
        # poses, in runs of 3-4, and clouds were dropped for want of them.
        self._inputs = {
            "points": _FollowingInput("points", PointCloud2, self._on_points,
                                      self.cfg.input.depth, self._on_lost),
            "odom": _FollowingInput("odom", Odometry, self._on_odometry, ODOMETRY_DEPTH)}
        self._update_inputs()
        # On the steady clock, not the node's: with use_sim_time and no /clock yet (a bag
        # played without --clock, or paused) ROS-time timers never fire, and the input
        # stayed best effort against a reliable publisher, losing big clouds, with no
        # diagnostics to tell.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0, self._update_inputs, clock=steady)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(1.0, self._publish_diagnostics, clock=steady)
        self.create_timer(10.0, release_free_memory, clock=steady)  # flat memory, long flights
        self.stats: dict[str, Any] = {"received": 0, "processed": 0, "rejected": 0,
                                      "dropped_no_pose": 0, "dropped_superseded": 0,
                                      "lost": 0, "failed": 0, "points_in": 0,
                                      "points_out": 0, "odometry_ignored": 0,
                                      "restarts": 0}
        self.reject_reasons: collections.Counter[str] = collections.Counter()
        self._dropped_reported = 0  # clouds dropped as of the last diagnostics
        self._received_reported = 0  # ... and received
        self._warned_at: dict[str, float] = {}  # the last warning of each kind of drop
        self.latencies: collections.deque[float] = collections.deque(
            maxlen=messages.LATENCY_WINDOW)
        self.recv_times: collections.deque[float] = collections.deque(
            maxlen=messages.RATE_WINDOW)
        self._inbox: collections.deque[PointCloud2] = collections.deque(
            maxlen=self.cfg.input.depth)  # (read-only: fixed for the node's life)
        self._inbox_lock = threading.Lock()
        self._size_checked = False  # the first cloud's size (`messages.large_cloud_hint`)
        self._wake = threading.Event()
        self._stopping = False
        self.stop_now = False  # set: stop without waiting for the cloud in hand
        self._worker = threading.Thread(target=self._work, name=f"{name}-worker", daemon=True)
        self._worker.start()

    # ---------------------------------------------------------------- configuration
    def _apply_config(self, cfg: Any) -> None:
        """An accepted parameter change, on the executor. It must not wait for the stage:
        the cloud in hand may take seconds (a big one, `ground.method: tin`), and the
        parameter services, diagnostics and odometry would wait as long (a revert timed
        out). The stage takes it before the next cloud (`_take_config`)."""
        with self._config_lock:
            self.cfg = cfg
            self._new_cfg = cfg

    def _take_config(self) -> Any:
        """The config of the cloud about to be handled (`stage_lock` held): one set since
        the last cloud goes to the stage first."""
        with self._config_lock:
            cfg, self._new_cfg = self._new_cfg, None
        if cfg is not None:
            self.reconfigure(cfg)
            self._stage_cfg = cfg
        return self._stage_cfg

    def reconfigure(self, cfg: Any) -> None:
        """New parameters go to the stage (`self.stage`), for the next cloud."""
        self.stage.reconfigure(cfg)

    # ---------------------------------------------------------------- input QoS
    def _wanted_reliability(self, topic: str) -> ReliabilityPolicy:
        mode = self.cfg.input.reliability if topic == "points" else "auto"
        if mode == "reliable":
            return ReliabilityPolicy.RELIABLE
        if mode == "best_effort":
            return ReliabilityPolicy.BEST_EFFORT
        infos = self.get_publishers_info_by_topic(self.resolve_topic_name(topic))
        # `auto`: reliable only when every publisher is reliable; best effort matches any.
        if infos and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos):
            return ReliabilityPolicy.RELIABLE
        return ReliabilityPolicy.BEST_EFFORT

    def _update_inputs(self) -> None:
        """Each input subscribed anew where its publishers' reliability asks for another."""
        for topic, following in self._inputs.items():
            wanted = self._wanted_reliability(topic)
            if following.subscribe(self, wanted):
                kind = "reliable" if wanted == ReliabilityPolicy.RELIABLE else "best effort"
                self.get_logger().info(f"subscribed to {self.resolve_topic_name(topic)} "
                                       f"({kind})")

    # ---------------------------------------------------------------- processing
    def _on_points(self, msg: PointCloud2) -> None:
        """The executor's callback: the cloud goes to the inbox, nothing more (the first
        one's size is checked against Fast DDS's transport, once)."""
        if not self._size_checked:
            self._size_checked = True
            hint = messages.large_cloud_hint(len(msg.data), self.resolve_topic_name("points"))
            if hint is not None:
                self.get_logger().warning(hint)
        self.stats["received"] += 1
        self.recv_times.append(time.monotonic())
        with self._inbox_lock:
            if len(self._inbox) == self._inbox.maxlen:
                self.stats["dropped_superseded"] += 1  # the oldest goes
            self._inbox.append(msg)
        self._wake.set()

    def _on_lost(self, event: Any) -> None:
        self.stats["lost"] += int(event.total_count_change)

    def _work(self) -> None:
        """The worker thread: the clouds in the inbox, oldest first, until stopped."""
        while True:
            self._wake.wait()
            if self._stopping:
                return
            with self._inbox_lock:
                msg = self._inbox.popleft() if self._inbox else None
                if not self._inbox:
                    self._wake.clear()
            if msg is not None:
                with self.stage_lock:
                    self._handle(msg)
            try:
                with self.stage_lock:
                    self.between_clouds()
            except Exception:  # noqa: BLE001 - as for a cloud: logged, and the node goes on
                if not self._stopping and self.context.ok():
                    self.get_logger().error(f"failed between clouds (a bug, please report "
                                            f"it):\n{traceback.format_exc()}",
                                            throttle_duration_sec=WARN_THROTTLE_S)

    def wake(self) -> None:
        """Have the worker thread run `between_clouds` soon (from any thread)."""
        self._wake.set()

    def between_clouds(self) -> None:
        """The node's own work on the worker thread (`stage_lock` held), after each cloud
        and on `wake`, off the executor: none here (the DEM builder makes its grid)."""

    def begin_stop(self) -> None:
        """No more clouds: the worker thread ends after the one in hand, and a service
        waiting on it (save_dem) answers that the node is stopping."""
        self._stopping = True
        self._wake.set()

    def destroy_node(self) -> None:
        self.begin_stop()
        if self._worker is not threading.current_thread():
            # The cloud in hand, 10 s at most, unless asked again to stop: a second Ctrl-C,
            # or launch's SIGTERM 5 s after its SIGINT. The worker, a daemon, is left to its
            # cloud (its publish fails on the destroyed node, which it knows is stopping).
            deadline = time.monotonic() + 10.0
            while (self._worker.is_alive() and not self.stop_now
                   and time.monotonic() < deadline):
                self._worker.join(timeout=0.1)
        super().destroy_node()

    def _handle(self, msg: PointCloud2) -> None:
        cfg = self._take_config()
        stamp_ns = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        pose = self.poses.nearest(stamp_ns, cfg.odometry_max_age,
                                  cfg.odometry_wait if cfg.use_odometry else 0.0)
        if cfg.use_odometry and pose is None:
            self._reject("no odometry pose near the cloud's stamp", counter="dropped_no_pose")
            return
        for kind, warning in enumerate((
                moving_frame_warning(msg.header.frame_id, pose, cfg.use_odometry),
                coarse_xyz_warning(msg, pose, cfg), missing_frame_warning(msg.header.frame_id))):
            # each kind once (rclpy's `once` is per line of code: one line for all of them
            # said only the first kind that came)
            if warning is not None and kind not in self._warned:
                self._warned.add(kind)
                self.get_logger().warning(warning)
        t0 = time.perf_counter()
        try:
            n_in, n_out = self.process_cloud(msg, pose)
        except LidarObstaclesError as exc:
            self._reject(str(exc))
            return
        except Exception as exc:  # noqa: BLE001 - beside a flight stack a bug must not
            # take the node down: the cloud is dropped, counted and logged with its trace
            if self._stopping or not self.context.ok():
                return  # the context was shut down under the cloud in hand
            self.stats["failed"] += 1
            self.reject_reasons[f"internal error: {type(exc).__name__}"] += 1
            self.get_logger().error(f"failed on a cloud (a bug, please report it):\n"
                                    f"{traceback.format_exc()}",
                                    throttle_duration_sec=WARN_THROTTLE_S)
            return
        self.latencies.append(time.perf_counter() - t0)
        self.stats["processed"] += 1
        self.stats["points_in"] += int(n_in)
        self.stats["points_out"] += int(n_out)

    def process_cloud(self, msg: PointCloud2, pose: Pose | None) -> tuple[int, int]:
        """Run the stage on one cloud and publish what it returns, each message on
        `self.pubs[topic]`; the points in and out go to the diagnostics: the points the
        stage processed (the finite ones: an organized cloud's NaN padding, its missing
        returns, are no points; `replay` counts the same) and the stats' `out_key`.
        Stages that publish on their own schedule (the DEM) override this."""
        outputs, stats = self.stage.process(msg, pose)
        self.note_restart(stats.get("restart", ""))
        for topic, out in outputs:
            self.pubs[topic].publish(out)
        return stats["points_in"], stats[self.out_key]

    def note_restart(self, why: str) -> None:
        """Count, and say, a cloud that started the stream over (`why`; "" when it did
        not): what the node remembered of the clouds before it is forgotten."""
        if why:
            self.stats["restarts"] += 1
            self.get_logger().warning(f"started afresh, forgetting {self.remembers}: {why}",
                                      throttle_duration_sec=WARN_THROTTLE_S)

    def _on_odometry(self, msg: Odometry) -> None:
        problem = self.poses.add(pose_of_odometry(msg))
        if problem is not None:  # left out: its clouds wait for a good pose, or are dropped
            self.stats["odometry_ignored"] += 1
            self.get_logger().warning(f"ignored an odometry message: {problem}",
                                      throttle_duration_sec=WARN_THROTTLE_S)

    def _reject(self, reason: str, counter: str = "rejected") -> None:
        self.stats[counter] += 1
        key = count_reason(self.reject_reasons, reason)
        # throttled per kind: one shared throttle said only the first of two alternating
        # reasons, and the other was only a count
        now = time.monotonic()
        if now - self._warned_at.get(key, float("-inf")) >= WARN_THROTTLE_S:
            self._warned_at[key] = now
            self.get_logger().warning(f"dropped a cloud: {reason}")

    # ---------------------------------------------------------------- diagnostics
    def _publish_diagnostics(self) -> None:
        self.diag_pub.publish(messages.diagnostics(
            # named by the node's namespace too ("uav1/obstacle_detector: processing"): two
            # vehicles' nodes share the global /diagnostics, and monitors tell them apart
            # by name (hardware_id stays the fully qualified name)
            self._diag_header(), self.get_fully_qualified_name().lstrip("/"),
            self.get_fully_qualified_name(),
            # copies: the worker thread counts while this (the executor's) thread reads, and
            # a new reason meanwhile stopped the node ("dictionary changed size")
            dict(self.stats), dict(self.reject_reasons), list(self.latencies),
            messages.rate_hz(self.recv_times, time.monotonic()), self.extra_diagnostics(),
            dropped_before=self._dropped_reported, received_before=self._received_reported))
        self._dropped_reported = messages.dropped(self.stats)
        self._received_reported = self.stats["received"]

    def extra_diagnostics(self) -> dict[str, str]:
        """Node-specific values for the diagnostics (the DEM's accuracy at its check
        points); none here."""
        return {}

    def _diag_header(self):
        from std_msgs.msg import Header

        return Header(stamp=self.get_clock().now().to_msg())


class StopSignals:
    """SIGINT and SIGTERM ask the node to stop; the spin loop stops between callbacks.

    rclpy's own handlers are not installed: on a signal they shut the context down and
    trigger the executors' guard conditions from a thread of their own, while the main
    thread, woken by the KeyboardInterrupt, destroys the node and shuts the same context
    down. That race crashed a node with SIGSEGV on Ctrl-C (once in CI; 300 stops here did not).
    Here the handler only notes the signal; the byte Python's C-level handler writes to a
    pipe wakes a thread that triggers a guard condition of the node, whose (empty)
    callback ends the executor's wait. The stop is prompt, and everything after it runs on
    the main thread, in order.

    A signal while the node stops (it waits for the cloud in hand) sets the node's
    `stop_now`; the handlers stay until the end, so that signal neither kills the node
    half-way (SIGTERM's default) nor raises a KeyboardInterrupt into its cleanup."""

    def __init__(self) -> None:
        self.received: int | None = None
        self._node: Any = None
        self._guard: Any = None
        self._lock = threading.Lock()
        self._read_fd, self._write_fd = os.pipe()
        os.set_blocking(self._write_fd, False)
        self._previous = {sig: signal.signal(sig, self._note)
                          for sig in (signal.SIGINT, signal.SIGTERM)}
        self._previous_wakeup_fd = signal.set_wakeup_fd(self._write_fd, warn_on_full_buffer=False)
        threading.Thread(target=self._wake, name="stop-signals", daemon=True).start()

    def _note(self, signum: int, frame: Any) -> None:
        if self.received is not None and self._node is not None:
            self._node.stop_now = True
        self.received = signum

    def _wake(self) -> None:
        while os.read(self._read_fd, 1):
            with self._lock:
                if self._guard is not None:
                    self._guard.trigger()

    def watch(self, node: Node) -> None:
        """Wake the executor spinning `node` on a signal."""
        with self._lock:
            self._guard = node.create_guard_condition(lambda: None)
        self._node = node

    def unwatch(self) -> None:
        """The executor is no longer woken (before the node and its guard condition go)."""
        with self._lock:
            self._guard = None

    def restore(self) -> None:
        """Back to the signal handling before."""
        self.unwatch()
        signal.set_wakeup_fd(self._previous_wakeup_fd)
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def _ros_options(argv: list[str], option: str) -> list[str]:
    """The values of `option` (e.g. --params-file) among the --ros-args of `argv`, in
    order; for -r / --remap, the rules."""
    names = ("-r", "--remap") if option in ("-r", "--remap") else (option,)
    inside, values = False, []
    for arg, nxt in zip(argv, [*argv[1:], None]):
        if arg == "--ros-args":
            inside = True
        elif arg == "--":
            inside = False
        elif inside and arg in names and nxt is not None:
            values.append(nxt)
    return values


def _missing_params_file(argv: list[str]) -> str | None:
    """The first `--params-file PATH` of the --ros-args in `argv` that is not a file."""
    return next((p for p in _ros_options(argv, "--params-file") if not Path(p).is_file()),
                None)


def _check_params_files(argv: list[str], cls: type | None) -> None:
    """Read each --params-file of `argv` as `replay` and `evaluate` read it, for node
    config `cls` under its namespace (-r __ns:=): ConfigError for what rcl takes silently
    or says in lines of its own (a section none of our nodes has, `obstacle_detektor:`;
    another node's parameter out of its range; bad YAML). Under a remapped node name
    (-r __node:=NAME) the file's sections are that name's."""
    from lidar_obstacles.config import NODE_CONFIGS, load_params_file

    name = next((k for k, c in NODE_CONFIGS.items() if c is cls), None)
    if name is None or cls is None:
        return
    namespace = "/"
    for rule in _ros_options(argv, "-r"):
        # a rule for one node only, `obstacle_detector:__ns:=/uav1`, is this node's when
        # it names it (and none of its business when it names another)
        target, sep, rest = rule.partition(":")
        if sep and not rest.startswith("="):
            if target != name:
                continue
            rule = rest
        if rule.startswith(("__node:=", "__name:=")):
            return  # (its sections are named otherwise: rcl's word stands)
        if rule.startswith("__ns:="):
            namespace = "/" + rule.split(":=", 1)[1].strip("/")
    full_name = namespace.rstrip("/") + "/" + name
    for path in _ros_options(argv, "--params-file"):
        # Only the sections rcl gives the node `full_name` are read and checked (a file of
        # one section per vehicle: /uav1's is not /uav2's business); a file that keys this
        # node only in sections that do not reach it (`obstacle_detector:` under
        # `-r __ns:=/uav1`, where the node ran on its defaults without a word) is refused.
        load_params_file(path, cls, name, full_name=full_name)


def node_executor(factory: Callable[[], Node]) -> Executor:
    """The executor a node runs on: one thread, unless the node's services wait for its
    worker thread (`services_wait`, dem_builder's save_dem): then a second thread runs
    them, in a callback group of their own, while the first serves the rest."""
    if getattr(factory, "services_wait", False):
        return MultiThreadedExecutor(num_threads=2)
    return SingleThreadedExecutor()


def _finish_callbacks(executor: Executor) -> None:
    """Let the callbacks a MultiThreadedExecutor has handed to its threads finish, before
    `shutdown()` destroys the guard condition they signal when done. Jazzy's rclpy (7.1)
    neither waits for them there nor closes its threads (ros2/rclpy#1309, backported later
    as #1670): a handler that ran after it (one whose mutually exclusive callback group was
    busy) raised "cannot use Destroyable because destruction was requested", printed at
    exit as "The following exception was never retrieved" on every stop of dem_builder.
    The spin loop has ended on this thread, so nothing more is handed over (the race of
    ros2/rclpy#1724 needs spin on another thread)."""
    from concurrent.futures import ThreadPoolExecutor

    pool = getattr(executor, "_executor", None)  # (rclpy's private pool; a newer rclpy's
    if isinstance(pool, ThreadPoolExecutor):  # shutdown has closed it: this is then a no-op)
        pool.shutdown(wait=True)


def spin_until(executor: Executor, stopped: Callable[[], bool]) -> None:
    """Spin `executor` until `stopped()`. An entity destroyed while a wait set was being
    built (rclpy's InvalidHandle) is passed over: `input.reliability: auto` re-creates the
    input subscription from a timer, which a multi-threaded executor (`dem_builder`'s)
    runs on another thread, and the wait set built meanwhile held the old subscription's
    event handler (rclpy 7.1; a CI run lost its dem_builder so, exit 1). The next wait set
    is built without it."""
    from rclpy._rclpy_pybind11 import InvalidHandle

    while not stopped():
        try:
            executor.spin_once()
        except InvalidHandle:
            continue


def run_node(factory: Callable[[], Node], args: list[str] | None = None) -> int:
    """Jazzy-style main: init, spin, and on SIGINT/SIGTERM destroy the node and shut down.

    A bad parameter (out of range, unknown to every node, or a params file rcl cannot
    read) ends with one line on stderr and exit status 2.
    """
    # First: a signal from here on stops the node cleanly (the console scripts'
    # handlers, lidar_obstacles.scripts, cover the imports before).
    stop = StopSignals()
    from rclpy._rclpy_pybind11 import RCLError
    from rclpy.signals import SignalHandlerOptions

    single_threaded_blas()
    reuse_freed_memory()
    # A crash prints every thread's stack to stderr, and `kill -USR1 <pid>` does too for a
    # node that does not stop, or stalls (it keeps running).
    faulthandler.enable(all_threads=True)
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    argv = args if args is not None else sys.argv
    program = Path(sys.argv[0]).stem or "node"
    missing = _missing_params_file(argv)
    if missing is not None:  # said here: rcl would add a line of its own ("[ERROR] [rcl]")
        print(f"{program}: error: params file {missing} "
              f"{'is a folder' if Path(missing).is_dir() else 'not found'}", file=sys.stderr)
        return 2
    try:  # (the same reasons: one line, before rcl's)
        _check_params_files(argv, getattr(factory, "config_cls", None))
    except ConfigError as exc:
        print(f"{program}: error: {exc}", file=sys.stderr)
        return 2
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except RCLError as exc:  # a --ros-args mistake: a params file that rcl cannot read
        print(f"{program}: error: {str(exc).split(', at ')[0]}", file=sys.stderr)
        return 2
    node = None
    executor = node_executor(factory)  # (after init: it needs the context)
    try:
        node = factory()
        executor.add_node(node)
        stop.watch(node)
        spin_until(executor, lambda: stop.received is not None)
    except ConfigError as exc:
        print(f"{program}: error: {exc}", file=sys.stderr)
        return 2
    except ExternalShutdownException:
        pass
    finally:
        stop.unwatch()
        if node is not None:  # (a save_dem waiting on the worker answers now, not after it)
            getattr(node, "begin_stop", lambda: None)()
        _finish_callbacks(executor)
        executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        stop.restore()
    return 0
