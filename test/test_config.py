"""The one config schema: validation, params files, the generated YAML in config/."""
from __future__ import annotations

import dataclasses

import pytest

from conftest import REPO
from lidar_obstacles.config import (
    NODE_CONFIGS,
    CloudSimplifierConfig,
    DemBuilderConfig,
    ObstacleDetectorConfig,
    dump_ros_yaml,
    flatten,
    load_params_file,
    params_of,
    replace,
)
from lidar_obstacles.errors import ConfigError


def test_every_parameter_is_documented_with_range_or_choices():
    for cls in NODE_CONFIGS.values():
        for p in params_of(cls):
            assert p.spec.description, p.name
            if p.type in (int, float):
                assert p.spec.min is not None and p.spec.max is not None, p.name
                assert p.spec.min <= p.default <= p.spec.max, p.name
            if p.spec.choices:
                assert p.default in p.spec.choices, p.name


def test_config_files_are_generated_from_the_schema():
    for node, cls in NODE_CONFIGS.items():
        text = (REPO / "config" / f"{node}.yaml").read_text()
        assert dump_ros_yaml(cls(), f"/**/{node}") in text, (
            f"config/{node}.yaml is stale: run `python -m lidar_obstacles.config`")
        assert load_params_file(REPO / "config" / f"{node}.yaml", cls, node) == cls()


def test_every_number_has_a_unit():
    # the contract: a description, a unit and a range in every ParameterDescriptor
    for cls in NODE_CONFIGS.values():
        for p in params_of(cls):
            assert p.spec.description
            if p.type in (int, float):
                assert p.spec.unit, p.name
                assert p.spec.min is not None and p.spec.max is not None, p.name


def test_parameter_docs_are_generated_from_the_schema():
    from lidar_obstacles.config import markdown_tables

    assert (REPO / "docs" / "parameters.md").read_text() == markdown_tables(), (
        "docs/parameters.md is stale: run `python -m lidar_obstacles.config`")


def test_replace_validates_and_is_all_or_nothing():
    cfg = ObstacleDetectorConfig()
    new = replace(cfg, {"ransac.distance_threshold": 0.5, "tiling.size": 20})
    assert new.ransac.distance_threshold == 0.5 and new.tiling.size == 20.0
    assert cfg.ransac.distance_threshold != 0.5  # frozen, untouched
    with pytest.raises(ConfigError, match="ransac.distance_threshold.*range"):
        replace(cfg, {"tiling.size": 30.0, "ransac.distance_threshold": -1.0})
    with pytest.raises(ConfigError, match="unknown parameter 'nope'"):
        replace(cfg, {"nope": 1})
    with pytest.raises(ConfigError, match="ground.method"):
        replace(cfg, {"ground.method": "magic"})
    with pytest.raises(ConfigError, match="expected an integer"):
        replace(cfg, {"tin.max_iterations": 2.5})
    with pytest.raises(ConfigError, match="expected true or false"):
        replace(cfg, {"use_odometry": 1})
    with pytest.raises(ConfigError, match="finite"):
        replace(cfg, {"tiling.size": float("nan")})


@pytest.mark.parametrize("name, value, message", [
    # YAML `true` (or `ros2 param set ... true`) is a Python bool, and bool is an int
    ("tin.max_iterations", True, "expected an integer, got True"),
    ("tiling.size", False, "expected a number, got False"),
    ("tiling.size", "40", "expected a number, got '40'"),
    ("tiling.size", 1000.5, "1000.5 is outside its range"),
    ("tin.max_iterations", 501, "501 is outside its range"),
])
def test_a_value_of_the_wrong_type_or_past_the_maximum_is_refused(name, value, message):
    with pytest.raises(ConfigError, match=f"parameter '{name}': {message}"):
        replace(ObstacleDetectorConfig(), {name: value})


def test_the_range_bounds_themselves_are_accepted():
    cfg = replace(ObstacleDetectorConfig(), {"tiling.size": 1000.0, "tin.max_iterations": 1,
                                             "ground.threshold": 0.05})
    assert (cfg.tiling.size, cfg.tin.max_iterations, cfg.ground.threshold) == (1000.0, 1, 0.05)


