"""The package builds the ROS way, the core never needs ROS, the metadata is complete."""
from __future__ import annotations

import ast
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from conftest import REPO

BLOCK_ROS = r"""
import importlib.abc, sys
BLOCKED = ("rclpy", "rcl_interfaces", "builtin_interfaces", "std_msgs", "sensor_msgs",
           "nav_msgs", "geometry_msgs", "visualization_msgs", "diagnostic_msgs", "std_srvs",
           "rosidl_runtime_py", "rpyutils")
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"ROS is blocked in this test: {name}")
        return None
sys.meta_path.insert(0, Block())
import importlib, pkgutil, lidar_obstacles, lidar_obstacles.core, lidar_obstacles.io
import lidar_obstacles.config, lidar_obstacles.errors
names = []
for pkg in (lidar_obstacles.core, lidar_obstacles.io):
    for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
        importlib.import_module(info.name)
        names.append(info.name)
leaked = [m for m in sys.modules if m.split(".")[0] in BLOCKED]
assert not leaked, leaked
print("imported", len(names), "modules")
"""


def test_core_imports_without_ros():
    out = subprocess.run([sys.executable, "-c", BLOCK_ROS], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert int(re.search(r"imported (\d+) modules", out.stdout).group(1)) >= 5


def test_package_xml_declares_every_ros_import():
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.get("format") == "3"
    deps = {e.text for e in root if e.tag.endswith("depend")}
    imported = set()
    for path in [*(REPO / "lidar_obstacles").rglob("*.py"), *(REPO / "launch").glob("*.py")]:
        for m in re.finditer(r"^\s*(?:from|import) (\w+)", path.read_text(), re.M):
            imported.add(m.group(1))
    ros_pkgs = {p for p in imported
                if p.endswith(("_msgs", "_srvs", "_interfaces", "_python"))
                or p in ("rclpy", "launch", "launch_ros")}
    assert ros_pkgs >= {"rclpy", "launch", "launch_ros"}, "the nodes and the launch file"
    assert ros_pkgs <= deps, ros_pkgs - deps
    assert root.find("export/build_type").text == "ament_python"


def test_setup_passes_no_option_setuptools_dropped():
    # setuptools 72 dropped `setup.py test` and with it `tests_require`/`test_suite`: every
    # install printed "Unknown distribution option: 'tests_require'". pytest comes from
    # requirements-dev.txt instead.
    tree = ast.parse((REPO / "setup.py").read_text())
    (call,) = [node for node in ast.walk(tree) if isinstance(node, ast.Call)
               and isinstance(node.func, ast.Name) and node.func.id == "setup"]
    assert not {k.arg for k in call.keywords} & {"tests_require", "test_suite"}
    assert re.search(r"^pytest==", (REPO / "requirements-dev.txt").read_text(), re.M)


def _workspace(tmp_path: Path) -> Path:
    src = tmp_path / "src" / "lidar_obstacles"
    files = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True,
                           check=True).stdout.split()
    for rel in files:
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / rel, src / rel)
    return tmp_path


