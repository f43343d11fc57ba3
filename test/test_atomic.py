"""Atomic outputs replace only a file of their own kind: a folder, or a file of another
kind, is the user's data. A writer killed outright leaves its temporary output only until
the next write of the same target."""
from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from lidar_obstacles.errors import OutputError
from lidar_obstacles.io.atomic import (HTML, JSON, LAS, PNG, TIFF, YAML, atomic_write,
                                       atomic_write_text, check_replaceable)

# The first bytes of a file of each kind, as their writers make them.
SAMPLES = {
    "TIFF (II)": (TIFF, b"II*\x00\x08\x00\x00\x00"),
    "TIFF (MM)": (TIFF, b"MM\x00*\x00\x00\x00\x08"),
    "PNG": (PNG, b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR"), "LAS": (LAS, b"LASF\x00\x00\x01\x02"),
    "JSON": (JSON, b'{\n  "messages": 3\n}\n'), "JSON list": (JSON, b" [1, 2]"),
    "HTML": (HTML, b"<!DOCTYPE html><html lang='en'></html>\n"),
    "params YAML": (YAML, b"# tuned\n/**:\n  ros__parameters:\n    use_odometry: true\n"),
}


@pytest.mark.parametrize("sample", sorted(SAMPLES))
def test_an_output_replaces_only_a_file_of_its_kind(sample, tmp_path):
    kind, same = SAMPLES[sample]
    path = tmp_path / "out"
    path.write_bytes(same)
    atomic_write(path, lambda tmp: tmp.write_bytes(same + b"new"), kind=kind)
    assert path.read_bytes() == same + b"new"
    others = [b"hi\n", b"\x00\x01binary"] + [b for k, b in SAMPLES.values() if k != kind]
    for other in others:
        path.write_bytes(other)
        with pytest.raises(OutputError) as err:
            atomic_write(path, lambda tmp: tmp.write_bytes(same), kind=kind)
        assert str(err.value) == f"{path} exists and is not {kind.name}: not overwriting it"
        assert path.read_bytes() == other
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temporary file left


def test_an_empty_file_is_replaced_and_a_folder_never(tmp_path):
    empty = tmp_path / "made_by_mktemp.json"
    empty.touch()
    atomic_write_text(empty, "{}\n", kind=JSON)
    assert empty.read_text() == "{}\n"
    folder = tmp_path / "dem.tif"
    folder.mkdir()
    with pytest.raises(OutputError, match="exists and is not a TIFF"):
        check_replaceable(folder, TIFF)
    check_replaceable(tmp_path / "new.tif", TIFF)  # nothing there: fine


@pytest.mark.parametrize("fails_in", ["write", "rename"])
def test_a_failed_write_leaves_the_old_file_and_no_temporary_one(tmp_path, fails_in,
                                                                 monkeypatch):
    """The writer raising halfway (a full disk, a bug), or the rename failing: the target
    keeps its old bytes and the half-written temporary file beside it is removed, in this
    process too (the next writer tidies only the partials of dead processes)."""
    path = tmp_path / "dem.tif"
    path.write_bytes(b"II*\x00old")

    def write(tmp):
        tmp.write_bytes(b"II*\x00half")
        if fails_in == "write":
            raise OSError(28, "No space left on device")

    if fails_in == "rename":
        def replace(src, dst):
            raise OSError(18, "Invalid cross-device link")

        monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(OSError):
        atomic_write(path, write, kind=TIFF)
    assert path.read_bytes() == b"II*\x00old"
    assert [p.name for p in tmp_path.iterdir()] == ["dem.tif"]


# The three ways an output is written, each as a statement that writes `out` and calls
# hold() in the middle of it: a file (GeoTIFF, PNG, LAS...), a folder (evaluate's report)
# and a bag.
WRITERS = {
    "file": "atomic_write(out, lambda tmp: (tmp.write_bytes(b'II*\\0'), hold()), kind=TIFF)",
    "folder": "atomic_folder(out, lambda tmp: ((tmp / 'report.html').touch(), hold()))",
    "bag": "with BagWriter(out) as bag:\n    hold()",
}
SETUP = """import sys, time
from pathlib import Path
from lidar_obstacles.io.atomic import TIFF, atomic_folder, atomic_write
from lidar_obstacles.io.bags import BagWriter
out = Path(sys.argv[1])
def hold():
    if len(sys.argv) > 2:
        print("writing", flush=True)
        time.sleep(600)
"""


def _writer(writer: str, out, *, hold: bool) -> subprocess.Popen:
    """A process writing `out`, stopped halfway (hold) once it says so, or done."""
    proc = subprocess.Popen([sys.executable, "-c", SETUP + WRITERS[writer], str(out),
                             *(["hold"] if hold else [])], stdout=subprocess.PIPE, text=True)
    if hold:
        assert proc.stdout.readline() == "writing\n", "the writer failed before writing"
    return proc


@pytest.mark.parametrize("writer", sorted(WRITERS))
def test_a_writer_killed_outright_leaves_its_partial_until_the_next_write(writer, tmp_path):
    out = tmp_path / ("dem.tif" if writer == "file" else "out")
    killed, running = _writer(writer, out, hold=True), _writer(writer, out, hold=True)
    try:
        killed.kill()  # kill -9: no chance to remove its partial output
        killed.wait()

        def partial(proc):
            return [p.name for p in tmp_path.iterdir()
                    if p.name.startswith(f".{out.name}.partial-{proc.pid}")]

        assert len(partial(killed)) == len(partial(running)) == 1
        # the dead writer's partials of other targets are not this write's to tidy
        others = {f".x{out.name}.partial-{killed.pid}", f".{out.name}x.partial-{killed.pid}"}
        for name in others:
            (tmp_path / name).mkdir()
        assert _writer(writer, out, hold=False).wait() == 0
        # the killed writer's partial is gone; the one being written stays
        assert {p.name for p in tmp_path.iterdir()} == {out.name, *partial(running), *others}
    finally:
        running.kill()
        running.wait()
    assert _writer(writer, out, hold=False).wait() == 0  # (and now its partial goes too)
    assert {p.name for p in tmp_path.iterdir()} == {out.name, *others}


# A writer that kills itself (kill -9) in the middle of swapping a folder over its target:
# between the two renames (the target is gone, its copy is .NAME.old-PID...) or after them
# (the new target is in place, the old copy not yet removed).
KILL_IN_SWAP = """import os, shutil, signal
_replace, _rmtree = os.replace, shutil.rmtree
def replace(src, dst):
    _replace(src, dst)
    if ".old-" in os.fspath(dst) and os.environ["KILL_AT"] == "between":
        os.kill(os.getpid(), signal.SIGKILL)
def rmtree(path, *args, **kwargs):
    if ".old-" in os.fspath(path) and os.environ["KILL_AT"] == "after":
        os.kill(os.getpid(), signal.SIGKILL)
    _rmtree(path, *args, **kwargs)
os.replace, shutil.rmtree = replace, rmtree
"""


def _olds(folder) -> set[str]:
    return {p.name for p in folder.iterdir() if ".old-" in p.name}


@pytest.mark.parametrize("writer", ["folder", "bag"])
@pytest.mark.parametrize("kill_at", ["between", "after"])
def test_a_writer_killed_while_it_swaps_a_folder_loses_no_data(writer, kill_at, tmp_path):
    from lidar_obstacles.io.atomic import remove_stale_partials

    out = tmp_path / "out"
    assert _writer(writer, out, hold=False).wait() == 0
    (out / "mark").write_text("the old version")
    proc = subprocess.run([sys.executable, "-c", KILL_IN_SWAP + SETUP + WRITERS[writer],
                           str(out)], env={**os.environ, "KILL_AT": kill_at})
    assert proc.returncode == -9
    (old,) = _olds(tmp_path)
    assert old.startswith(".out.old-") and out.exists() == (kill_at == "after")
    # a live writer's old copy (this process's), and another target's, are not touched
    rest = old.removeprefix(".out.")  # old-PID or old-PID-XXXXXXXX, PID the dead writer's
    others = {".out." + re.sub(r"\d+", str(os.getpid()), rest, count=1),
              f".xout.{rest}", f".outx.{rest}"}
    for name in others:
        (tmp_path / name).mkdir()
    remove_stale_partials(out)  # what the next writer does first
    # between: the old copy was the only one, and is the target again; after: the new
    # target is whole, and the old copy is gone
    assert (out / "mark").is_file() == (kill_at == "between")
    assert _olds(tmp_path) == others
    assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name]


