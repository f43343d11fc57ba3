"""The node executables' console scripts: a stop signal while a node is still importing its
modules (rclpy, the messages, numpy: ~0.5 s) stops it as one does later, when it runs."""
from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import (REPO, interrupt_while_importing, signal_at_import, signal_when,
                      stop_inside_exec)

# The node executables as setup.py installs them: name -> module of main
NODES = dict(re.findall(r'"(\w+) = (lidar_obstacles\.[\w.]+):console"',
                        (REPO / "setup.py").read_text()))
NODES.pop("lidar", None)  # (`lidar-obstacles` has a test of its own, in test_cli)


def _heavy(module: str) -> bool:
    """A module of the node's own imports, not of Python's start: numpy, rclpy, rosidl
    and the message packages."""
    return re.match(r"(numpy|rclpy|rosidl_\w+|\w+_(msgs|srvs|interfaces))(\.|$)",
                    module) is not None


def test_every_node_executable_is_checked():
    assert set(NODES) == {"obstacle_detector", "dem_builder", "cloud_simplifier"}


@pytest.mark.parametrize("name", sorted(NODES))
@pytest.mark.parametrize("delay, sig", [(0.0, signal.SIGINT), (0.03, signal.SIGINT),
                                        (0.1, signal.SIGINT), (0.3, signal.SIGINT),
                                        (0.1, signal.SIGTERM)])
def test_a_stop_signal_while_the_node_imports_its_modules_stops_it_cleanly(name, delay, sig):
    """What the console script runs (its module, then main) is sent the signal `delay` s
    after the first heavy module has been imported: the node module imported rclpy, the
    messages and numpy before its main could catch anything, and a Ctrl-C there printed a
    traceback (exit -2). Now the node stops as a signal stops it once it runs: status 0,
    at most one line of its own, no traceback. The delays land in the imports (~0.5 s)
    and, the longest, in rclpy's start."""
    script = f"import sys\nfrom {NODES[name]} import main\nsys.exit(main())\n"
    code, err = interrupt_while_importing(["-c", script, "--ros-args", "-r", "__ns:=/start"],
                                          _heavy, delay, sig)
    said = [x for x in err.splitlines()
            if not x.startswith("import time:") and not re.match(r"\[(INFO|WARN)\]", x)]
    word = "interrupted" if sig == signal.SIGINT else "terminated"
    assert code == 0 and "Traceback" not in err, err[-3000:]
    assert said in ([], [f"{name}: {word}"]), said


