"""Files written whole or not at all.

Every output of the package (GeoTIFF DEMs, hillshades, report pictures and pages, params
YAML, LAS subsets, generated config) is written to a temporary file beside its target and
renamed over it: os.replace is atomic on one file system, so a reader never sees half a
file and a failure (a full disk, Ctrl-C, a writer's exception) leaves the old file, or
none, and no temporary one. What is renamed over is only a file of the same kind (or an
empty one): a folder, or a file of another kind, is the user's data.

A writer killed outright (kill -9, the OOM killer, a power cut) cannot remove its
temporary output, so each is named ``.NAME.partial-PID...`` after its target and its
writer's process, and the next writer of the same target removes those whose process is
gone (:func:`remove_stale_partials`). A folder replaced is first renamed away to
``.NAME.old-PID...``: killed between the two renames, the writer leaves the target only
there, and the next writer renames it back before it writes anything.
"""
from __future__ import annotations

import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable

from lidar_obstacles.errors import OutputError

HEAD = 64 * 1024  # bytes of an existing file read to tell its kind


@dataclass(frozen=True)
class Kind:
    """A kind of output file: its name for the error, and a test of a file's first HEAD
    bytes (the whole file when it is shorter)."""

    name: str
    matches: Callable[[bytes], bool]


def _starts(*magic: bytes, text: bool = False) -> Callable[[bytes], bool]:
    """Starts with one of `magic`; for text, after white space and in any case."""
    return lambda head: (head.lstrip().lower() if text else head).startswith(magic)


def _yaml_mapping(head: bytes) -> bool:
    """A whole file of YAML whose top is a block mapping, as a params file is (a JSON
    object is a YAML mapping too, in flow style, but another kind of file)."""
    import yaml

    if len(head) == HEAD or head.lstrip().startswith(b"{"):
        return False
    try:
        return isinstance(yaml.safe_load(head), dict)
    except yaml.YAMLError:
        return False


TIFF = Kind("a TIFF", _starts(b"II*\0", b"MM\0*"))
PNG = Kind("a PNG", _starts(b"\x89PNG\r\n\x1a\n"))
LAS = Kind("a LAS/LAZ file", _starts(b"LASF"))
JSON = Kind("JSON", _starts(b"{", b"[", text=True))
HTML = Kind("an HTML page", _starts(b"<!doctype html", b"<html", text=True))
YAML = Kind("a YAML mapping", _yaml_mapping)


def check_replaceable(path: str | Path, kind: Kind) -> None:
    """Raise OutputError unless `path` is free, an empty file or a file of `kind`.
    Callers that work long before they write call it first, to say so at once."""
    path = Path(path)
    if not path.exists():
        return
    if path.is_file():
        with open(path, "rb") as file:
            head = file.read(HEAD)
        if not head or kind.matches(head):
            return
    raise OutputError(f"{path} exists and is not {kind.name}: not overwriting it")


def check_not_input(out: str | Path, inputs: list[str | Path]) -> None:
    """Raise OutputError when `out` is one of `inputs` (the same file or folder, by any
    name: a link, a relative path), a folder holding one (a bag's folder and its .mcap),
    or lies inside an input bag's folder (which would hold a second bag, and readers of
    the first meet its files): writing it would destroy or spoil what is being read."""
    out_path = Path(os.path.abspath(out))
    for src in inputs:
        src_path = Path(os.path.abspath(src))
        same = out_path.resolve() == src_path.resolve() or (
            out_path.exists() and src_path.exists() and os.path.samefile(out_path, src_path))
        if same or out_path.resolve() in src_path.resolve().parents:
            raise OutputError(f"{out} is the input {src}"
                              f"{'' if same else ' (it holds it)'}: not overwriting it")
        if (src_path / "metadata.yaml").is_file() \
                and src_path.resolve() in out_path.resolve().parents:
            raise OutputError(f"{out} lies inside the input {src}: write it elsewhere")


def partial_prefix(path: Path) -> str:
    """The start of the name of this process's temporary outputs of `path`:
    ``.NAME.partial-PID`` (a bag folder's whole name; a file or report folder's is followed
    by ``-`` and mkstemp's 8 random characters, then the file's suffix)."""
    return f".{path.name}.partial-{os.getpid()}"