@pytest.mark.slow
def test_code_is_flake8_clean():
    # style (setup.cfg: 100 columns) and pyflakes: unused imports and names, undefined ones
    res = subprocess.run([sys.executable, "-m", "flake8", "lidar_obstacles", "test",
                          "benchmarks", "docs", "launch", "setup.py"], cwd=REPO,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr


@pytest.mark.slow
def test_the_package_is_mypy_clean():
    # the architecture's "mypy-clean core", and the nodes and tools too (setup.cfg's [mypy];
    # ~25 s without a cache)
    res = subprocess.run([sys.executable, "-m", "mypy", "lidar_obstacles"], cwd=REPO,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr


def test_colcon_build_and_installed_node_starts(tmp_path):
    colcon = shutil.which("colcon", path=str(Path(sys.executable).parent))
    if colcon is None:
        pytest.fail("colcon is not installed in this environment (requirements-dev.txt has it)")
    ws = _workspace(tmp_path)
    build = subprocess.run([colcon, "build", "--base-paths", "src"], cwd=ws, capture_output=True,
                           text=True, timeout=300)
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    share = ws / "install" / "lidar_obstacles" / "share" / "lidar_obstacles"
    for rel in ("package.xml", "config/obstacle_detector.yaml", "config/dem_builder.yaml",
                "config/cloud_simplifier.yaml", "config/fastdds_large_data.xml",
                "launch/lidar_obstacles.launch.py"):
        assert (share / rel).is_file(), rel
    for name in ("obstacle_detector", "dem_builder", "cloud_simplifier"):  # the contract's
        exe = ws / "install" / "lidar_obstacles" / "lib" / "lidar_obstacles" / name
        assert exe.is_file(), name
    assert (ws / "install/lidar_obstacles/share/ament_index/resource_index/packages/"
            "lidar_obstacles").is_file()
    exe = ws / "install" / "lidar_obstacles" / "lib" / "lidar_obstacles" / "obstacle_detector"
    assert exe.is_file()
    site = next((ws / "install" / "lidar_obstacles" / "lib").glob("python*/site-packages"))
    env = dict(os.environ, PYTHONPATH=str(site))
    # the package comes from the installed tree, not from the checkout (this venv's editable
    # install would stand in for an install tree that lacks it)
    where = subprocess.run([sys.executable, "-c", "import lidar_obstacles.ros.obstacle_detector "
                            "as m; print(m.__file__)"], env=env, cwd=tmp_path,
                           capture_output=True, text=True, timeout=60)
    assert Path(where.stdout.strip()).is_relative_to(ws / "install"), where.stdout + where.stderr
    proc = subprocess.Popen([sys.executable, str(exe), "--ros-args", "-p", "tiling.size:=30.0",
                             "--params-file", str(share / "config" / "obstacle_detector.yaml")],
                            cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 60
        lines = []
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "ready" in line:
                break
        assert any("subscribed to /points" in x for x in lines), "".join(lines)
        assert any("ready" in x for x in lines), "".join(lines)
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=30)
        assert code == 0, "".join(lines) + proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()


def test_the_launch_file_declares_the_standard_arguments_and_passes_them(monkeypatch):
    """`launch` is not installed here: the launch file runs against stand-ins that record
    what it builds. It had no use_sim_time (launch's usual way: a `/**` params file, which
    the nodes then refused), no params file of the user's, no log level, and no way to
    the large-data profile the README advises."""
    import types

    built: dict[str, list] = {"args": [], "nodes": [], "env": []}

    class Recorder:
        def __init__(self, *args, **kwargs):
            self.args, self.kwargs = args, kwargs

    class Config(Recorder):
        def __repr__(self):
            return f"${self.args[0]}"

    def declare(name, **kwargs):
        built["args"].append((name, kwargs))

    def node(**kwargs):
        built["nodes"].append(kwargs)

    def env(name, value, **kwargs):
        built["env"].append((name, value, kwargs))

    modules = {
        "ament_index_python": types.ModuleType("ament_index_python"),
        "ament_index_python.packages": types.SimpleNamespace(
            get_package_share_directory=lambda pkg: str(REPO)),
        "launch": types.SimpleNamespace(LaunchDescription=lambda actions: actions),
        "launch.actions": types.SimpleNamespace(DeclareLaunchArgument=declare,
                                                SetEnvironmentVariable=env),
        "launch.conditions": types.SimpleNamespace(IfCondition=Recorder),
        "launch.substitutions": types.SimpleNamespace(LaunchConfiguration=Config),
        "launch_ros": types.ModuleType("launch_ros"),
        "launch_ros.actions": types.SimpleNamespace(Node=node),
    }
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    source = (REPO / "launch" / "lidar_obstacles.launch.py").read_text()
    scope: dict = {}
    exec(compile(source, "lidar_obstacles.launch.py", "exec"), scope)
    scope["generate_launch_description"]()
    args = dict(built["args"])
    assert {"points", "odom", "namespace", "simplifier", "use_sim_time", "detector_params",
            "dem_params", "simplifier_params", "log_level", "large_data"} <= set(args)
    for key in ("detector_params", "dem_params", "simplifier_params"):
        assert Path(args[key]["default_value"]).is_file(), key  # the shipped files
    assert [n["executable"] for n in built["nodes"]] == ["obstacle_detector", "dem_builder",
                                                         "cloud_simplifier"]
    for n, params in zip(built["nodes"], ("detector_params", "dem_params", "simplifier_params")):
        assert repr(n["parameters"][0]) == f"${params}"
        assert repr(n["parameters"][1]["use_sim_time"]) == "$use_sim_time"
        assert repr(n["namespace"]) == "$namespace"
        remaps = [(a, repr(b)) for a, b in n["remappings"]]
        assert remaps == [("points", "$points"), ("odom", "$odom")]
        assert n["ros_arguments"][0] == "--log-level"
    (name, value, kwargs), = built["env"]
    assert name == "FASTRTPS_DEFAULT_PROFILES_FILE" and Path(value).is_file()
    assert repr(kwargs["condition"].args[0]) == "$large_data"
