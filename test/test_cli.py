"""The command line's --help: what the README promises of it; its exit on a closed pipe and
on Ctrl-C at start."""
from __future__ import annotations

import argparse
import os
import re
import signal
import json
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO, interrupt_while_importing, signal_at_import, stop_inside_exec
from lidar_obstacles.cli import build_parser, main


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    """Every subcommand's parser, as the parser itself lists them."""
    parser = build_parser()
    (sub,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _option_entries(parser: argparse.ArgumentParser) -> dict[str, str]:
    """Each option's entry in the rendered --help, unwrapped onto one line, by its first
    option string."""
    entries: dict[str, str] = {}
    current = None
    for line in parser.format_help().splitlines():
        if re.match(r"  -", line):
            current = line.split()[0].rstrip(",")
            entries[current] = line.strip()
        elif current is not None and line.startswith("   "):
            entries[current] += " " + line.strip()
        else:
            current = None
    return entries


@pytest.mark.parametrize("command", sorted(_subcommands()))
def test_help_shows_every_options_default_once(command):
    parser = _subcommands()[command]
    entries = _option_entries(parser)
    options = [a for a in parser._actions if a.option_strings]
    assert set(entries) == {a.option_strings[0] for a in options}
    for action in options:
        entry = entries[action.option_strings[0]]
        if isinstance(action, argparse._HelpAction):  # "show this help message and exit"
            continue
        assert entry.count("(default") == 1, entry
        assert "(default: None)" not in entry and "(default: )" not in entry, entry


def test_a_malformed_params_file_is_one_line_with_its_position_and_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("not: [valid")
    # (the params file is read before the bag is opened)
    code = main(["export-dem", str(tmp_path / "no_bag"), str(tmp_path / "o.tif"),
                 "--params-file", str(bad)])
    assert code == 2
    assert capsys.readouterr().err == (
        f"lidar-obstacles export-dem: error: params file {bad}: line 1, column 12: "
        "expected ',' or ']', but got '<stream end>'\n")


def _bag_commands() -> list[str]:
    """The subcommands whose input is a bag only (IN_BAG)."""
    return sorted(name for name, parser in _subcommands().items()
                  if any(a.dest == "src" and a.metavar == "IN_BAG" for a in parser._actions))


def _las_file(path: Path) -> Path:
    import laspy

    las = laspy.LasData(laspy.LasHeader(point_format=1, version="1.2"))
    las.x, las.y, las.z = [0.0, 1.0, 2.0], [0.0, 1.0, 0.0], [5.0, 5.0, 5.0]
    las.write(str(path))
    return path


@pytest.mark.parametrize("command", _bag_commands())
@pytest.mark.parametrize("name", ["survey.las", "survey.LAZ"])
def test_a_las_file_given_for_a_bag_is_said_to_be_one_with_the_way_to_a_bag(
        command, name, tmp_path, capsys):
    # rosbags said "cannot open bag survey.las: Unrecognized storage format '.las'"
    las = _las_file(tmp_path / name)
    out = {"replay": [str(tmp_path / "out")], "export-dem": [str(tmp_path / "o.tif")]}
    assert main([command, str(las), *out.get(command, [])]) == 2
    assert capsys.readouterr().err == (
        f"lidar-obstacles {command}: error: {las} is a LAS/LAZ file, not a bag: "
        "`lidar-obstacles las2bag` turns it into one\n")


def test_the_commands_that_read_only_bags_are_found():
    assert _bag_commands() == ["export-dem", "play", "replay"]


def test_a_las_file_named_otherwise_is_said_to_be_one_read_by_name(tmp_path, capsys):
    # `evaluate` (as `tune`, `simplify`, `features`) reads LAS/LAZ files by their name
    las = _las_file(tmp_path / "survey")
    assert main(["evaluate", str(las), "--no-dem"]) == 2
    assert capsys.readouterr().err == (
        f"lidar-obstacles evaluate: error: {las} is a LAS/LAZ file, not a bag: "
        "`lidar-obstacles las2bag` turns it into one (`evaluate`, `tune`, `simplify` and "
        "`features` read it named .las or .laz)\n")


@pytest.mark.parametrize("args", [["simulate", "{tmp}/bag", "--duration", "0.1", "--points",
                                   "100"], ["simulate", "--help"], ["--help"]])
def test_a_reader_that_stops_early_ends_the_command_quietly(args, tmp_path):
    # `lidar-obstacles ... | head -c 10`: the pipe is closed before the JSON (or the help)
    # is written; as SIGPIPE ends other tools, status 141 (--help: argparse's own 0)
    read, write = os.pipe()
    os.close(read)
    proc = subprocess.run([sys.executable, "-m", "lidar_obstacles.cli",
                           *(a.format(tmp=tmp_path) for a in args)],
                          cwd=REPO, stdout=write, stderr=subprocess.PIPE, text=True, timeout=120)
    os.close(write)
    assert proc.stderr == "" and proc.returncode == (0 if "--help" in args else 141)


@pytest.mark.parametrize("stdout", ["full disk", "closed"])
def test_a_summary_that_cannot_be_written_is_one_line_and_status_2(stdout, tmp_path):
    # `lidar-obstacles ... > /dev/full` (or `>&-`): a traceback and status 1 came after the
    # work; now one line naming it, status 2, and the bag written stays
    bag = tmp_path / "bag"
    args = [sys.executable, "-m", "lidar_obstacles.cli", "simulate", str(bag),
            "--duration", "0.1", "--points", "100"]
    if stdout == "full disk":
        with open("/dev/full", "w") as full:
            proc = subprocess.run(args, cwd=REPO, stdout=full, stderr=subprocess.PIPE,
                                  text=True, timeout=120)
        reason = "No space left on device"
    else:
        proc = subprocess.run(args, cwd=REPO, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True, timeout=120,
                              preexec_fn=lambda: os.close(1))
        reason = "stdout is closed"
    assert (proc.returncode, proc.stderr) == (2, "lidar-obstacles simulate: error: the "
                                              f"summary could not be written to stdout: {reason}\n")
    assert bag.is_dir()


# What pip's console script `lidar-obstacles` runs (where it is not installed)
CONSOLE_SCRIPT = "import sys\nfrom lidar_obstacles.cli import console\nsys.exit(console())\n"


@pytest.mark.parametrize("delay", [0.0, 0.01, 0.03, 0.1, 0.3])
def test_ctrl_c_while_the_modules_are_imported_is_one_line_and_exit_130(delay, tmp_path):
    """Ctrl-C in the first ~0.3 s, while Python imports the command's modules (numpy, rclpy
    ...), ends it as Ctrl-C during the command does: one line, status 130, no traceback.

    The SIGINT goes `delay` s after the first heavy import has begun (-X importtime prints
    each module as it is imported: numpy's first, or the package's own algorithms'), which
    cli.py used to import before main could catch anything. The moment is the process's,
    not a clock's, so a loaded machine cannot move the signal out of the imports; they take
    ~0.3 s, so the delays land in them and in the command. Before that moment Python starts
    (site and its .pth files), imports cli.py's few standard-library modules and calls
    main: a signal in those few milliseconds is Python's to report, no package can catch
    it."""
    exe = Path(sys.executable).parent / "lidar-obstacles"
    script = [str(exe)] if exe.is_file() else ["-c", CONSOLE_SCRIPT]
    code, err = interrupt_while_importing(
        [*script, "simulate", str(tmp_path / "bag"), "--duration", "600"],
        lambda module: module.split(".")[0] == "numpy" or module.startswith(
            "lidar_obstacles.core"), delay)
    said = [x for x in err.splitlines() if not x.startswith("import time:")]
    assert code == 130 and "Traceback" not in err, err[-3000:]
    assert said in (["lidar-obstacles: interrupted"],
                    ["lidar-obstacles simulate: interrupted"]), said


@pytest.mark.parametrize("sig, code, word", [(signal.SIGINT, 130, "interrupted"),
                                             (signal.SIGTERM, 143, "terminated")])
def test_a_signal_inside_an_import_a_c_extension_makes_is_one_line(sig, code, word, tmp_path):
    # numpy's C core imports datetime: the KeyboardInterrupt raised there came out of numpy
    # as an ImportError ("Importing the numpy C-extensions failed ... bad install"), a
    # traceback and status 1
    proc = subprocess.run([sys.executable, "-c", signal_at_import("lidar_obstacles.cli",
                                                                  "datetime", sig),
                           "simulate", str(tmp_path / "bag"), "--duration", "600"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert (proc.returncode, proc.stderr) == (code, f"lidar-obstacles: {word}\n")


@pytest.mark.parametrize("sig, code, word", [(signal.SIGINT, 130, "interrupted"),
                                             (signal.SIGTERM, 143, "terminated")])
def test_a_signal_inside_a_weakref_callback_is_one_line_too(sig, code, word, tmp_path):
    # Python prints and drops what a weakref's callback raises: it printed the
    # KeyboardInterrupt's traceback, and the command went on
    proc = subprocess.run([sys.executable, "-c",
                           signal_at_import("lidar_obstacles.cli", "numpy", sig,
                                            in_callback=True),
                           "simulate", str(tmp_path / "bag"), "--duration", "600"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert (proc.returncode, proc.stderr) == (code, f"lidar-obstacles: {word}\n")


def test_run_with_python_m_a_ctrl_c_inside_an_exec_still_exits_130(tmp_path):
    """`python -m lidar_obstacles.cli` (as the tests run it): a Ctrl-C raised inside code
    that exec() runs from a string, as dataclasses make their methods while modules are
    imported, was noted by Python as unhandled, and a process run with -m then killed
    itself by SIGINT at exit: status -2 after its line, not 130."""
    proc = subprocess.run([sys.executable, "-m", "lidar_obstacles.cli", "simulate",
                           str(tmp_path / "bag"), "--duration", "600"],
                          cwd=REPO, env=stop_inside_exec("numpy", tmp_path), capture_output=True,
                          text=True, timeout=120)
    assert (proc.returncode, proc.stderr) == (130, "lidar-obstacles: interrupted\n")


@pytest.mark.parametrize("args", [
    ["replay", "{bag}", "{bag}"], ["replay", "{bag}/bag_0.mcap", "{bag}"],
    ["simplify", "{bag}", "{tmp}/./bag"], ["features", "{las}", "{las}"],
    ["simplify", "{las}", "{tmp}/link.laz"], ["evaluate", "{bag}", "--report", "{bag}"],
    ["replay", "{bag}", "{tmp}/params.yaml", "--params-file", "{tmp}/params.yaml"],
    ["tune", "{las}", "--start", "{tmp}/params.yaml", "--out", "{tmp}/params.yaml"],
    ["tune", "{las}", "--space", "{tmp}/params.yaml", "--out", "{tmp}/params.yaml"]])
def test_an_output_that_is_the_input_is_refused_before_any_work(args, tmp_path, capsys):
    # `replay b b` replaced the bag with its own output, `simplify s.laz s.laz` the survey
    # with 6 842 of its points: exit 0, the input gone; `tune --space s.yaml --out s.yaml`
    # the search space with the tuned parameters
    bag = tmp_path / "bag"
    assert main(["simulate", str(bag), "--duration", "0.1", "--points", "300"]) == 0
    las = _las_file(tmp_path / "s.laz")
    (tmp_path / "link.laz").symlink_to(las)
    (tmp_path / "params.yaml").write_text("/**:\n  ros__parameters: {}\n")
    capsys.readouterr()
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    argv = [a.format(bag=bag, las=las, tmp=tmp_path) for a in args]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"lidar-obstacles {args[0]}: error: ") and err.count("\n") == 1
    assert "is the input" in err and err.endswith(": not overwriting it\n")
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before


@pytest.mark.parametrize("command", ["replay", "simplify"])
def test_an_output_inside_the_input_bag_is_refused(command, tmp_path, capsys):
    # `replay b b/sub` wrote a second bag into the first, exit 0
    bag = tmp_path / "bag"
    assert main(["simulate", str(bag), "--duration", "0.1", "--points", "300"]) == 0
    capsys.readouterr()
    before = sorted(p.name for p in bag.iterdir())
    assert main([command, str(bag), str(bag / "sub")]) == 2
    assert capsys.readouterr().err == (f"lidar-obstacles {command}: error: {bag / 'sub'} lies "
                                       f"inside the input {bag}: write it elsewhere\n")
    assert sorted(p.name for p in bag.iterdir()) == before


def test_a_topic_named_relative_is_the_root_namespaces(tmp_path, capsys):
    # `--topic points` was "no PointCloud2 topic 'points' (it has: /points)"
    bag = tmp_path / "bag"
    assert main(["simulate", str(bag), "--duration", "0.1", "--points", "300"]) == 0
    assert main(["replay", str(bag), str(tmp_path / "out"), "--topic", "points",
                 "--no-dem"]) == 0
    assert '"topic": "/points"' in capsys.readouterr().out


def test_play_names_the_topics_the_bag_lacks(tmp_path, capsys):
    # `play --topics /points /pointz` dropped the misspelt one, exit 0
    bag = tmp_path / "bag"
    assert main(["simulate", str(bag), "--duration", "0.1", "--points", "300"]) == 0
    capsys.readouterr()
    assert main(["play", str(bag), "--topics", "/points", "/pointz"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"lidar-obstacles play: error: bag {bag} has no topic /pointz "
                          "(it has: ") and "/points" in err and err.count("\n") == 1


def test_version(capsys):
    from lidar_obstacles import __version__

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out == f"lidar-obstacles {__version__}\n"


def test_a_bad_crs_is_refused_before_the_work_naming_the_option(tmp_path, capsys):
    # it was said after the whole bag was processed, as "parameter 'export.crs'"
    code = main(["export-dem", str(tmp_path / "no_bag"), str(tmp_path / "o.tif"),
                 "--crs", "foo"])
    assert code == 2
    assert capsys.readouterr().err == (
        "lidar-obstacles export-dem: error: --crs: 'foo' is neither EPSG:<code> nor a CRS WKT\n")


def test_a_stop_after_the_work_is_done_does_not_fail_the_run(tmp_path):
    """SIGINT once the outputs are in place (here: as the summary is printed) left a
    complete output and its summary, but exit status 130: a caller took the run for
    failed. It now ends with 0."""
    code = ("import os, signal, sys\n"
            "from lidar_obstacles import cli\n"
            "write = cli.write_summary\n"
            "def late(summary):\n"
            "    os.kill(os.getpid(), signal.SIGINT)\n"
            "    write(summary)\n"
            "cli.write_summary = late\n"
            f"sys.exit(cli.main(['simulate', {str(tmp_path / 'f')!r}, '--duration', '0.1',"
            " '--points', '300']))\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    assert (res.returncode, res.stderr) == (0, ""), res.stderr
    assert json.loads(res.stdout)["messages"] >= 1


def test_main_leaves_the_callers_signal_handlers_as_they_were(tmp_path):
    """In-process callers (tests, scripts) keep their own handlers: an ignored SIGINT
    would also be ignored by every process they start afterwards."""
    import signal

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    assert main(["simulate", str(tmp_path / "f"), "--duration", "0.1", "--points", "300"]) == 0
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_a_full_disk_is_one_line_and_leaves_no_output(tmp_path, monkeypatch, capsys):
    """ENOSPC while a bag was written gave a traceback and status 1; the other errors of
    the machine's (no permission, a read-only folder) went the same way."""
    import errno

    from lidar_obstacles.io.bags import BagWriter

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path / "f"))

    monkeypatch.setattr(BagWriter, "write", full)
    assert main(["simulate", str(tmp_path / "f"), "--duration", "0.2", "--points", "300"]) == 2
    err = capsys.readouterr().err
    assert err == f"lidar-obstacles simulate: error: No space left on device: {tmp_path / 'f'}\n"
    assert list(tmp_path.iterdir()) == []  # the partial bag removed


def test_las2bag_refuses_an_output_named_as_a_las_file(tmp_path, capsys):
    """`las2bag x.laz out.las` wrote a bag folder named out.las, which `evaluate` then
    refused as "not a LAS file, a folder"."""
    from conftest import data_file

    out = tmp_path / "out.las"
    assert main(["las2bag", str(data_file("isprs/samp71-utm.laz")), str(out)]) == 2
    assert capsys.readouterr().err == (
        f"lidar-obstacles las2bag: error: OUT_BAG {out} is named as a LAS/LAZ file, but "
        "las2bag writes a bag (a folder): name it without the suffix\n")
    assert not out.exists()