def _alive(pid: int) -> bool:
    """Whether process `pid` may be running: only a PID known to be gone makes a temporary
    output stale. One of another user is alive too (PermissionError), and so is a number
    that is no PID (0 is a process group to os.kill; one too big for it)."""
    if pid <= 0:
        return True
    try:
        os.kill(pid, 0)  # signal 0: no signal sent, only whether the process exists
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def remove_stale_partials(path: Path) -> None:
    """Tidy what writers of `path` killed outright left beside it, so that it stays only
    until the next write of the same target:

    - the temporary outputs (``.NAME.partial-PID...``, files or folders) are removed;
    - the old copy a folder's swap makes (``.NAME.old-PID...``: the target renamed away,
      then the new folder renamed to its name) is removed when `path` exists (the kill came
      after the swap), and renamed back to `path` when it does not (the kill came between
      the two renames: it is the only copy of the target), before anything is written.

    Only the outputs of writers whose process is gone: one whose process is alive is
    another writer at work and stays; so do the outputs of other targets, and anything
    that cannot be removed (this is tidying, never a reason to fail)."""
    folder = path.parent if str(path.parent) else Path(".")
    partial, old = f".{path.name}.partial-", f".{path.name}.old-"
    # the PID, then nothing (a bag), or mkstemp's random part and the target's suffix
    partial_rest = re.compile(rf"(\d+)(?:-[a-z0-9_]{{8}}{re.escape(path.suffix)})?")
    old_rest = re.compile(r"(\d+)(?:-[a-z0-9_]{8})?")  # (a folder's: no suffix)

    def stale(entry: os.DirEntry, head: str, rest: re.Pattern) -> bool:
        found = rest.fullmatch(entry.name[len(head):])
        return found is not None and not _alive(int(found.group(1)))

    try:
        entries = [e for e in os.scandir(folder) if e.name.startswith((partial, old))]
    except OSError:
        return
    # Old copies first; with several (writers killed in turn), the latest swapped away.
    olds = [e for e in entries if e.name.startswith(old) and stale(e, old, old_rest)]
    for entry in sorted(olds, key=_changed, reverse=True):
        if not os.path.lexists(path):
            try:
                os.rename(entry.path, path)  # (fails on a folder made there meanwhile)
                continue
            except OSError:
                pass
        if os.path.exists(path):  # (never the only copy; nor beside a dangling link)
            _remove(entry)
    for entry in entries:
        if entry.name.startswith(partial) and stale(entry, partial, partial_rest):
            _remove(entry)


def _changed(entry: os.DirEntry) -> float:
    """When `entry` was last renamed (its inode's change time, s), or 0."""
    try:
        return entry.stat(follow_symlinks=False).st_ctime
    except OSError:
        return 0.0


def _remove(entry: os.DirEntry) -> None:
    """Remove a file or folder, quietly: it may be gone meanwhile (another writer tidying
    too), or not ours to remove."""
    if entry.is_dir(follow_symlinks=False):
        shutil.rmtree(entry.path, ignore_errors=True)
    else:
        try:
            os.unlink(entry.path)
        except OSError:
            pass


def umask() -> int:
    """The process umask, read without changing it.

    os.umask can only read the mask by setting it, so a round trip leaves it 0 for a
    moment, and files another thread creates then (exports run in a ROS service callback
    beside the executor's threads) would be world-writable. Linux >= 4.7 shows the mask in
    /proc/self/status; the round trip is the fallback where that line is missing.
    """
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return _umask_round_trip()


@lru_cache(maxsize=1)
def _umask_round_trip() -> int:
    """The umask by setting it and back; once per process, so the window is opened once."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: str | Path, write: Callable[[Path], object], *, kind: Kind | None
                 ) -> Path:
    """Call ``write(tmp)`` on a temporary path beside ``path`` (ending in the same suffix,
    for writers that choose the format by it: .laz, .png), give the file the mode open()
    would have (0o666 minus the umask, read per file; mkstemp's are 0o600), and rename it
    over ``path``, which must be free or of ``kind`` (:func:`check_replaceable`; None, for
    files a developer regenerates: anything). The temporary file is removed on any
    failure, and the error raised. Returns ``path``."""
    path = Path(path)
    if kind is not None:
        check_replaceable(path, kind)
    remove_stale_partials(path)
    fd, name = tempfile.mkstemp(prefix=partial_prefix(path) + "-", suffix=path.suffix,
                                dir=path.parent if str(path.parent) else ".")
    os.close(fd)
    tmp = Path(name)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~umask())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def atomic_write_text(path: str | Path, text: str, *, kind: Kind | None) -> Path:
    """``text`` as UTF-8 into ``path``, atomically (:func:`atomic_write`)."""
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"), kind=kind)


def swap_in(new: Path, path: Path, old: Path) -> None:
    """Rename the finished output `new` to `path`. An existing `path` (a folder or a file)
    is renamed to `old` first and removed after: between the two renames a kill leaves it
    there, where `remove_stale_partials` finds it (the name must be ``.NAME.old-PID...``)."""
    if not os.path.lexists(path):
        os.replace(new, path)
        return
    os.replace(path, old)
    os.replace(new, path)
    if old.is_dir() and not old.is_symlink():
        shutil.rmtree(old, ignore_errors=True)
    else:
        old.unlink(missing_ok=True)


def atomic_folder(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a new temporary folder beside ``path``, give the folder the
    mode mkdir would (0o777 minus the umask; mkdtemp's is 0o700) and rename it to
    ``path``; an existing ``path`` is swapped out only then (whether it may be replaced is
    the caller's to judge). The temporary folder is removed on any failure, Ctrl-C and
    SIGTERM included, and the error raised. Returns ``path``."""
    path = Path(path)
    remove_stale_partials(path)
    tmp = Path(tempfile.mkdtemp(prefix=partial_prefix(path) + "-",
                                dir=path.parent if str(path.parent) else "."))
    try:
        write(tmp)
        os.chmod(tmp, 0o777 & ~umask())
        head = f".{path.name}.partial-"
        swap_in(tmp, path, tmp.with_name(f".{path.name}.old-{tmp.name.removeprefix(head)}"))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # (gone once renamed)
    return path
