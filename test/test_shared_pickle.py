"""Objects handed between processes with their buffers in shared memory (`replay`)."""
from __future__ import annotations

import multiprocessing
import os
import pickle
from pathlib import Path

import numpy as np
import pytest

from lidar_obstacles.io.shared_pickle import (NAME_PREFIX, BlockPool, attach, discard_shared,
                                              from_shared, to_shared)

SHM = Path("/dev/shm")


def blocks() -> set[Path]:
    """This test process's blocks (another process's, made meanwhile, would count)."""
    return set(SHM.glob(NAME_PREFIX + "*"))


def _round_trip_in_child(shared, out):
    obj = from_shared(shared)
    out.put((obj["xyz"].sum(), bytes(obj["cdr"])))


@pytest.fixture
def cloud():
    rng = np.random.default_rng(3)
    points = np.zeros(1000, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("i", "u2")])
    points["x"] = rng.uniform(size=1000)
    return {"xyz": rng.uniform(size=(5000, 3)), "points": points,
            "ground": rng.uniform(size=9) > 0.5,
            "cdr": pickle.PickleBuffer(b"\x00\x01" * 4000), "frame": "map", "n": 7}


def test_round_trip_keeps_every_value_and_frees_the_block(cloud):
    before = blocks()
    shared = to_shared(cloud)
    assert shared.block is not None and len(shared.head) < 2000  # the arrays are not in it
    assert len(blocks() - before) == 1
    back = from_shared(shared)
    assert blocks() == before
    for key in ("xyz", "points", "ground"):
        np.testing.assert_array_equal(back[key], cloud[key])
        assert back[key].flags.writeable
    assert bytes(back["cdr"]) == b"\x00\x01" * 4000
    assert (back["frame"], back["n"]) == ("map", 7)
    back["xyz"][0, 0] = -1.0  # a copy: the sender's arrays are its own
    assert cloud["xyz"][0, 0] >= 0.0


def test_small_objects_need_no_block():
    shared = to_shared(("map", 3, None))
    assert shared.block is None
    assert from_shared(shared) == ("map", 3, None)


def test_another_process_reads_it(cloud):
    before = blocks()
    shared = to_shared(cloud)
    ctx = multiprocessing.get_context("fork")
    out = ctx.Queue()
    child = ctx.Process(target=_round_trip_in_child, args=(shared, out))
    child.start()
    total, cdr = out.get(timeout=60)
    child.join(timeout=60)
    assert total == pytest.approx(cloud["xyz"].sum())
    assert cdr == b"\x00\x01" * 4000
    assert blocks() == before


def test_discard_frees_what_was_never_read(cloud):
    before = blocks()
    shared = to_shared(cloud)
    discard_shared(shared)
    assert blocks() == before
    discard_shared(shared)  # gone already: nothing to do
    with pytest.raises(FileNotFoundError):
        from_shared(shared)


def test_without_shared_memory_it_goes_through_the_pipe(cloud, monkeypatch):
    """A container's /dev/shm may be tiny or full: the object then travels whole."""
    import lidar_obstacles.io.shared_pickle as sp

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(sp, "SharedMemory", full)
    shared = to_shared(cloud)
    assert shared.block is None and len(shared.head) > 40000
    back = from_shared(shared)
    np.testing.assert_array_equal(back["points"], cloud["points"])
    assert bytes(back["cdr"]) == b"\x00\x01" * 4000


def _result_into_job_block(shared, out):
    job = from_shared(shared)
    result = to_shared({"sum": job["xyz"].sum(axis=1)}, into=attach(shared.block))
    out.put(result)


def test_pool_blocks_are_reused_and_carry_the_result_back(cloud):
    before = blocks()
    pool = BlockPool()
    shared = to_shared(cloud, pool=pool)
    assert shared.kept and len(blocks() - before) == 1
    ctx = multiprocessing.get_context("fork")
    out = ctx.Queue()
    child = ctx.Process(target=_result_into_job_block, args=(shared, out))
    child.start()
    result = out.get(timeout=30)
    child.join(timeout=30)
    assert result.kept and result.block == shared.block  # the job's block, read already
    back = from_shared(result, pool=pool)
    np.testing.assert_array_equal(back["sum"], cloud["xyz"].sum(axis=1))
    discard_shared(result)  # a pool's block: left to the pool
    pool.give(shared.block)
    again = to_shared(cloud, pool=pool)
    assert again.block == shared.block and len(blocks() - before) == 1  # reused
    np.testing.assert_array_equal(from_shared(again, pool=pool)["xyz"], cloud["xyz"])
    pool.give(again.block)
    bigger = to_shared({"xyz": np.zeros((400_000, 3))}, pool=pool)  # does not fit: a new one
    assert bigger.block != shared.block and len(blocks() - before) == 2
    pool.close()
    assert blocks() == before


def test_blocks_of_a_run_killed_outright_are_swept_by_the_next(tmp_path, monkeypatch):
    """A replay killed with SIGKILL left its blocks in /dev/shm (9 MB for one run, still
    there hours later); the next run's first pool unlinks those of processes gone, and
    leaves those of live ones (a run beside it), of another PID namespace (a container
    sharing /dev/shm: its PIDs are not ours to look up) and names not ours."""
    import subprocess
    import sys

    from lidar_obstacles.io import shared_pickle

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    ns = shared_pickle._pid_namespace()
    names = [f"lidar_obstacles_{ns}_{dead.pid}_0badf00d", f"lidar_obstacles_{ns}_{10**20}_0bad",
             f"lidar_obstacles_{ns}_{os.getppid()}_0badf00d", "psm_0badf00d",
             f"lidar_obstacles_{ns}_{dead.pid}", f"lidar_obstacles_{ns + 1}_{dead.pid}_0badf00d"]
    for name in names:
        (tmp_path / name).write_bytes(b"x" * 10)
    monkeypatch.setattr(shared_pickle, "SHM_DIR", str(tmp_path))
    monkeypatch.setattr(shared_pickle, "_SWEPT", False)
    shared_pickle.BlockPool().close()
    # kept: a live process's, not ours, not a block's name, another PID namespace's
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names[2:])
    assert not shared_pickle.sweep_orphans()  # (once per process: the pool swept them)
