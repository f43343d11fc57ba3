"""The public contract (../shared/design/interfaces.md), read from the page itself, against
what is built: executables, subcommands and their options, ASPRS classes, parameters, and
the topics, services and types of the running nodes. When the page changes, this says what
no longer matches."""
from __future__ import annotations

import importlib
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import REPO

CONTRACT = REPO.parent / "shared" / "design" / "interfaces.md"


@pytest.fixture(scope="module")
def contract() -> str:
    if not CONTRACT.is_file():
        pytest.skip(f"the contract is not present: {CONTRACT}")
    return CONTRACT.read_text()


def _section(text: str, heading: str) -> str:
    """The text under the `## heading` line, up to the next `## `."""
    start = text.index(f"## {heading}")
    end = text.find("\n## ", start + 1)
    return text[start:end if end >= 0 else len(text)]


def test_every_executable_is_installed_as_a_console_script(contract):
    names = re.findall(r"^\| `([\w-]+)` \|", _section(contract, "Executables"), re.M)
    assert {"obstacle_detector", "dem_builder", "lidar-obstacles"} <= set(names)
    setup = (REPO / "setup.py").read_text()
    for name in names:
        entry = re.search(rf'"{re.escape(name)} = (lidar_obstacles\.[\w.]+):(\w+)"', setup)
        assert entry, name
        assert callable(getattr(importlib.import_module(entry[1]), entry[2])), name


def test_every_subcommand_and_option_exists(contract):
    from lidar_obstacles.cli import build_parser

    parser = build_parser()
    subparsers = next(a for a in parser._actions if a.dest == "command").choices
    rows = re.findall(r"^\| `([\w-]+)[^`]*` \| (.*) \|$",
                      _section(contract, "`lidar-obstacles` subcommands"), re.M)
    assert len(rows) >= 10
    for command, text in rows:
        assert command in subparsers, command
        options = {o for a in subparsers[command]._actions for o in a.option_strings}
        for option in re.findall(r"`(--[a-z-]+)", text):
            assert option in options, f"{command} {option}"


def test_asprs_classes_are_the_contracts(contract):
    from lidar_obstacles.core.classes import CLASS_NAMES

    text = _section(contract, "ASPRS classes")
    codes = {int(c) for c in re.findall(r"(?:^|, )(\d+) [a-z]", text.split("\n", 1)[1], re.M)}
    assert codes == set(CLASS_NAMES)


def test_every_parameter_named_exists(contract):
    from lidar_obstacles.config import NODE_CONFIGS, params_of

    known = {p.name for cls in NODE_CONFIGS.values() for p in params_of(cls)}
    named = set(re.findall(r"`([a-z_]+(?:\.[a-z_]+)+)`", contract))
    named |= set(re.findall(r"`([a-z_]+): (?:true|false)`", contract))
    assert {"tiling.size", "input.reliability", "use_odometry", "export.path"} <= named
    assert named <= known, named - known


def _interfaces(text: str) -> list[tuple[str, str]]:
    """(name, ROS type) of every topic or service in a part of the Topics section, e.g.
    ("dem_info", "nav_msgs/msg/MapMetaData"), ("save_dem", "std_srvs/srv/Trigger")."""
    text = re.sub(r"\s+", " ", text)  # (an entry may wrap to the next line)
    out = []
    for names, package, kind in re.findall(
            r"((?:`[\w/]+`(?: and |, ))*`[\w/]+`) — `(\w+)/(\w+)`", text):
        sub = "srv" if f"service {names}" in text else "msg"
        out += [(n, f"{package}/{sub}/{kind}") for n in re.findall(r"`([\w/]+)`", names)]
    return out


def test_the_topic_list_is_read_from_the_contract(contract):
    topics = _section(contract, "Topics")
    detector = _interfaces(topics.split("`obstacle_detector` publishes:")[1].split(
        "`dem_builder` publishes:")[0])
    assert ("obstacle_markers", "visualization_msgs/msg/MarkerArray") in detector
    assert {("save_dem", "std_srvs/srv/Trigger"),
            ("dem_info", "nav_msgs/msg/MapMetaData")} <= set(_interfaces(topics))


NODES = {"obstacle_detector": ["-p", "features.enabled:=true"],  # (obstacle_edges too)
         "dem_builder": [], "cloud_simplifier": []}


@pytest.mark.slow
@pytest.mark.parametrize("node", list(NODES))
def test_a_running_node_offers_the_contracts_topics_and_services(contract, node):
    import rclpy

    topics = _section(contract, "Topics")
    inputs = _interfaces(topics.split("Outputs are published")[0])
    outputs = _interfaces(topics.split(f"`{node}` publishes")[1].split("` publishes")[0])
    outputs.append(("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"))  # every node
    ns = "/contract_test"
    exe = Path(sys.executable).parent / node
    cmd = [str(exe)] if exe.is_file() else [sys.executable, "-m", f"lidar_obstacles.scripts.{node}"]
    proc = subprocess.Popen(cmd + ["--ros-args", "-r", f"__ns:={ns}", *NODES[node]], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    probe = rclpy.create_node("contract_probe")

    def offered() -> dict[str, set[tuple[str, str]]]:
        def pairs(found):
            return {(name, t) for name, types in found for t in types}
        return {"pub": pairs(probe.get_publisher_names_and_types_by_node(node, ns)),
                "sub": pairs(probe.get_subscriber_names_and_types_by_node(node, ns)),
                "srv": pairs(probe.get_service_names_and_types_by_node(node, ns))}

    def absolute(name: str) -> str:
        return name if name.startswith("/") else f"{ns}/{name}"

    want = {"pub": {(absolute(n), t) for n, t in outputs if "/srv/" not in t},
            "srv": {(absolute(n), t) for n, t in outputs if "/srv/" in t},
            "sub": {(absolute(n), t) for n, t in inputs}}
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            have = offered() if node in probe.get_node_names() else None
            if have and all(want[k] <= have[k] for k in want):
                break
            assert proc.poll() is None, proc.stdout.read()
            rclpy.spin_once(probe, timeout_sec=0.2)
        for kind in want:
            assert want[kind] <= have[kind], (kind, want[kind] - have[kind])
    finally:
        probe.destroy_node()
        rclpy.try_shutdown()
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    assert proc.returncode == 0
