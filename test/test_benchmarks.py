"""The benchmarks still run. CI never runs `make bench` (25 minutes, anchors installed), so a
change in the package that broke a benchmark went unseen until the next full run; here each
script's --smoke run (every code path on tiny inputs, the anchors that are not installed
skipped) must exit 0 and write its results where it is told, never into
benchmarks/results."""
from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import REPO

BENCH = REPO / "benchmarks"
SCRIPTS = sorted(path.name for path in BENCH.glob("bench_*.py"))


def committed_results() -> dict[str, int]:
    return {path.name: path.stat().st_mtime_ns for path in (BENCH / "results").iterdir()}


@pytest.mark.slow
@pytest.mark.parametrize("script", SCRIPTS)
def test_smoke_run(script, tmp_path):
    before = committed_results()
    # The environment is conftest's: this run's ROS_DOMAIN_ID and discovery on this machine
    # only, for the nodes bench_pipeline starts.
    res = subprocess.run([sys.executable, str(BENCH / script), "--smoke", "--out", str(tmp_path)],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, f"{res.stdout[-2000:]}\n{res.stderr[-4000:]}"
    name = script.removeprefix("bench_").removesuffix(".py")
    assert (tmp_path / f"{name}.json").is_file(), res.stdout[-2000:]
    assert committed_results() == before


@pytest.mark.parametrize("out", [[], ["--out", str(BENCH / "results")]])
def test_smoke_refuses_the_committed_results(out):
    res = subprocess.run([sys.executable, str(BENCH / "run_all.py"), "--smoke", *out],
                         cwd=REPO, capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    assert "--smoke needs --out DIR" in res.stderr


@pytest.mark.slow
def test_memory_only_run_writes_its_own_file(tmp_path):
    """`bench_pipeline.py --memory-only` (the 30-minute flight's memory, on its own) writes
    pipeline_memory.json with the growth, and no pipeline.json."""
    res = subprocess.run([sys.executable, str(BENCH / "bench_pipeline.py"), "--smoke",
                          "--memory-only", "--out", str(tmp_path)],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-4000:]
    import json

    memory = json.loads((tmp_path / "pipeline_memory.json").read_text())
    assert memory["messages"] == 20 and memory["rss_end_mb"] > 0
    assert memory["growth"] == pytest.approx(memory["rss_end_mb"]
                                             / memory["rss_after_10pct_mb"] - 1, abs=1e-3)
    assert not (tmp_path / "pipeline.json").exists()
    assert "memory growth over" in res.stdout


@pytest.mark.slow
def test_only_reruns_splice_their_sections_into_the_summary(tmp_path):
    """`run_all.py --only NAME`: just that benchmark runs, and its section replaces the one
    of the existing summary, marked as rerun; the other sections stay as they were."""
    def run_all(*names):
        res = subprocess.run([sys.executable, str(BENCH / "run_all.py"), "--smoke", "--out",
                              str(tmp_path), "--only", *names],
                             cwd=REPO, capture_output=True, text=True, timeout=300)
        assert res.returncode == 0, res.stderr[-4000:]
        return (tmp_path / "summary.md").read_text()

    first = run_all("simulate", "pointcloud2")
    assert first.startswith("# Benchmarks (") and "rerun alone" in first
    kept = first[first.index("## simulate ("):]
    second = run_all("pointcloud2")
    assert second.index("## pointcloud2 (") < second.index("## simulate (")
    assert second.endswith(kept)  # simulate's section untouched
    assert second.count("## pointcloud2 (") == 1