def _dead_pid() -> int:
    """The PID of a process that has ended."""
    proc = subprocess.Popen([sys.executable, "-c", ""])
    proc.wait()
    return proc.pid


def test_stale_old_copies_give_back_the_latest_and_never_the_only_one(tmp_path):
    """Writers killed in turn while swapping left two old copies and no target: the one
    swapped away last is the target again, the other goes. Beside a dangling link at the
    target's name an old copy is the only copy of the data, and stays."""
    import time

    from lidar_obstacles.io.atomic import remove_stale_partials

    out, dead = tmp_path / "out", _dead_pid()
    for k, name in enumerate((f".out.old-{dead}", f".out.old-{dead}-abcdefgh")):
        folder = tmp_path / f"staging{k}"
        folder.mkdir()
        (folder / "mark").write_text(name)
        time.sleep(0.05)  # (the rename sets its change time: the second is the later)
        folder.rename(tmp_path / name)
    remove_stale_partials(out)
    assert (out / "mark").read_text() == f".out.old-{dead}-abcdefgh"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    # a dangling link where the target was: the old copy is not removed
    lonely = tmp_path / "lonely"
    (tmp_path / f".lonely.old-{dead}").mkdir()
    lonely.symlink_to(tmp_path / "nowhere")
    remove_stale_partials(lonely)
    assert (tmp_path / f".lonely.old-{dead}").is_dir()


def test_a_partial_named_by_no_process_is_no_dead_writers(tmp_path):
    """PID 0 is no process (a process group to os.kill): a partial named so may be a
    live writer's, and stays; a dead writer's goes."""
    from lidar_obstacles.io.atomic import remove_stale_partials

    out = tmp_path / "out"
    kept, gone = tmp_path / ".out.partial-0", tmp_path / f".out.partial-{_dead_pid()}"
    kept.mkdir()
    gone.mkdir()
    remove_stale_partials(out)
    assert kept.is_dir() and not gone.exists()