def test_params_file_forms(tmp_path):
    nested = tmp_path / "nested.yaml"
    nested.write_text("/**:\n  ros__parameters:\n    tiling:\n      size: 25.0\n"
                      "    dem:\n      resolution: 0.5\n")
    det = load_params_file(nested, ObstacleDetectorConfig, "obstacle_detector")
    dem = load_params_file(nested, DemBuilderConfig, "dem_builder")
    assert det.tiling.size == 25.0 and dem.dem.resolution == 0.5 and dem.tiling.size == 25.0
    dotted = tmp_path / "dotted.yaml"
    dotted.write_text("obstacle_detector:\n  ros__parameters:\n    ransac.distance_threshold: 0.4\n"
                      "dem_builder:\n  ros__parameters:\n    dem.resolution: 2.0\n")
    assert load_params_file(dotted, ObstacleDetectorConfig, "obstacle_detector") \
        .ransac.distance_threshold == 0.4
    assert load_params_file(dotted, ObstacleDetectorConfig, "obstacle_detector") \
        .tiling == ObstacleDetectorConfig().tiling
    bad = tmp_path / "bad.yaml"
    bad.write_text("/**:\n  ros__parameters:\n    tiling:\n      sise: 25.0\n")
    with pytest.raises(ConfigError, match="unknown parameter 'tiling.sise'"):
        load_params_file(bad, ObstacleDetectorConfig, "obstacle_detector")
    with pytest.raises(ConfigError, match="not found"):
        load_params_file(tmp_path / "missing.yaml", ObstacleDetectorConfig, "x")
    # a misspelt node is no node of ours; another package's node beside ours is fine
    typo = tmp_path / "typo.yaml"
    typo.write_text("obstacle_detektor:\n  ros__parameters:\n    tiling.size: 30.0\n")
    with pytest.raises(ConfigError, match="no section for obstacle_detector.*obstacle_detektor"):
        load_params_file(typo, ObstacleDetectorConfig, "obstacle_detector")
    shared = tmp_path / "shared.yaml"
    shared.write_text("flight_stack:\n  ros__parameters:\n    rate: 5\n"
                      "/**/obstacle_detector:\n  ros__parameters:\n    tiling.size: 30.0\n")
    assert load_params_file(shared, ObstacleDetectorConfig, "obstacle_detector").tiling.size == 30
    # rclpy's own parameters are rclpy's: launch's use_sim_time under /**, and the outputs'
    # qos_overrides as `ros2 param dump` writes them (both stopped the nodes: "unknown")
    ros = tmp_path / "ros.yaml"
    ros.write_text("/**:\n  ros__parameters:\n    use_sim_time: true\n"
                   "/**/obstacle_detector:\n  ros__parameters:\n    tiling.size: 31.0\n"
                   "    start_type_description_service: true\n    qos_overrides:\n"
                   "      /uav1/clearance:\n        publisher:\n          depth: 3\n")
    assert load_params_file(ros, ObstacleDetectorConfig, "obstacle_detector").tiling.size == 31
    # a value bad for the other node is bad input for this one too (one shared file)
    magic = tmp_path / "magic.yaml"
    magic.write_text("/**:\n  ros__parameters:\n    ground.method: magic\n")
    with pytest.raises(ConfigError, match="magic.yaml.*ground.method"):
        load_params_file(magic, CloudSimplifierConfig, "cloud_simplifier")
    for text, what in (("/**:\n  ros__parameters: [1, 2]\n", "not a mapping"),
                       ("/**:\n  ros__parameters: 7\n", "not a mapping")):
        odd = tmp_path / "odd.yaml"
        odd.write_text(text)
        with pytest.raises(ConfigError, match=what):
            load_params_file(odd, ObstacleDetectorConfig, "obstacle_detector")
    twice = tmp_path / "twice.yaml"
    twice.write_text("/**:\n  ros__parameters:\n    tiling.size: 30.0\n"
                     "    tiling:\n      size: 20.0\n")
    with pytest.raises(ConfigError, match="twice.yaml: parameter 'tiling.size' is given twice"):
        load_params_file(twice, ObstacleDetectorConfig, "obstacle_detector")
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00garbage\x80")
    with pytest.raises(ConfigError, match="binary.yaml"):
        load_params_file(binary, ObstacleDetectorConfig, "obstacle_detector")
    broken = tmp_path / "broken.yaml"
    broken.write_text("a: [1, 2\n")
    with pytest.raises(ConfigError, match="broken.yaml"):
        load_params_file(broken, ObstacleDetectorConfig, "obstacle_detector")


