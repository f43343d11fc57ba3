"""The node executables' console scripts: a stop signal while a node is still importing its
modules (rclpy, the messages, numpy: ~0.5 s) stops it as one does later, when it runs."""
from __future__ import annotations

import re
import signal
import subprocess
import sys

import pytest

from conftest import REPO, interrupt_while_importing, signal_at_import

# The node executables as setup.py installs them: name -> module of main
NODES = dict(re.findall(r'"(\w+) = (lidar_obstacles\.[\w.]+):main"',
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
