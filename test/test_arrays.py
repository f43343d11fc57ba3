"""The column-wise reductions agree with numpy's own; BLAS can be limited to one thread."""
import numpy as np
import pytest

from lidar_obstacles.core.arrays import (all_columns, cell_index, column_max, column_mean,
                                         column_min, distinct_points, points_xyz,
                                         release_free_memory, reuse_freed_memory, row_norm,
                                         single_threaded_blas, snap_micrometres, unique_ints)
from lidar_obstacles.errors import CloudFormatError


@pytest.mark.parametrize("shape", [(1, 3), (7, 2), (5000, 3)])
def test_reductions_match_numpy(shape):
    rng = np.random.default_rng(1)
    a = rng.normal(size=shape) * 1e3
    assert np.array_equal(column_min(a), a.min(axis=0))
    assert np.array_equal(column_max(a[:, ::-1]), a[:, ::-1].max(axis=0))
    assert np.allclose(column_mean(a), a.mean(axis=0), rtol=1e-12, atol=1e-9)
    ints = rng.integers(-5, 5, size=shape)
    assert np.array_equal(column_min(ints), ints.min(axis=0))
    assert column_min(ints).dtype == ints.dtype
    mask = rng.random(shape) > 0.3
    assert np.array_equal(all_columns(mask), mask.all(axis=1))
    assert np.allclose(row_norm(a), np.linalg.norm(a, axis=1))


def test_points_xyz_passes_good_points_through_uncopied():
    xyz = np.arange(12.0).reshape(4, 3)
    assert points_xyz(xyz, "xyz") is xyz
    assert points_xyz(np.zeros((0, 3)), "xyz").shape == (0, 3)  # no points is a cloud too
    ints = points_xyz([[1, 2, 3]], "xyz")
    assert ints.dtype == np.float64 and ints.tolist() == [[1.0, 2.0, 3.0]]


@pytest.mark.parametrize("bad, kwargs, message", [
    (np.zeros((1000, 6)), {}, r"^f: xyz: expected points of shape \(N, 3\), got \(1000, 6\)$"),
    (np.zeros(9), {}, r"shape \(N, 3\), got \(9,\)$"),  # not 3 points
    (np.zeros((4, 3)), {"columns": 2}, r"shape \(N, 2\), got \(4, 3\)$"),
    (np.zeros((4, 0)), {"columns": None}, r"shape \(N, D\), got \(4, 0\)$"),
    (np.zeros((0, 3)), {"min_points": 1}, r"shape \(N, 3\) with N >= 1, got \(0, 3\)$"),
    (np.ones((4, 3), bool), {}, "expected numbers, got dtype bool"),
    (np.array([["a", "b", "c"]]), {}, "expected numbers, got dtype <U1"),
    ([[0.0, 1.0, 2.0], [3.0]], {}, "not an array of numbers"),
    (np.array([[0.0, 0.0, np.nan], [0.0, np.inf, 0.0], [1.0, 1.0, 1.0]]), {},
     "2 of 3 points have a NaN or infinite coordinate"),
])
def test_points_xyz_refuses_naming_the_argument_and_what_it_got(bad, kwargs, message):
    with pytest.raises(CloudFormatError, match=message) as err:
        points_xyz(bad, "f: xyz", **kwargs)
    assert str(err.value).startswith("f: xyz: ")


def test_points_xyz_drops_or_keeps_non_finite_rows_when_asked():
    xyz = np.array([[0.0, 0.0, np.nan], [1.0, 2.0, 3.0], [-np.inf, 0.0, 0.0]])
    assert points_xyz(xyz, "xyz", nonfinite="drop").tolist() == [[1.0, 2.0, 3.0]]
    kept = points_xyz(xyz, "xyz", nonfinite="keep")
    assert kept is xyz
    xy = points_xyz(np.zeros((5, 2)), "xy", columns=2)
    assert xy.shape == (5, 2)
    features = points_xyz(np.zeros((5, 7)), "x", columns=None, min_points=5)
    assert features.shape == (5, 7)


@pytest.mark.parametrize("n, cells, ratio", [(0, 1, 2.0), (1, 1, 2.0), (30000, 5000, 2.0),
                                             (5000, 10**12, 2.0), (5000, 30000, 8.0),
                                             (5000, 30000, 2.0), (5000, 2**23, 1e9)])
def test_unique_ints_matches_numpy_on_small_and_large_grids(n, cells, ratio):
    # a small grid goes through the table, a large one through np.unique: same answer
    keys = np.random.default_rng(2).integers(0, cells, n)
    distinct, inverse = unique_ints(keys, table_ratio=ratio)
    expected, expected_inverse = np.unique(keys, return_inverse=True)
    assert np.array_equal(distinct, expected)
    assert np.array_equal(inverse, expected_inverse.ravel())
    assert np.array_equal(distinct[inverse], keys)