@pytest.mark.parametrize("text, expected", [
    ("not: [valid", "line 1, column 12: expected ',' or ']', but got '<stream end>'"),
    ("/**:\n  ros__parameters:\n    a: b: c\n",
     "line 3, column 9: mapping values are not allowed here"),
])
def test_malformed_yaml_says_what_is_wrong_and_where(tmp_path, text, expected):
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_params_file(bad, ObstacleDetectorConfig, "obstacle_detector")
    assert str(info.value) == f"params file {bad}: {expected}"


def test_flatten_roundtrip():
    cfg = DemBuilderConfig()
    flat = flatten(cfg)
    assert set(flat) == {p.name for p in params_of(DemBuilderConfig)}
    assert replace(cfg, flat) == cfg
    assert all(dataclasses.is_dataclass(getattr(cfg, f.name)) or f.name in flat
               for f in dataclasses.fields(cfg))


def test_a_node_section_with_another_nodes_parameter_is_an_error(tmp_path):
    # `dem.resolution` under `obstacle_detector:` was ignored: the DEM ran at 1 m
    from lidar_obstacles.config import DemBuilderConfig, load_params_file

    wrong = tmp_path / "wrong.yaml"
    wrong.write_text("obstacle_detector:\n  ros__parameters:\n    dem:\n      resolution: 0.5\n")
    for cls, node in ((ObstacleDetectorConfig, "obstacle_detector"),
                      (DemBuilderConfig, "dem_builder")):  # whichever command reads it
        with pytest.raises(ConfigError, match=r"obstacle_detector has no parameter "
                           r"'dem.resolution' \(a parameter of dem_builder: put it under that "
                           r"node or /\*\*\)$"):
            load_params_file(wrong, cls, node)
    shared = tmp_path / "shared.yaml"  # /** may mix them; each node takes its own
    shared.write_text("/**:\n  ros__parameters:\n    dem.resolution: 0.5\n    tiling.size: 40.0\n")
    assert load_params_file(shared, DemBuilderConfig, "dem_builder").dem.resolution == 0.5
    assert load_params_file(shared, ObstacleDetectorConfig, "obstacle_detector").tiling.size == 40


MULTI = ("/uav1/obstacle_detector:\n  ros__parameters:\n    ground.cell: 1.5\n{uav1}"
         "/uav2/obstacle_detector:\n  ros__parameters:\n    ground.cell: 2.0\n")


@pytest.mark.parametrize("uav1", ["", "    ground.method: magic\n", "    dem.resolution: 0.5\n",
                                  "    tiling.sise: 30.0\n"])
