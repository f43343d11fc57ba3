"""The `obstacle_detector` executable's console script: only the standard library is imported
before main (see lidar_obstacles.scripts)."""
from __future__ import annotations

from lidar_obstacles.scripts import exit_as_module, start


def main(args: list[str] | None = None) -> int:
    return start("obstacle_detector", args)


# `python -m lidar_obstacles.scripts.obstacle_detector`: where the executable is not installed
if __name__ == "__main__":
    exit_as_module("obstacle_detector")
