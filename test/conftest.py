"""Shared test setup: isolated DDS, paths to the shared real data."""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import pytest

# Every test run gets its own DDS domain and never talks beyond this machine.
os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random(os.getpid()).randint(1, 101)))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"


def data_file(relative: str) -> Path:
    """Path of a file in ../shared/data, or skip the test with the reason."""
    path = DATA / relative
    if not path.is_file():
        pytest.skip(f"shared data not present: {path}")
    return path


def interrupt_while_importing(args: list[str], heavy: Callable[[str], bool], delay: float,
                              sig: int = signal.SIGINT) -> tuple[int, str]:
    """Run ``python -X importtime ARGS``, send it `sig` `delay` s after the first module for
    which `heavy(name)` holds has been imported (-X importtime prints each module as its
    import ends), and return its exit status and stderr.

    The moment is the process's own, not a clock's, so a loaded machine cannot move the
    signal out of the imports. Fails the test when the process ends before such a module."""
    proc = subprocess.Popen([sys.executable, "-X", "importtime", *args], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    seen: list[str] = []

    def imported() -> None:
        for line in proc.stderr:  # "import time: self | cumulative | module"
            seen.append(line)
            if line.startswith("import time:") and heavy(line.rsplit("|", 1)[-1].strip()):
                break
        else:
            pytest.fail("it ended before its modules were imported:\n" + "".join(seen))
        time.sleep(delay)

    _, rest = signal_when(proc, imported, sig)
    return proc.returncode, "".join(seen) + rest


def signal_when(proc: subprocess.Popen, ready: Callable[[], None], sig: int,
                timeout: float = 120.0) -> tuple[str | None, str | None]:
    """Call ready() (it waits for the moment, or fails the test), send proc `sig` and return
    the rest of its (stdout, stderr). The process is killed and reaped whatever happens, so
    a failing test leaves none behind."""
    try:
        ready()
        proc.send_signal(sig)
        return proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def stop_inside_exec(module: str, tmp_path: Path) -> dict[str, str]:
    """The environment of a process that sends itself SIGINT inside code exec() runs from
    a string, when `module` is first imported (a `sitecustomize` in tmp_path): as a Ctrl-C
    lands in the methods dataclasses and typing make so while modules are imported."""
    (tmp_path / "sitecustomize.py").write_text(
        "import os, signal, sys\n"
        "class StopInsideExec:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        f"        if name == {module!r}:\n"
        "            sys.meta_path.remove(self)\n"
        "            exec('os.kill(os.getpid(), signal.SIGINT)', {'os': os, 'signal': signal})\n"
        "sys.meta_path.insert(0, StopInsideExec())\n")
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(REPO)]))


def signal_at_import(entry: str, module: str, sig: int = signal.SIGINT, *,
                     in_callback: bool = False) -> str:
    """A script that runs ``main()`` of `entry` (a module, as a console script does) and
    sends itself `sig` when `module` is first imported: the signal comes inside that
    import, wherever it is made (a C extension's: numpy's of datetime), at a moment no
    machine load can move. With `in_callback`, the signal comes inside a weakref's
    callback there, whose exceptions Python prints ("Exception ignored in") and drops, as
    it does for importlib's own module locks."""
    send = f"signal.raise_signal({int(sig)})"  # (the handler runs before it returns)
    if in_callback:
        send = (f"held = type('Held', (), {{}})()\n"
                f"            keep = weakref.ref(held, lambda ref: {send})\n"
                f"            del held")
    return (f"import signal, sys, weakref\n"
            f"class Signal:\n"
            f"    def find_spec(self, name, path=None, target=None):\n"
            f"        if name == {module!r}:\n"
            f"            sys.meta_path.remove(self)\n"
            f"            {send}\n"
            f"sys.meta_path.insert(0, Signal())\n"
            f"from {entry} import main\n"
            f"sys.exit(main())\n")


@pytest.fixture(scope="module")
def ros_node():
    """A node of the test module's own, to listen and call services with (rclpy started for
    it, and shut down after the module)."""
    rclpy = pytest.importorskip("rclpy")
    rclpy.init()
    node = rclpy.create_node("test_listener")
    yield node
    node.destroy_node()
    rclpy.try_shutdown()
