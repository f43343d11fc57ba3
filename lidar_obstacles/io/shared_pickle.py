"""Objects handed between processes with their large buffers in shared memory.

`replay` sends each cloud (~3 MB of arrays) to a worker process and gets its messages
(~3 MB of CDR bytes) back. Through a pipe, the sending process writes those megabytes
64 KB at a time, taking the interpreter lock again for every piece, while its own main
thread is busy finding the next cloud's ground: the obstacle worker sat idle ~16 ms
between clouds waiting for its input. Here the object is pickled (protocol 5) with its
buffers out of band: they are copied once into one block of shared memory, and only the
small pickle and the block's name go through the pipe. The receiver copies the buffers
out and unlinks the block.

A fresh block per object cost more than the copies: its pages are faulted in and zeroed
on the first write, and again in the receiver's mapping (`replay`: ~7.5 ms of CPU per
message over its three processes). A `BlockPool` keeps the blocks of one process for
reuse: the receiver then only reads the block (through a mapping it keeps, `attach`), and
the pool's owner takes it back once it knows the block was read.
"""
from __future__ import annotations

import collections
import os
import pickle
import secrets
from dataclasses import dataclass
from multiprocessing.shared_memory import SharedMemory
from typing import Any, cast


def _pid_namespace() -> int:
    """The inode of this process's PID namespace (0 where there is none to read): PIDs are
    those of a namespace, and containers sharing /dev/shm (`docker --ipc=host`) need not
    share it."""
    try:
        return os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        return 0


# The start of the name of every block this package makes (`/dev/shm/NAME` on Linux): the
# process that imported this module (in its PID namespace), whose forked workers
# (`replay`'s) keep it, so the blocks of one run are known by it and never taken for another
# program's (psm_...).
NAME_PREFIX = f"lidar_obstacles_{_pid_namespace()}_{os.getpid()}_"


SHM_DIR = "/dev/shm"  # where Linux keeps the blocks, by name
_SWEPT = False  # (once per process)


def sweep_orphans() -> list[str]:
    """Unlink the blocks of runs that are gone: those named NAME_PREFIX-style, in this PID
    namespace, after a process that no longer exists. A run killed outright (`kill -9`,
    the OOM killer) leaves its blocks behind (megabytes each, until the machine restarts);
    this is done by the next run's first pool. A block of a live process, of another
    user's, or of another PID namespace (a container's, whose PIDs this one cannot see) is
    left be. Returns the names unlinked; nothing on a system without SHM_DIR."""
    gone: list[str] = []
    try:
        names = os.listdir(SHM_DIR)
    except OSError:
        return gone
    ours = f"lidar_obstacles_{_pid_namespace()}_"
    for name in names:
        head, _, rest = name.partition(ours)
        pid_text, sep, _ = rest.partition("_")
        if head or not sep or not pid_text.isdigit() or int(pid_text) == os.getpid():
            continue
        try:
            os.kill(int(pid_text), 0)
            continue  # alive (the pid may be another program's now: its blocks stay)
        except (ProcessLookupError, OverflowError):  # (gone, or no pid at all)
            pass
        except PermissionError:
            continue  # another user's process, alive
        try:
            os.unlink(os.path.join(SHM_DIR, name))
            gone.append(name)
        except OSError:
            pass  # (another user's block, or another run swept it first)
    return gone


def _create(size: int) -> SharedMemory:
    """A new block of `size` bytes named NAME_PREFIX + 8 random hex digits. OSError when
    there is no shared memory to be had."""
    while True:
        try:
            return SharedMemory(name=NAME_PREFIX + secrets.token_hex(4), create=True,
                                size=size)
        except FileExistsError:
            continue  # (one in 4 billion: another name)


@dataclass(frozen=True)
class SharedPickle:
    """What crosses the pipe: the pickle without its large buffers, the name of the
    shared memory block holding them (None: none), and their sizes in bytes, in order.
    kept: the block belongs to a `BlockPool`, and the reader leaves it be."""

    head: bytes
    block: str | None
    sizes: tuple[int, ...]
    kept: bool = False


