"""Mirror the config schema into ROS 2 parameters: dotted names, descriptors with ranges,
validated runtime updates."""
from __future__ import annotations

from typing import Any, Callable

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from lidar_obstacles.config import NODE_CONFIGS, ParamInfo, params_of, replace, ros_own
from lidar_obstacles.errors import ConfigError


_TYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
          float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}


def descriptor(info: ParamInfo) -> ParameterDescriptor:
    """The ParameterDescriptor of one schema parameter (description, unit, range, choices)."""
    spec = info.spec
    text = spec.description + (f" [{spec.unit}]" if spec.unit else "")
    d = ParameterDescriptor(name=info.name, type=_TYPES[info.type], description=text,
                            read_only=spec.read_only)
    if spec.choices:
        d.additional_constraints = "one of: " + ", ".join(spec.choices)
    if info.type is float and spec.min is not None and spec.max is not None:
        d.floating_point_range = [FloatingPointRange(
            from_value=float(spec.min), to_value=float(spec.max), step=0.0)]
    elif info.type is int and spec.min is not None and spec.max is not None:
        d.integer_range = [IntegerRange(from_value=int(spec.min), to_value=int(spec.max), step=1)]
    return d


def _refusal(info: ParamInfo, given: Parameter | None, exc: Exception) -> str:
    """One line on an override rclpy refused: the name, the value and the rule it broke
    (rclpy's own text said the name three times and the value twice)."""
    value = f" = {given.value!r}" if given is not None else ""
    if "out of range" in str(exc) or "InvalidParameterValue" in type(exc).__name__:
        unit = f" {info.spec.unit}" if info.spec.unit and info.spec.unit != "1" else ""
        return f"parameter '{info.name}'{value}: not in its {info.spec.range_text()}{unit}"
    if "expecting type" in str(exc):
        kind = {float: "a number", int: "an integer", bool: "true or false",
                str: "a string"}.get(info.type, info.type.__name__)
        return f"parameter '{info.name}'{value}: not {kind}"
    return f"parameter '{info.name}'{value}: {str(exc).splitlines()[0]}"


def declare_config(node: Node, cls: type) -> Any:
    """Declare every parameter of `cls` on `node` and return the validated config.

    Raises ConfigError when an override (``-p``, ``--params-file``) is invalid.
    """
    values = {}
    overrides = node._parameter_overrides  # (private in rclpy: no public accessor in Jazzy)
    for info in params_of(cls):
        given = overrides.get(info.name)
        if info.type is float and given is not None and given.type_ == Parameter.Type.INTEGER:
            # `-p tiling.size:=40` or `size: 40` in a file: rcl reads an integer, which
            # rclpy refuses for a double. `replay` and `evaluate` read the same file as 40.0,
            # so the node does too.
            overrides[info.name] = Parameter(info.name, Parameter.Type.DOUBLE,
                                             float(given.value))
        try:
            param = node.declare_parameter(info.name, info.default, descriptor(info))
        except Exception as exc:  # rclpy raises its own types for type and range errors
            raise ConfigError(_refusal(info, overrides.get(info.name), exc)) from None
        values[info.name] = param.value
    # As `load_params_file`: a shared params file may carry another node's parameters,
    # but a name no node knows is a typo the user must hear of, not a silent default.
    all_known = {p.name for c in NODE_CONFIGS.values() for p in params_of(c)}
    unknown = sorted(n for n in overrides if n not in all_known and not ros_own(n))
    if unknown:
        executable = next((k for k, c in NODE_CONFIGS.items() if c is cls), node.get_name())
        raise ConfigError(f"unknown parameter '{unknown[0]}' (`{executable} --help` lists "
                          "the parameters)")
    # outputs take qos_overrides (node_base.create_output); the input's QoS follows its
    # publishers, and an override of it would do nothing
    inputs = sorted(n for n in overrides if n.startswith("qos_overrides.")
                    and ".subscription." in n)
    if inputs:
        raise ConfigError(f"parameter '{inputs[0]}': the input's QoS follows its publishers; "
                          "set input.reliability (auto, reliable or best_effort) instead")
    return replace(cls(), values)


def on_parameter_change(node: Node, get_cfg: Callable[[], Any],
                        set_cfg: Callable[[Any], None]) -> None:
    """Validate runtime updates against the schema; accepted ones take effect on the next
    message, rejected ones leave everything as it was and say why."""

    doubles = {p.name for p in params_of(type(get_cfg())) if p.type is float}

    def as_declared(params: list) -> list:
        # `ros2 param set NODE tiling.size 40` sends an integer, which rclpy refuses for a
        # double ("Wrong parameter type"); `-p tiling.size:=40` at start is 40.0
        # (declare_config), and so is it here.
        return [Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
                if p.name in doubles and p.type_ == Parameter.Type.INTEGER else p
                for p in params]

    def callback(params: list) -> SetParametersResult:
        ours = {p.name: p.value for p in params if not ros_own(p.name)}
        if not ours:
            return SetParametersResult(successful=True)  # use_sim_time: rclpy's own
        try:
            new_cfg = replace(get_cfg(), ours)
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        set_cfg(new_cfg)
        return SetParametersResult(successful=True)

    node.add_pre_set_parameters_callback(as_declared)
    node.add_on_set_parameters_callback(callback)