def test_all_columns_does_not_modify_its_input():
    mask = np.array([[True, False], [True, True]])
    all_columns(mask)
    assert mask[0, 0]


def test_single_threaded_blas_limits_blas():
    from threadpoolctl import threadpool_info

    single_threaded_blas()
    blas = [p for p in threadpool_info() if p["user_api"] == "blas"]
    assert blas and all(p["num_threads"] == 1 for p in blas)


def test_release_free_memory_hands_freed_pages_back():
    def rss_mb() -> float:
        import os

        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

    # Freeing an 8 MB array raises glibc's mmap threshold, so the arrays below come from
    # the heap; freeing every other one leaves ~160 MB of free pages resident until trimmed.
    rng = np.random.default_rng(0)
    big = np.ones(10**6)
    del big
    arrays = [np.ones(int(n)) for n in rng.integers(20_000, 60_000, 1000)]
    del arrays[::2]
    before = rss_mb()
    release_free_memory()
    assert rss_mb() < before - 50


def test_reuse_freed_memory_is_set_on_glibc():
    # the CI machine is glibc Linux; mallopt says 1 for each of the three settings
    import platform

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("glibc only")
    assert reuse_freed_memory() is True


def test_cell_index_puts_a_point_on_an_edge_in_the_same_cell_wherever_the_cloud_lies():
    # heights 0.793 and 1.043 m (AHN4, 1 mm lattice): 1.043 - 0.793 is 0.2499999999999999
    # in binary, the same two points moved 2 km up 0.25
    assert 1.043 - 0.793 < 0.25 <= (1.043 + 2000.0) - (0.793 + 2000.0)
    for lo, z in ((0.793, 1.043), (2000.793, 2001.043), (0.793, 1.543)):
        offset = np.array([z - lo])
        assert cell_index(offset, 0.25)[0] == round((z - lo) / 0.25)
    assert np.array_equal(cell_index(np.array([-0.3, 0.0, 0.2499, 0.75, 1.7]), 0.25),
                          [-2, 0, 0, 3, 6])
    assert cell_index(np.array([0.5]), 1.0).dtype == np.int64


def test_snap_micrometres_rounds_in_place():
    a = np.array([[0.2499999999999773, -1.0000004], [3.0000006, 7.0]])
    assert snap_micrometres(a) is a
    assert np.array_equal(a, [[0.25, -1.0], [3.000001, 7.0]])


@pytest.mark.parametrize("repeats", [0, 1, 3])
def test_distinct_points_are_numpys_unique_rows_in_order_of_first_occurrence(repeats):
    rng = np.random.default_rng(repeats)
    xyz = np.round(rng.uniform(0, 50, (20000, 3)), 2)
    if repeats:
        xyz = np.concatenate([xyz] + [xyz[rng.random(len(xyz)) < 0.2]] * repeats)
        xyz = xyz[rng.permutation(len(xyz))]
    found = distinct_points(xyz)
    if repeats == 0:
        assert found is None
        return
    first, inverse = found
    _, expected_first = np.unique(xyz, axis=0, return_index=True)
    assert np.array_equal(first, np.sort(expected_first))
    assert np.array_equal(xyz[first][inverse], xyz)
    assert distinct_points(np.array([[0.0, -0.0, 1.0], [0.0, 0.0, 1.0]]))[0].tolist() == [0]
    assert distinct_points(np.zeros((1, 3))) is None


def test_a_stop_signal_during_a_threaded_query_waits_for_it_to_end():
    # SciPy joins a parallel query's threads in Python: a Ctrl-C raised in the join left
    # them writing into freed arrays, and `evaluate` segfaulted after "interrupted"
    import os
    import signal
    import threading

    from scipy.spatial import cKDTree

    from lidar_obstacles.core.arrays import stop_signals_held, tree_query

    rng = np.random.default_rng(0)
    data, query = rng.random((200_000, 3)), rng.random((200_000, 3))
    tree = cKDTree(data)
    expected = tree.query(query, k=8)
    assert np.array_equal(tree_query(tree, query, k=8, workers=-1)[1], expected[1])
    timer = threading.Timer(0.02, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    with pytest.raises(KeyboardInterrupt):
        tree_query(tree, query, k=8, workers=-1)  # the Ctrl-C comes inside it
        # (only when it has ended, so that no thread of SciPy's is still writing)
    timer.join()
    assert [t for t in threading.enumerate() if t is not threading.main_thread()] == []
    # held and delivered once, to the handler that was there before
    seen = []
    before = signal.signal(signal.SIGTERM, lambda s, f: seen.append(s))
    try:
        with stop_signals_held():
            os.kill(os.getpid(), signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGTERM)
            assert seen == []
        assert seen == [signal.SIGTERM]
    finally:
        signal.signal(signal.SIGTERM, before)
