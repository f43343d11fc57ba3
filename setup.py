"""ament_python setup: installs the package, its config and launch files, and the executables."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "lidar_obstacles"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks", "benchmarks.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*")),
        (f"share/{PACKAGE}/launch", glob("launch/*")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="lidar_obstacles developers",
    maintainer_email="dev@lidar-obstacles.invalid",
    description="Flight-obstacle extraction and rolling DEMs from airborne LiDAR for UAVs",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "obstacle_detector = lidar_obstacles.scripts.obstacle_detector:console",
            "dem_builder = lidar_obstacles.scripts.dem_builder:console",
            "cloud_simplifier = lidar_obstacles.scripts.cloud_simplifier:console",
            "lidar-obstacles = lidar_obstacles.cli:console",
        ],
    },
)