def test_a_node_reads_only_the_sections_of_a_multi_vehicle_file_that_reach_it(tmp_path, uav1):
    """One section per vehicle: /uav1's section stopped the node under /uav2 ("does not
    reach the node"), and a bad value there did too. Each node reads the sections rcl
    gives it, and only those are checked."""
    params = tmp_path / "multi.yaml"
    params.write_text(MULTI.format(uav1=uav1))
    cfg = load_params_file(params, ObstacleDetectorConfig, "obstacle_detector",
                           full_name="/uav2/obstacle_detector")
    assert (cfg.ground.cell, cfg.ground.method) == (2.0, "hybrid")
    params.write_text(MULTI.format(uav1=uav1) + "/**/obstacle_detector:\n  ros__parameters:\n"
                      "    tiling.size: 30.0\n/*/*:\n  ros__parameters:\n    ground.slope: 0.3\n")
    cfg = load_params_file(params, ObstacleDetectorConfig, "obstacle_detector",
                           full_name="/uav2/obstacle_detector")
    assert (cfg.ground.cell, cfg.tiling.size, cfg.ground.slope) == (2.0, 30.0, 0.3)
    # the root node (the offline commands') takes /**/obstacle_detector, not /*/* nor /uav2's
    cfg = load_params_file(params, ObstacleDetectorConfig, "obstacle_detector")
    assert (cfg.ground.cell, cfg.tiling.size, cfg.ground.slope) == (1.0, 30.0, 0.2)


def test_offline_commands_read_a_params_file_as_a_node_in_the_root_namespace(tmp_path):
    """`evaluate` ran ransac for a file holding only `/uav1/obstacle_detector:` (a node in
    the root namespace is given nothing of it); now that is one line naming the section and
    what reaches the node, and a section that reaches it beside /uav1's is what counts."""
    only = tmp_path / "uav1.yaml"
    only.write_text("/uav1/obstacle_detector:\n  ros__parameters:\n    ground.method: ransac\n")
    with pytest.raises(ConfigError) as info:
        load_params_file(only, ObstacleDetectorConfig, "obstacle_detector")
    assert str(info.value) == (
        f"params file {only}: section '/uav1/obstacle_detector' does not reach the node "
        "/obstacle_detector in the root namespace (rcl matches the whole name): key it "
        "'obstacle_detector' or '/**/obstacle_detector'")
    # dem_builder (replay reads the file for both) is not named: its defaults, no word
    assert load_params_file(only, DemBuilderConfig, "dem_builder") == DemBuilderConfig()
    both = tmp_path / "both.yaml"
    for root in ("obstacle_detector", "/obstacle_detector", "/**/obstacle_detector"):
        both.write_text(f"{root}:\n  ros__parameters:\n    ground.method: tin\n"
                        "/uav1/obstacle_detector:\n  ros__parameters:\n    ground.method: magic\n"
                        "    dem.resolution: 0.5\n")
        assert load_params_file(both, ObstacleDetectorConfig, "obstacle_detector") \
            .ground.method == "tin", root
    # named only where it is not reached: a `/**` beside it (launch's use_sim_time) or the
    # other vehicles' sections do not make it reach
    multi = tmp_path / "multi.yaml"
    for text in (MULTI.format(uav1=""),
                 "/**:\n  ros__parameters:\n    use_sim_time: true\n" + only.read_text()):
        multi.write_text(text)
        with pytest.raises(ConfigError, match="section '/uav1/obstacle_detector' does not "
                           "reach the node /obstacle_detector in the root namespace"):
            load_params_file(multi, ObstacleDetectorConfig, "obstacle_detector")


