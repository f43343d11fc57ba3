"""The node executables' console scripts: `obstacle_detector`, `dem_builder` and
`cloud_simplifier`.

A console script imports its module before it calls ``main``, where a Ctrl-C can be caught;
the node modules import rclpy, the message packages and numpy (~0.5 s), so a Ctrl-C in that
time printed a traceback (and a SIGINT to a node started in the background, where it is
ignored, was lost). These modules import only the standard library: :func:`start` sets
the stop signals first, then imports the node. A signal while the node is imported stops
it as a signal does later, once it runs: exit status 0, and one line instead of the
traceback.
"""
from __future__ import annotations

import importlib
import os
import signal
import sys
from typing import Callable, NoReturn


_RECEIVED: list[int] = []  # the stop signals received while the node was imported


def _on_signal(signum: int, frame: object) -> None:
    """Note the signal, then raise KeyboardInterrupt where the import is. Noted, because
    the exception need not come out as itself: raised in an import that a C extension
    makes (numpy's of datetime), it comes out as an ImportError, and a library that takes
    that for a missing module goes on without it."""
    _RECEIVED.append(signum)
    raise KeyboardInterrupt


def quiet_interrupts_in_callbacks() -> Callable[[], None]:
    """While a stop signal handler raises where the program is, a signal can land in a
    callback whose exceptions Python prints and drops: a weakref's (importlib's module
    locks have one) or a ``__del__``. It printed "Exception ignored in ..." and a traceback
    for the KeyboardInterrupt (once in CI, a SIGTERM 0.1 s into a node's imports). The
    handlers note every signal, and their callers act on the note, so that exception is not
    lost with this hook; others are printed as before. Returns what puts the previous hook
    back."""
    previous = sys.unraisablehook

    def hook(unraisable: "sys.UnraisableHookArgs") -> None:
        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            previous(unraisable)

    sys.unraisablehook = hook
    return lambda: setattr(sys, "unraisablehook", previous)


# What each node does, and its topics (relative names), for --help.
_ABOUT = {
    "obstacle_detector": ("ground, obstacles and their classes, markers and a clearance grid "
                          "of every cloud",
                          "points (PointCloud2), odom (Odometry, with use_odometry)",
                          "ground, obstacles, obstacle_edges (PointCloud2), obstacle_markers "
                          "(MarkerArray), clearance (OccupancyGrid), /diagnostics"),
    "dem_builder": ("a rolling DEM of the ground of every cloud",
                    "points (PointCloud2), odom (Odometry, with use_odometry)",
                    "dem (PointCloud2), dem_image (Image), dem_info (MapMetaData), "
                    "/diagnostics; service save_dem (Trigger: a GeoTIFF)"),
    "cloud_simplifier": ("every cloud simplified by K-means++ on its normals",
                         "points (PointCloud2), odom (Odometry, with use_odometry)",
                         "points_simplified (PointCloud2), "
                         "/diagnostics"),
}


def usage(name: str) -> str:
    """`<node> --help`: what the node does, its topics and every parameter with its default
    and unit (from the config schema, which imports no ROS)."""
    from lidar_obstacles.config import NODE_CONFIGS, params_of

    about, inputs, outputs = _ABOUT[name]
    lines = [f"usage: {name} [--ros-args [-p NAME:=VALUE]... [--params-file FILE] "
             "[-r __ns:=/NS] [-r points:=TOPIC]...]", "",
             f"ROS 2 node: {about}.", f"  subscribes: {inputs}", f"  publishes:  {outputs}",
             "", "parameters (default, unit; descriptions and ranges in "
             f"share/lidar_obstacles/config/{name}.yaml, or `ros2 param describe`):"]
    for info in params_of(NODE_CONFIGS[name]):
        unit = f" {info.spec.unit}" if info.spec.unit not in ("", "1") else ""
        lines.append(f"  {info.name} = {info.default!r}{unit}")
    return "\n".join(lines) + "\n"


def start(name: str, args: list[str] | None) -> int:
    """Run node `name` (its module in lidar_obstacles.ros, whose ``main`` takes the
    command line `args`) and return its exit status; with -h or --help before any
    --ros-args, print :func:`usage` instead. The node's own handlers
    (:class:`~lidar_obstacles.ros.node_base.StopSignals`) take over from these once it is
    imported."""
    argv = sys.argv[1:] if args is None else args
    ours = argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv
    if "-h" in ours or "--help" in ours:
        sys.stdout.write(usage(name))
        return 0
    # Ctrl-C as Python has it, also where a shell started the node in the background with
    # SIGINT ignored (`kill -INT` then stops it, as it does the running node); SIGTERM too.
    _RECEIVED.clear()  # (of an earlier call in this process)
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    restore_hook = quiet_interrupts_in_callbacks()
    try:
        node = importlib.import_module(f"lidar_obstacles.ros.{name}")
        if _RECEIVED:
            raise KeyboardInterrupt  # (taken for a missing module, or dropped by a callback)
        return node.main(args)
    except BaseException:
        if not _RECEIVED:
            raise
        # a stop asked for, as when the node runs (status 0): no traceback
        word = "terminated" if _RECEIVED[-1] == signal.SIGTERM else "interrupted"
        print(f"{name}: {word}", file=sys.stderr)
        return 0
    finally:
        restore_hook()


def exit_process(status: int, *, stopped: bool) -> NoReturn:
    """End a program run with ``python -m`` with `status`: at once, its output flushed, when
    it was `stopped` by a signal, else as usual.

    Python ends a process run with -m by SIGINT (status -2), whatever status it asked
    for, when a KeyboardInterrupt ever left code that exec() ran from a string, even one
    caught later: dataclasses and typing make their methods so while modules are imported,
    and a Ctrl-C landing there is noted as unhandled and acted on at exit. A console
    script or ``python -c`` exits on SystemExit before that check. Everything the program
    has to undo on a stop is undone by then (its own ``finally`` blocks).

    From here on the stop signals are ignored: the node has stopped, and a second Ctrl-C
    landing in the interpreter's ~0.2 s of teardown killed it by the signal (status 130 or
    143 with nothing said; launch reports such a node as died). Ignored, not handled:
    Python's teardown puts its own handlers' signals back to the default before the end,
    and leaves ignored ones be."""
    for stop in (signal.SIGINT, signal.SIGTERM):
        signal.signal(stop, signal.SIG_IGN)
    if stopped:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a reader gone, a stream closed: nothing to lose
                pass
        os._exit(status)
    raise SystemExit(status)


def exit_as_module(name: str) -> NoReturn:
    """The node executables (`console`) and `python -m lidar_obstacles.scripts.<name>`:
    run node `name` with the process's command line and exit with its status."""
    status = start(name, None)
    exit_process(status, stopped=bool(_RECEIVED))
