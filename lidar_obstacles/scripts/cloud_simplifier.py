"""The `cloud_simplifier` executable's console script: only the standard library is imported
before main (see lidar_obstacles.scripts)."""
from __future__ import annotations

from typing import NoReturn

from lidar_obstacles.scripts import exit_as_module, start


def main(args: list[str] | None = None) -> int:
    """Run the node on `args` (default: the process's command line); its exit status."""
    return start("cloud_simplifier", args)


def console() -> NoReturn:
    """The `cloud_simplifier` executable: `main`, then the exit (see `exit_process`)."""
    exit_as_module("cloud_simplifier")


# `python -m lidar_obstacles.scripts.cloud_simplifier`: where the executable is not installed
if __name__ == "__main__":
    exit_as_module("cloud_simplifier")
