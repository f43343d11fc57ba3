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
