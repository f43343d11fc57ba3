"""The `dem_builder` executable's console script: only the standard library is imported
before main (see lidar_obstacles.scripts)."""
from __future__ import annotations

from lidar_obstacles.scripts import exit_as_module, start


def main(args: list[str] | None = None) -> int:
    return start("dem_builder", args)


# `python -m lidar_obstacles.scripts.dem_builder`: where the executable is not installed
if __name__ == "__main__":
    exit_as_module("dem_builder")