class BlockPool:
    """Shared memory blocks made by this process and reused, each for one object at a
    time: `to_shared(obj, pool=...)` takes a free one (or makes one), `give` hands it
    back once its object was read, `close` unlinks them all. Reused blocks keep their
    pages: a new block's were faulted in and zeroed on every write."""

    def __init__(self, max_free: int = 16) -> None:
        global _SWEPT
        if not _SWEPT:  # the blocks earlier runs killed outright left behind
            _SWEPT = True
            sweep_orphans()
        self._blocks: dict[str, SharedMemory] = {}
        self._free: list[SharedMemory] = []
        self._max_free = max_free

    def take(self, size: int) -> SharedMemory:
        """A free block of at least `size` bytes (the smallest), or a new one with room
        to spare (the next object is rarely the same size). OSError when there is no
        shared memory to be had."""
        fits = [b for b in self._free if b.size >= size]
        if fits:
            block = min(fits, key=lambda b: b.size)
            self._free.remove(block)
            return block
        block = _create(_rounded(size + size // 4))
        self._blocks[block.name] = block
        return block

    def give(self, name: str) -> None:
        """Block `name` is free again: its object was read. The smallest free blocks go
        when more than `max_free` are free."""
        block = self._blocks.get(name)
        if block is None or block in self._free:
            return
        self._free.append(block)
        while len(self._free) > self._max_free:
            self._drop(min(self._free, key=lambda b: b.size))

    def block(self, name: str) -> SharedMemory | None:
        """This pool's block `name` (its own mapping), or None."""
        return self._blocks.get(name)

    def _drop(self, block: SharedMemory) -> None:
        if block in self._free:
            self._free.remove(block)
        del self._blocks[block.name]
        block.close()
        block.unlink()

    def close(self) -> None:
        """Unlink every block (the readers' mappings stay valid until they close them)."""
        for block in list(self._blocks.values()):
            self._drop(block)


def _rounded(size: int) -> int:
    return max(1, -(-size // (256 << 10))) * (256 << 10)  # whole 256 KB


# The mappings of other processes' pool blocks this process read lately (`attach`).
_ATTACHED: collections.OrderedDict[str, SharedMemory] = collections.OrderedDict()
_MAX_ATTACHED = 32


def attach(name: str) -> SharedMemory:
    """A mapping of another process's pool block, kept for the next object it carries
    (a fresh mapping faults every page in again). The oldest mappings are closed beyond
    a few dozen: their pool may have dropped them."""
    block = _ATTACHED.pop(name, None)
    if block is None:
        block = SharedMemory(name=name)
    _ATTACHED[name] = block
    while len(_ATTACHED) > _MAX_ATTACHED:
        _ATTACHED.popitem(last=False)[1].close()
    return block


def to_shared(obj: Any, *, pool: BlockPool | None = None,
              into: SharedMemory | None = None) -> SharedPickle:
    """obj, to be read once by `from_shared` in this or another process. Its contiguous
    numpy arrays, and bytes wrapped in pickle.PickleBuffer, go into shared memory: a
    block of `pool`, or the block `into` (a pool's, of another process) when they fit,
    else a block of their own, which the reader frees."""
    buffers: list[pickle.PickleBuffer] = []
    head = pickle.dumps(obj, protocol=5, buffer_callback=buffers.append)
    if not buffers:
        return SharedPickle(head, None, ())
    raws = [b.raw() for b in buffers]
    sizes = tuple(r.nbytes for r in raws)
    total = sum(sizes)
    if into is not None and into.size >= total:
        _fill(into, raws)
        return SharedPickle(head, into.name, sizes, kept=True)
    try:
        block = (pool.take(total) if pool is not None
                 else _create(max(total, 1)))
    except OSError:
        # No shared memory to be had (a container's small /dev/shm is full, or there is
        # none): the whole object through the pipe, slower but the same.
        return SharedPickle(pickle.dumps(obj, protocol=5), None, ())
    if pool is not None:
        _fill(block, raws)  # (a failure leaves the block to the pool's close)
        return SharedPickle(head, block.name, sizes, kept=True)
    try:
        _fill(block, raws)
    except BaseException:
        block.close()
        block.unlink()
        raise
    block.close()
    return SharedPickle(head, block.name, sizes)


def _fill(block: SharedMemory, raws: list[memoryview]) -> None:
    offset = 0
    buf = cast(memoryview, block.buf)  # (None only once closed)
    for raw in raws:
        buf[offset:offset + raw.nbytes] = raw
        offset += raw.nbytes


def from_shared(shared: SharedPickle, *, pool: BlockPool | None = None) -> Any:
    """The object `to_shared` made. A block of its own is freed; a pool's is left to
    its pool (read through `pool`'s own mapping when it is this process's, else through
    `attach`). Arrays come back writable, bytes as read-only memoryviews."""
    if shared.block is None:
        return pickle.loads(shared.head)
    if shared.kept:
        block = (pool.block(shared.block) if pool is not None else None) or attach(shared.block)
        return pickle.loads(shared.head, buffers=_copied(block, shared.sizes))
    block = SharedMemory(name=shared.block)
    try:
        buffers = _copied(block, shared.sizes)
    finally:
        block.close()
        block.unlink()
    return pickle.loads(shared.head, buffers=buffers)


def _copied(block: SharedMemory, sizes: tuple[int, ...]) -> list[bytearray]:
    buffers, offset = [], 0
    buf = cast(memoryview, block.buf)  # (None only once closed)
    for size in sizes:
        buffers.append(bytearray(buf[offset:offset + size]))
        offset += size
    return buffers


def discard_shared(shared: SharedPickle) -> None:
    """Free the block of an object that will never be read (work cancelled, a result
    nobody waits for any more); nothing when it was read already, or when the block is a
    pool's (its pool frees it)."""
    if shared.block is None or shared.kept:
        return
    try:
        block = SharedMemory(name=shared.block)
    except FileNotFoundError:
        return
    block.close()
    block.unlink()
