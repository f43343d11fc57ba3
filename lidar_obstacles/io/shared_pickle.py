"""Objects handed between processes with their large buffers in shared memory.

`replay` sends each cloud (~3 MB of arrays) to a worker process and gets its messages
(~3 MB of CDR bytes) back. Through a pipe, the sending process writes those megabytes
64 KB at a time, taking the interpreter lock again for every piece, while its own main
thread is busy finding the next cloud's ground: the obstacle worker sat idle ~16 ms
between clouds waiting for its input. Here the object is pickled (protocol 5) with its
buffers out of band: they are copied once into one block of shared memory, and only the
small pickle and the block's name go through the pipe. The receiver copies the buffers
out and unlinks the block.
"""
from __future__ import annotations

import pickle
from dataclasses import dataclass
from multiprocessing.shared_memory import SharedMemory
from typing import Any


@dataclass(frozen=True)
class SharedPickle:
    """What crosses the pipe: the pickle without its large buffers, the name of the
    shared memory block holding them (None: none), and their sizes in bytes, in order."""

    head: bytes
    block: str | None
    sizes: tuple[int, ...]


def to_shared(obj: Any) -> SharedPickle:
    """obj, to be read once by `from_shared` in this or another process. Its contiguous
    numpy arrays, and bytes wrapped in pickle.PickleBuffer, go into shared memory."""
    buffers: list[pickle.PickleBuffer] = []
    head = pickle.dumps(obj, protocol=5, buffer_callback=buffers.append)
    if not buffers:
        return SharedPickle(head, None, ())
    raws = [b.raw() for b in buffers]
    sizes = tuple(r.nbytes for r in raws)
    try:
        block = SharedMemory(create=True, size=max(sum(sizes), 1))
    except OSError:
        # No shared memory to be had (a container's small /dev/shm is full, or there is
        # none): the whole object through the pipe, slower but the same.
        return SharedPickle(pickle.dumps(obj, protocol=5), None, ())
    try:
        offset = 0
        for raw in raws:
            block.buf[offset:offset + raw.nbytes] = raw
            offset += raw.nbytes
    except BaseException:
        block.close()
        block.unlink()
        raise
    block.close()
    return SharedPickle(head, block.name, sizes)


def from_shared(shared: SharedPickle) -> Any:
    """The object `to_shared` made; its shared memory block is freed. Arrays come back
    writable, bytes as read-only memoryviews."""
    if shared.block is None:
        return pickle.loads(shared.head)
    block = SharedMemory(name=shared.block)
    try:
        buffers, offset = [], 0
        for size in shared.sizes:
            buffers.append(bytearray(block.buf[offset:offset + size]))
            offset += size
    finally:
        block.close()
        block.unlink()
    return pickle.loads(shared.head, buffers=buffers)


def discard_shared(shared: SharedPickle) -> None:
    """Free the block of an object that will never be read (work cancelled, a result
    nobody waits for any more); nothing when it was read already."""
    if shared.block is None:
        return
    try:
        block = SharedMemory(name=shared.block)
    except FileNotFoundError:
        return
    block.close()
    block.unlink()