def test_evaluate_says_in_one_line_that_a_vehicles_section_does_not_reach_it(tmp_path):
    import subprocess
    import sys

    from conftest import data_file

    laz = data_file("isprs/samp11-utm.laz")
    params = tmp_path / "uav1.yaml"
    params.write_text("/uav1/obstacle_detector:\n  ros__parameters:\n    ground.method: ransac\n")
    res = subprocess.run([sys.executable, "-m", "lidar_obstacles.cli", "evaluate", str(laz),
                          "--params-file", str(params), "--no-dem"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert (res.returncode, res.stdout) == (2, "")
    assert res.stderr == (f"lidar-obstacles evaluate: error: params file {params}: section "
                          "'/uav1/obstacle_detector' does not reach the node /obstacle_detector "
                          "in the root namespace (rcl matches the whole name): key it "
                          "'obstacle_detector' or '/**/obstacle_detector'\n")


def test_a_clearance_grid_too_many_cells_a_side_is_refused():
    # 2 000 m at 0.1 m, each in range: 400 M cells, 10 s and 4.4 GB a cloud
    with pytest.raises(ConfigError, match="20000 cells a side, more than 2000"):
        replace(ObstacleDetectorConfig(), {"clearance.size": 2000.0, "clearance.resolution": 0.1})
    assert replace(ObstacleDetectorConfig(), {"clearance.size": 2000.0}).clearance.size == 2000
    assert replace(ObstacleDetectorConfig(), {"clearance.size": 200.0,
                                              "clearance.resolution": 0.1}).clearance.size == 200


def test_a_clearance_cell_larger_than_the_grid_is_refused():
    # size 5 m, resolution 50 m, each in range: one 50 m cell stood for the 5 m grid
    with pytest.raises(ConfigError, match="clearance.resolution 50 m is coarser than "
                                          "clearance.size 5 m: not one cell fits"):
        replace(ObstacleDetectorConfig(), {"clearance.size": 5.0, "clearance.resolution": 50.0})
    assert replace(ObstacleDetectorConfig(), {"clearance.size": 50.0,
                                              "clearance.resolution": 50.0}).clearance.size == 50


@pytest.mark.parametrize("text, value", [("1e-6", 1e-6), ("1E-6", 1e-6), ("1.0e-06", 1e-6),
                                         (".00001", 1e-5), ("2e-3", 2e-3)])
def test_floats_are_read_as_the_nodes_read_them(tmp_path, text, value):
    """`kmeans.tol: 1e-6` is a number to rcl (YAML 1.2); PyYAML (YAML 1.1) read a string
    and `replay` refused the file the nodes load: "expected a number, got '1e-6'"."""
    params = tmp_path / "p.yaml"
    params.write_text(f"/**:\n  ros__parameters:\n    kmeans:\n      tol: {text}\n")
    assert load_params_file(params, DemBuilderConfig, "dem_builder").kmeans.tol == value


def test_a_dumped_config_loads_back_whatever_its_floats(tmp_path):
    """Our own dump of 1e-05 (written `1e-05`) was refused by our own loader."""
    cfg = replace(DemBuilderConfig(), {"kmeans.tol": 1e-5, "rbfnn.goal": 2.5e-7})
    path = tmp_path / "dump.yaml"
    path.write_text(dump_ros_yaml(cfg, "/**"))
    assert load_params_file(path, DemBuilderConfig, "dem_builder") == cfg


def test_a_fleet_file_serves_a_vehicle_without_a_section_of_its_own(tmp_path):
    """`/**` for all and `/uav1/...`, `/uav2/...` overrides: a /uav3 node (and the offline
    commands, root namespace) take `/**` alone; a bare `obstacle_detector:` beside `/**`
    still refuses a namespaced node, which it was meant for but cannot reach."""
    from lidar_obstacles.config import ObstacleDetectorConfig, load_params_file

    fleet = tmp_path / "fleet.yaml"
    fleet.write_text("/**:\n  ros__parameters:\n    ground.cell: 1.5\n"
                     "/uav1/obstacle_detector:\n  ros__parameters:\n    ground.cell: 2.0\n"
                     "/uav2/obstacle_detector:\n  ros__parameters:\n    ground.cell: 3.0\n")
    for full_name in ("/uav3/obstacle_detector", None):
        cfg = load_params_file(fleet, ObstacleDetectorConfig, "obstacle_detector",
                               full_name=full_name)
        assert cfg.ground.cell == 1.5
    assert load_params_file(fleet, ObstacleDetectorConfig, "obstacle_detector",
                            full_name="/uav2/obstacle_detector").ground.cell == 3.0
    bare = tmp_path / "bare.yaml"
    bare.write_text("/**:\n  ros__parameters:\n    ground.cell: 1.5\n"
                    "obstacle_detector:\n  ros__parameters:\n    ground.cell: 2.0\n")
    with pytest.raises(ConfigError, match="section 'obstacle_detector' does not reach"):
        load_params_file(bare, ObstacleDetectorConfig, "obstacle_detector",
                         full_name="/uav1/obstacle_detector")