@pytest.mark.parametrize("name", sorted(NODES))
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_signal_inside_an_import_a_c_extension_makes_stops_the_node_cleanly(name, sig):
    # numpy's C core imports datetime: the KeyboardInterrupt raised there comes out of
    # numpy as an ImportError ("Importing the numpy C-extensions failed ... bad install")
    proc = subprocess.run([sys.executable, "-c", signal_at_import(NODES[name], "datetime", sig),
                           "--ros-args", "-r", "__ns:=/start"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    word = "interrupted" if sig == signal.SIGINT else "terminated"
    assert (proc.returncode, proc.stderr) == (0, f"{name}: {word}\n")


@pytest.mark.parametrize("name", sorted(NODES))
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_signal_inside_a_weakref_callback_stops_the_node_without_a_traceback(name, sig):
    """A signal 0.1 s into a node's imports once landed in the weakref callback of one of
    importlib's module locks (in CI): Python printed the KeyboardInterrupt raised there
    as "Exception ignored in ..." with its traceback. Here the signal comes inside such a
    callback while rclpy is imported."""
    proc = subprocess.run([sys.executable, "-c",
                           signal_at_import(NODES[name], "rclpy", sig, in_callback=True),
                           "--ros-args", "-r", "__ns:=/start"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    word = "interrupted" if sig == signal.SIGINT else "terminated"
    assert (proc.returncode, proc.stderr) == (0, f"{name}: {word}\n")


@pytest.mark.parametrize("name", sorted(NODES))
def test_a_node_run_as_a_module_stops_cleanly_when_the_stop_lands_inside_an_exec(name, tmp_path):
    """`python -m lidar_obstacles.scripts.<node>` (what the tests and the benchmarks run in a
    checkout without the executables): a Ctrl-C raised inside code that exec() runs from a
    string is noted by the interpreter as unhandled, even when caught later, and a process
    started with -m then kills itself by SIGINT at exit. The node said `interrupted` and
    still ended with status -2 (one CI run in session 21); now it exits 0."""
    proc = subprocess.run([sys.executable, "-m", NODES[name], "--ros-args", "-r", "__ns:=/start"],
                          cwd=REPO, env=stop_inside_exec("rclpy", tmp_path), capture_output=True,
                          text=True, timeout=120)
    assert (proc.returncode, proc.stderr) == (0, f"{name}: interrupted\n")


@pytest.mark.parametrize("name", sorted(NODES))
def test_a_node_run_as_a_module_where_no_executable_is_installed_stops_cleanly_too(name):
    """The same form, sent a Ctrl-C while it imports rclpy, wherever the signal lands: status
    0 and no traceback. Run as `-m lidar_obstacles.ros.<node>`, the node module's own
    imports came first."""
    assert NODES[name] == f"lidar_obstacles.scripts.{name}"
    code, err = interrupt_while_importing(["-m", NODES[name], "--ros-args", "-r", "__ns:=/start"],
                                          _heavy, 0.1)
    assert code == 0 and "Traceback" not in err, err[-3000:]
    said = [x for x in err.splitlines()
            if not x.startswith("import time:") and not re.match(r"\[(INFO|WARN)\]", x)]
    assert said in ([], [f"{name}: interrupted"]), said


@pytest.mark.parametrize("name", sorted(NODES))
def test_help_prints_the_topics_and_parameters_without_starting_the_node(name):
    """`obstacle_detector --help` started the node (it ran until killed). Now it prints the
    usage, the topics and every parameter of the schema with its default, and exits 0
    without importing rclpy; after --ros-args, -h is ROS's business and is passed on."""
    from lidar_obstacles.config import NODE_CONFIGS, params_of

    res = subprocess.run([sys.executable, "-c", f"import sys; from {NODES[name]} import main; "
                          "code = main(['--help']); "
                          "assert 'rclpy' not in sys.modules; sys.exit(code)"],
                         cwd=REPO, capture_output=True, text=True, timeout=30)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith(f"usage: {name} [--ros-args")
    assert "subscribes: points (PointCloud2)" in res.stdout
    listed = re.findall(r"^  ([\w.]+) = ", res.stdout, re.MULTILINE)
    assert listed == [info.name for info in params_of(NODE_CONFIGS[name])]


MULTI = ("/uav1/obstacle_detector:\n  ros__parameters:\n    ground.cell: 1.5\n{uav1}"
         "/uav2/obstacle_detector:\n  ros__parameters:\n    ground.cell: 2.0\n")


def _parameter_of_a_started_node(params: Path, namespace: str, name: str,
                                 timeout: float = 60.0) -> tuple[float | None, str]:
    """Start obstacle_detector under `namespace` with the params file and ask it for the
    value of the double parameter `name`: (the value, None if it never answered; its log)."""
    import time

    import rclpy
    from rcl_interfaces.srv import GetParameters
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    proc = subprocess.Popen([sys.executable, "-m", NODES["obstacle_detector"], "--ros-args",
                             "-r", f"__ns:={namespace}", "--params-file", str(params)],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    probe = rclpy.create_node("node_start_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(probe)
    value = None
    try:
        client = probe.create_client(GetParameters,
                                     f"{namespace}/obstacle_detector/get_parameters")
        deadline = time.monotonic() + timeout
        while value is None and proc.poll() is None and time.monotonic() < deadline:
            if not client.wait_for_service(timeout_sec=0.5):
                continue
            # asked again every 5 s: a request sent as the service is discovered can be lost
            future = client.call_async(GetParameters.Request(names=[name]))
            executor.spin_until_future_complete(future, timeout_sec=5.0)
            if future.done():
                value = future.result().values[0].double_value
    finally:
        executor.shutdown()
        probe.destroy_node()
        rclpy.try_shutdown(context=context)
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            log = proc.communicate(timeout=20)[0]
        except subprocess.TimeoutExpired:
            proc.kill()
            log = proc.communicate()[0]
    return value, log


@pytest.mark.parametrize("uav1", ["", "    ground.method: magic\n", "    ground.cell: -1.0\n"
                                  "    dem.resolution: 0.5\n    tiling.sise: 30.0\n"])
def test_a_node_takes_its_own_section_of_a_params_file_with_one_per_vehicle(tmp_path, uav1):
    """A params file of one section per vehicle, given to the node under /uav2: it exited 2,
    "section '/uav1/obstacle_detector' does not reach the node /uav2/obstacle_detector",
    and a bad value in /uav1's section stopped it too. Now it runs with /uav2's value."""
    params = tmp_path / "multi.yaml"
    params.write_text(MULTI.format(uav1=uav1))
    value, log = _parameter_of_a_started_node(params, "/uav2", "ground.cell")
    assert value == 2.0, log
    assert "error" not in log and "Traceback" not in log, log


def test_a_node_named_only_in_other_vehicles_sections_is_refused_in_one_line(tmp_path):
    # what the check is for: rcl would give the node none of it, without a word
    params = tmp_path / "multi.yaml"
    params.write_text(MULTI.format(uav1=""))
    proc = subprocess.run([sys.executable, "-m", NODES["obstacle_detector"], "--ros-args",
                           "-r", "__ns:=/uav3", "--params-file", str(params)],
                          cwd=REPO, capture_output=True, text=True, timeout=60)
    assert (proc.returncode, proc.stderr) == (2, (
        f"obstacle_detector: error: params file {params}: section '/uav1/obstacle_detector' "
        "does not reach the node /uav3/obstacle_detector (rcl matches the whole name): key it "
        "'/uav3/obstacle_detector' or '/**/obstacle_detector'\n"))


def test_a_remap_rule_for_this_node_only_sets_its_namespace(tmp_path):
    """`-r obstacle_detector:__ns:=/uav1` (a rule naming the node) is valid ROS 2 and rclpy
    applies /uav1's section under it; the check before the node starts took the namespace
    for / and refused the file. A rule for another node is none of this one's business."""
    from lidar_obstacles.config import ObstacleDetectorConfig
    from lidar_obstacles.errors import ConfigError
    from lidar_obstacles.ros.node_base import _check_params_files

    params = tmp_path / "uav1.yaml"
    params.write_text("/uav1/obstacle_detector:\n  ros__parameters:\n    ground.cell: 2.0\n")
    rules = ["-r", "obstacle_detector:__ns:=/uav1"]
    _check_params_files(["--ros-args", *rules, "--params-file", str(params)],
                        ObstacleDetectorConfig)
    with pytest.raises(ConfigError, match="does not reach the node /uav2/obstacle_detector"):
        _check_params_files(["--ros-args", "-r", "dem_builder:__ns:=/uav1", "-r",
                             "__ns:=/uav2", "--params-file", str(params)],
                            ObstacleDetectorConfig)


@pytest.mark.parametrize("second", [signal.SIGINT, signal.SIGTERM])
def test_a_second_stop_signal_as_the_stopped_node_exits_changes_nothing(second):
    """Ctrl-C twice (or launch's SIGTERM after its SIGINT) killed an idle node by the
    second signal (status 130 / 143, nothing said): it landed in the interpreter's teardown,
    after the node had stopped and its handlers were gone. Now ignored there: status 0."""
    proc = subprocess.Popen([sys.executable, "-m", NODES["obstacle_detector"], "--ros-args",
                             "-r", "__ns:=/second_stop"], cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)

    def first_stop() -> None:
        while "ready" not in (line := proc.stderr.readline()):
            assert line, "the node ended before it was ready"
        proc.send_signal(signal.SIGINT)
        time.sleep(0.02)  # (the node stops in milliseconds: the second comes in its exit)

    err = signal_when(proc, first_stop, second, timeout=30)[1]
    assert proc.returncode == 0 and "Traceback" not in err, (proc.returncode, err)
