"""Files written whole or not at all.

Every output of the package (GeoTIFF DEMs, hillshades, report pictures and pages, params
YAML, LAS subsets, generated config) is written to a temporary file beside its target and
renamed over it: os.replace is atomic on one file system, so a reader never sees half a
file and a failure (a full disk, Ctrl-C, a writer's exception) leaves the old file, or
none, and no temporary one.
"""
from __future__ import annotations

import os
import tempfile
from functools import lru_cache
from pathlib import Path
from typing import Callable


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


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a temporary path beside ``path`` (ending in the same suffix,
    for writers that choose the format by it: .laz, .png), give the file the mode open()
    would have (0o666 minus the umask, read per file; mkstemp's are 0o600), and rename it
    over ``path``. The temporary file is removed on any failure, and the error raised.
    Returns ``path``."""
    path = Path(path)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}",
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


def atomic_write_text(path: str | Path, text: str) -> Path:
    """``text`` as UTF-8 into ``path``, atomically (:func:`atomic_write`)."""
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))
