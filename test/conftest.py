"""Shared test setup: isolated DDS, paths to the shared real data."""
from __future__ import annotations

import os
import random
from pathlib import Path

import pytest

# Every test run gets its own DDS domain and never talks beyond this machine.
os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random(os.getpid()).randint(1, 101)))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"


def data_file(relative: str) -> Path:
    """Path of a file in ../shared/data, or skip the test with the reason."""
    path = DATA / relative
    if not path.is_file():
        pytest.skip(f"shared data not present: {path}")
    return path
