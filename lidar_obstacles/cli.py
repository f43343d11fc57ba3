"""`lidar-obstacles`: the command-line tool.

Each subcommand prints a JSON summary on stdout; progress bars go to stderr. Bad input of
any kind ends with one line on stderr naming the problem and exit status 2.

This module is what the console script imports before it calls :func:`main`, where Ctrl-C is
caught: it imports only the standard library's light modules, so that the heavy ones
(numpy, rclpy, ... ~0.3 s) are imported inside main and an interrupt then ends as any other.
"""
from __future__ import annotations

import argparse
import re
import signal
import sys
from pathlib import Path
from typing import NoReturn

from lidar_obstacles.errors import ConfigError, LidarObstaclesError  # (imports only re)

SCENES = ("mixed", "corridor", "urban", "forest")


def _between(low: float, high: float, kind: type = float):
    """An argparse type: a number of `kind` in [low, high] (a rate of 1e-300 overflows a
    timer, a tile of 1e-300 m is no tile)."""
    def parse(text: str) -> float:
        value = kind(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must lie in [{low:g}, {high:g}], got {text}")
        return value
    parse.__name__ = kind.__name__  # argparse names the type in "invalid int value"
    return parse


# ROS 2 names: tokens of letters, digits and underscores (not starting with a digit),
# joined by single slashes, with one in front or none.
_TOKENS = r"[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*"


def _topic(text: str) -> str:
    """A topic of a bag, whose names are absolute: `points` is the root namespace's, as a
    node with no namespace would resolve it (it was not found beside `/points`)."""
    if not re.fullmatch(rf"/?{_TOKENS}", text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a valid ROS 2 topic name")
    return text if text.startswith("/") else "/" + text


def _frame_id(text: str) -> str:
    # tf2 names: no leading slash (REP-105), not empty (tf2 rejects an empty frame)
    if not re.fullmatch(_TOKENS, text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a valid frame id (e.g. map)")
    return text


def _namespace(text: str) -> str:
    if text and not re.fullmatch(rf"/?{_TOKENS}", text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a valid ROS 2 namespace "
                                         "(e.g. /uav1)")
    return text


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Appends "(default: X)" to each option's help, except where the help already says
    what the default is: a default of None or "" would print as "(default: None)" or
    "(default: )", which tells nothing, so those options say what happens in their help."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if "(default" in (action.help or "") or action.default in (None, ""):
            return action.help
        return super()._get_help_string(action)


class _Parser(argparse.ArgumentParser):
    """A usage mistake is bad input like any other: one line and exit status 2 (argparse
    would print the whole usage first). Defaults are shown in --help."""

    commands: dict[str, _Parser]  # the top parser's: each command's own

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


# What an option's default of None means when it names a params file.
_DEFAULT_PARAMS = "(default: none, the defaults in config/*.yaml)"


def build_parser() -> _Parser:
    from lidar_obstacles import __version__

    p = _Parser(prog="lidar-obstacles", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p.commands = sub.choices  # (name -> its parser)

    s = sub.add_parser("demo", help="simulate a UAV flight and run the whole job on it")
    s.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    s.add_argument("--scene", choices=SCENES, default="mixed", help="simulated scene")
    s.add_argument("--duration", type=_between(1e-3, 1e6), default=20.0, help="flight seconds")
    s.add_argument("--seed", type=int, default=0, help="random seed of the scene and flight")

    s = sub.add_parser("simulate", help="write a labelled synthetic UAV flight bag")
    s.add_argument("out", type=Path, metavar="OUT_BAG",
                   help="the bag to write (a folder; mcap unless --storage sqlite3)")
    s.add_argument("--seed", type=int, default=0, help="random seed of the scene and flight")
    s.add_argument("--scene", choices=SCENES, default="mixed", help="simulated scene")
    s.add_argument("--duration", type=_between(1e-3, 1e6), default=20.0,
                   help="seconds of flight")
    s.add_argument("--frame", choices=("map", "sensor"), default="map",
                   help="clouds in the map frame, or in the sensor frame (use odometry)")
    s.add_argument("--rate", type=_between(0.01, 1000.0), default=10.0,
                   help="clouds per second")
    s.add_argument("--points", type=_between(100, 1_000_000, int), default=50_000,
                   help="points per cloud")
    s.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                   help="rosbag2 storage of the output bag")

    s = sub.add_parser("las2bag", help="stream a LAS/LAZ survey as PointCloud2 messages")
    s.add_argument("src", type=Path, metavar="IN.las",
                   help="the survey, a LAS or LAZ file")
    s.add_argument("out", type=Path, metavar="OUT_BAG",
                   help="the bag to write")
    s.add_argument("--slice-seconds", type=_between(1e-3, 1e5), default=0.1,
                   help="GPS-time slice per message (and stamp spacing otherwise)")
    s.add_argument("--tile-size", type=_between(0.1, 1e6), default=None,
                   help="cut square tiles of this edge (m) instead of GPS slices/strips "
                        "(default: none, GPS slices/strips)")
    s.add_argument("--strip-width", type=_between(0.1, 1e6), default=10.0,
                   help="without GPS time: strips of this width (m) along the longer axis")
    s.add_argument("--topic", type=_topic, default="/points",
                   help="PointCloud2 topic to write")
    s.add_argument("--frame-id", type=_frame_id, default="map", help="frame_id of the clouds")
    s.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                   help="rosbag2 storage of the output bag")

    s = sub.add_parser("replay", help="run the pipeline offline on every cloud of a bag")
    s.add_argument("src", type=Path, metavar="IN_BAG",
                   help="a bag of PointCloud2 scans (rosbag2 mcap or sqlite3, or ROS 1 .bag)")
    s.add_argument("out", type=Path, metavar="OUT_BAG",
                   help="the bag of what the nodes would publish")
    s.add_argument("--topic", type=_topic, default=None,
                   help="PointCloud2 topic (default: the only/biggest)")
    s.add_argument("--params-file", type=Path, default=None,
                   help=f"ROS 2 params YAML {_DEFAULT_PARAMS}")
    s.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                   help="rosbag2 storage of the output bag")
    s.add_argument("--no-dem", action="store_true", help="skip the DEM builder")
    _skip_malformed_flag(s)

    s = sub.add_parser("play", help="publish a bag into the live ROS graph")
    s.add_argument("src", type=Path, metavar="IN_BAG",
                   help="the bag to publish")
    s.add_argument("--rate", type=_between(0.001, 1000.0), default=1.0, help="speed factor")
    s.add_argument("--loop", action="store_true",
                   help="start again from the beginning at the end, until Ctrl-C")
    s.add_argument("--topics", nargs="+", type=_topic, default=None,
                   help="only these bag topics (default: all)")
    s.add_argument("--namespace", type=_namespace, default="",
                   help="publish under this namespace, e.g. /uav1 (default: none, the bag's "
                        "topic names)")
    s.add_argument("--clock", nargs="?", type=_between(0.1, 1000.0), const=40.0, default=None,
                   metavar="HZ",
                   help="publish the bag's time on /clock, HZ times a second (40 when not "
                        "given) and at each message, for nodes with use_sim_time (as ros2 "
                        "bag play --clock; put it after IN_BAG) (default: none, no /clock)")

    s = sub.add_parser("export-dem", help="build the DEM of a bag and write a GeoTIFF")
    s.add_argument("src", type=Path, metavar="IN_BAG",
                   help="a bag of PointCloud2 scans")
    s.add_argument("out", type=Path, metavar="OUT.tif",
                   help="the GeoTIFF to write (a hillshade PNG goes beside it)")
    s.add_argument("--topic", type=_topic, default=None,
                   help="PointCloud2 topic (default: the only/biggest)")
    s.add_argument("--params-file", type=Path, default=None,
                   help=f"ROS 2 params YAML (`dem_builder`'s `dem.*`) {_DEFAULT_PARAMS}")
    s.add_argument("--crs", default=None,
                   help="e.g. EPSG:32632 (default: the params file's export.crs, else the "
                        "bag's)")
    _skip_malformed_flag(s)

    for name, what, params in (
            ("simplify", "K-means++ simplification on normals",
             "`cloud_simplifier`'s `simplify.*`"),
            ("features", "Gaussian-map feature points", "`obstacle_detector`'s `features.*`")):
        s = sub.add_parser(name, help=f"{what} of a LAS/LAZ file or a bag")
        s.add_argument("src", type=Path, metavar="IN", help="a LAS/LAZ file or a bag")
        s.add_argument("out", type=Path, metavar="OUT",
                       help="a .las/.laz file for a LAS/LAZ input, a bag for a bag")
        s.add_argument("--params-file", type=Path, default=None,
                       help=f"ROS 2 params YAML ({params}) {_DEFAULT_PARAMS}")
        s.add_argument("--topic", type=_topic, default=None,
                       help="PointCloud2 topic (default: the only/biggest)")
        s.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                       help="rosbag2 storage of an output bag")
        _skip_malformed_flag(s)

    s = sub.add_parser("evaluate", help="compare the classes with the `classification` field")
    s.add_argument("src", type=Path, metavar="IN",
                   help="a replay's output bag, a labelled bag or a LAS/LAZ file "
                        "(with --benchmark isprs: the folder of the 15 samples)")
    s.add_argument("--params-file", type=Path, default=None,
                   help=f"parameters of the pipeline run on a labelled input {_DEFAULT_PARAMS}")
    s.add_argument("--report", type=Path, default=None, metavar="DIR",
                   help="write report.html, metrics.json and PNGs here (default: no report)")
    s.add_argument("--blocks", default="6x6", help="grid of the per-block kappa, e.g. 6x6")
    s.add_argument("--topic", type=_topic, default=None,
                   help="PointCloud2 topic of a labelled bag (default: a replay's /ground and "
                        "/obstacles, else the only/biggest)")
    s.add_argument("--no-dem", action="store_true", help="skip the DEM comparison")
    s.add_argument("--benchmark", choices=("isprs",), default=None,
                   help="run all ISPRS samples in IN with one parameter set (default: none, IN "
                        "is one input)")
    _skip_malformed_flag(s)

    s = sub.add_parser("tune", help="search parameters on labelled inputs; write a params YAML")
    s.add_argument("src", type=Path, nargs="+", metavar="IN",
                   help="labelled bags or LAS/LAZ files used for the search")
    s.add_argument("--validate", type=Path, nargs="+", default=None, metavar="FILE",
                   help="held-out inputs scored with the result (default: none, or the last "
                        "input when several are given)")
    s.add_argument("--out", type=Path, default=Path("tuned.yaml"), help="params YAML to write")
    s.add_argument("--budget", default="10m", help="time budget, e.g. 90s, 10m, 1h")
    s.add_argument("--trials", type=_between(1, 1_000_000, int), default=200,
                   help="candidates at most")
    s.add_argument("--seed", type=int, default=0, help="random seed of the search")
    s.add_argument("--space", type=Path, default=None,
                   help="YAML narrowing the search: {name: [min, max] | [choice, ...]} "
                        "(default: every tunable parameter over its declared range)")
    s.add_argument("--start", type=Path, default=None,
                   help="params file of the first candidate (default: the defaults in "
                        "config/obstacle_detector.yaml)")
    s.add_argument("--objective", choices=("ground_kappa", "kappa", "total_error"),
                   default="ground_kappa",
                   help="what the search optimises (the kappas up, total_error down)")
    s.add_argument("--topic", type=_topic, default=None,
                   help="PointCloud2 topic of the labelled bags (default: a replay's /ground "
                        "and /obstacles, else the only/biggest)")
    _skip_malformed_flag(s)
    return p


def _skip_malformed_flag(s: argparse.ArgumentParser) -> None:
    s.add_argument("--skip-malformed", action="store_true",
                   help="skip a malformed cloud of a bag and count it in the summary's "
                        "`rejected`, as the nodes drop it (default: stop at it, one line "
                        "naming it, exit status 2)")


def run(args: argparse.Namespace) -> dict:
    from lidar_obstacles.io.atomic import check_not_input
    from lidar_obstacles.ros import offline

    src = getattr(args, "src", None)
    inputs = [*(src if isinstance(src, list) else [src] if src is not None else []),
              *([args.params_file] if getattr(args, "params_file", None) else []),
              *(getattr(args, "validate", None) or []),  # (tune's other inputs)
              *(f for f in (getattr(args, "space", None), getattr(args, "start", None)) if f)]
    for out in (getattr(args, "out", None), getattr(args, "report", None)):
        if out is not None:
            check_not_input(out, inputs)  # before any work: one line, exit 2

    if args.command == "simulate":
        return offline.simulate(args.out, scene=args.scene, seed=args.seed,
                                duration=args.duration, frame=args.frame, rate=args.rate,
                                points_per_frame=args.points, storage=args.storage)
    if args.command == "las2bag":
        return offline.las2bag(args.src, args.out, slice_seconds=args.slice_seconds,
                               tile_size=args.tile_size, strip_width=args.strip_width,
                               topic=args.topic, frame_id=args.frame_id, storage=args.storage)
    if args.command == "replay":
        return offline.replay(args.src, args.out, topic=args.topic,
                              params_file=args.params_file, storage=args.storage,
                              with_dem=not args.no_dem, skip_malformed=args.skip_malformed)
    if args.command == "play":
        return offline.play(args.src, rate=args.rate, loop=args.loop, topics=args.topics,
                            namespace=args.namespace, clock_hz=args.clock)
    if args.command == "export-dem":
        return offline.export_dem(args.src, args.out, topic=args.topic,
                                  params_file=args.params_file, crs=args.crs,
                                  skip_malformed=args.skip_malformed)
    if args.command in ("simplify", "features"):
        from lidar_obstacles.ros import cloud_tools

        tool = cloud_tools.simplify if args.command == "simplify" else cloud_tools.features
        return tool(args.src, args.out, params_file=args.params_file, topic=args.topic,
                    storage=args.storage, skip_malformed=args.skip_malformed)
    if args.command == "evaluate":
        from lidar_obstacles import evaluate

        if args.benchmark == "isprs":
            unused = [flag for flag, given in (
                ("--report", args.report is not None), ("--blocks", args.blocks != "6x6"),
                ("--topic", args.topic is not None), ("--no-dem", args.no_dem),
                ("--skip-malformed", args.skip_malformed)) if given]
            if unused:  # (they were ignored)
                raise ConfigError(f"--benchmark isprs takes only --params-file, not "
                                  f"{', '.join(unused)}")
            result = evaluate.benchmark_isprs(args.src, params_file=args.params_file)
            print(evaluate.isprs_table(result), file=sys.stderr)
            return result
        return evaluate.evaluate(args.src, params_file=args.params_file,
                                 report_dir=args.report, blocks=args.blocks, topic=args.topic,
                                 with_dem=not args.no_dem, skip_malformed=args.skip_malformed)
    if args.command == "tune":
        from lidar_obstacles import tune

        return tune.tune(args.src, validate=args.validate, out=args.out,
                         budget_s=tune.parse_budget(args.budget), max_trials=args.trials,
                         seed=args.seed, space_file=args.space, start_file=args.start,
                         objective=args.objective, topic=args.topic,
                         skip_malformed=args.skip_malformed)
    if args.command == "demo":
        from lidar_obstacles.demo import run_demo

        return run_demo(args.out, scene=args.scene, duration=args.duration, seed=args.seed,
                        say=lambda line: print(line, file=sys.stderr))
    raise AssertionError(args.command)  # argparse only lets known commands through


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the program is, so that it unwinds as on Ctrl-C: workers
    stopped, partial outputs removed."""


_RECEIVED: list[int] = []  # the stop signals received, the latest last
STOPS = (signal.SIGINT, signal.SIGTERM)


def _on_signal(signum: int, frame: object) -> None:
    """Note the signal, then raise KeyboardInterrupt (SIGINT) or _Terminated (SIGTERM)
    where the program is. Noted, because the exception need not come out as itself: raised
    in an import that a C extension makes (numpy's of datetime), it comes out as an
    ImportError, and a library that takes that for a missing module goes on without it."""
    _RECEIVED.append(signum)
    raise _Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _stopped(exc: BaseException) -> bool | None:
    """Whether `exc` ends the program because of a stop signal: None when it does not
    (a bug, to be raised), else True for SIGTERM, False for SIGINT."""
    if _RECEIVED:  # (KeyboardInterrupt, or what an interrupted import made of it)
        return _RECEIVED[-1] == signal.SIGTERM
    if isinstance(exc, KeyboardInterrupt):  # (raised, not signalled)
        return isinstance(exc, _Terminated)
    return None


def main(argv: list[str] | None = None) -> int:
    """Run a command; its exit status. A reader of stdout that stops early (`| head`) ends
    it quietly, as SIGPIPE ends other tools: status 141, no traceback. Ctrl-C (SIGTERM)
    before the command has begun, while its modules are imported, ends it as during the
    command: one line, status 130 (143), no traceback."""
    try:
        try:
            return _main(argv)
        finally:
            if sys.stdout is not None:  # (None: closed at the start)
                sys.stdout.flush()  # here, where a reader gone is caught, not at exit
    except BrokenPipeError:
        _stdout_to_devnull()  # so that Python's own flush at exit finds no pipe to fail on
        return 141
    except BaseException as exc:  # before _main's own handler: no command to name yet
        terminated = _stopped(exc)
        if terminated is None:
            raise
        print(f"lidar-obstacles: {'terminated' if terminated else 'interrupted'}",
              file=sys.stderr)
        return 143 if terminated else 130


def _main(argv: list[str] | None) -> int:
    """`_command`, the caller's signal handlers restored after it (for a caller in the same
    process: tests, scripts; an ignored SIGINT would be ignored by the processes they
    start afterwards too)."""
    from lidar_obstacles.scripts import quiet_interrupts_in_callbacks

    before = {stop: signal.getsignal(stop) for stop in STOPS}
    restore_hook = quiet_interrupts_in_callbacks()  # (while _on_signal raises)
    try:
        return _command(argv)
    finally:
        for stop, handler in before.items():
            signal.signal(stop, handler)
        restore_hook()


def _command(argv: list[str] | None) -> int:
    _RECEIVED.clear()  # (of an earlier call in this process)
    # Ctrl-C as Python has it, also where the shell started the command in the background
    # with SIGINT ignored: `kill -INT` stops it as Ctrl-C does. First, so that the imports
    # below stop the same way (main catches what comes before the command's own try).
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    from lidar_obstacles.core.arrays import reuse_freed_memory, single_threaded_blas  # numpy

    if _RECEIVED:
        raise KeyboardInterrupt  # (taken for a missing module, or dropped by a callback)

    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # said by the subcommand, whose --help lists its options
        parser.commands[args.command].error(f"unrecognized arguments: {' '.join(extra)}")
    single_threaded_blas()
    reuse_freed_memory()
    try:
        summary = run(args)
    except LidarObstaclesError as exc:
        print(f"lidar-obstacles {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        # The machine's, not the input's: a full disk, no permission, a read-only or vanished
        # folder. One line too (the outputs are temporary until complete: none is left).
        if isinstance(exc, BrokenPipeError) or exc.strerror is None:
            raise  # (a reader of stdout gone: main's; no strerror: not the system's word)
        where = f": {exc.filename}" if exc.filename else ""
        print(f"lidar-obstacles {args.command}: error: {exc.strerror}{where}", file=sys.stderr)
        return 2
    except BaseException as exc:
        terminated = _stopped(exc)
        if terminated is None:
            raise
        detail = f" ({exc})" if isinstance(exc, KeyboardInterrupt) and str(exc) else ""
        # (what was done: `play`'s count)
        print(f"lidar-obstacles {args.command}: "
              f"{'terminated' if terminated else 'interrupted'}{detail}", file=sys.stderr)
        return 143 if terminated else 130
    # The work is done and its outputs are in place: a stop from here on changes nothing,
    # and must not turn the run into a failure (status 130 after the summary). Ignored
    # while the summary is written (`_main` then restores the caller's handlers; `console`
    # ignores it again up to the exit).
    for stop in STOPS:
        signal.signal(stop, signal.SIG_IGN)
    try:
        write_summary(summary)
    except OSError as exc:
        if isinstance(exc, BrokenPipeError):
            raise  # (a reader of stdout gone: main's)
        # stdout on a full disk, or closed (`>&-`): the outputs are in place, the summary
        # is what was lost; one line, as for the machine's other errors
        print(f"lidar-obstacles {args.command}: error: the summary could not be written to "
              f"stdout: {exc.strerror or exc}", file=sys.stderr)
        _stdout_to_devnull()  # (what it still holds would fail again at the exit's flush)
        return 2
    return 0


def write_summary(summary: dict) -> None:
    """The command's JSON summary on stdout, flushed: OSError here when it cannot be
    written (a full disk; stdout closed, which Python makes None)."""
    import errno
    import json

    if sys.stdout is None:
        raise OSError(errno.EBADF, "stdout is closed")
    print(json.dumps(summary, indent=2, default=str))
    sys.stdout.flush()


def _stdout_to_devnull() -> None:
    """stdout's descriptor onto /dev/null, so that the flush of what its buffer holds
    succeeds (a reader gone, a full disk: nothing more can reach it anyway)."""
    import os

    if sys.stdout is not None:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def console() -> NoReturn:
    """The `lidar-obstacles` executable (and ``python -m lidar_obstacles.cli``): `main`,
    then the exit. After Ctrl-C or SIGTERM at once, its output flushed, past Python's
    finalisation, where what the interrupted work left in the compiled libraries crashed
    it now and then after the "interrupted" line (status 139 for 130: 2 of ~40 runs of
    `evaluate --report` stopped mid-way). Everything a stop must undo is undone by then,
    in `main`'s own `finally` blocks."""
    from lidar_obstacles.scripts import exit_process

    status = main()
    stopped = bool(_RECEIVED)
    for stop in STOPS:  # done: a stop now changes nothing (see _main)
        signal.signal(stop, signal.SIG_IGN)
    exit_process(status, stopped=stopped)


if __name__ == "__main__":  # `python -m lidar_obstacles.cli`
    console()
