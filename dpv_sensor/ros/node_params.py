"""The node's ROS parameters from the settings table (dpv_sensor.params): declared with their descriptions, types
and ranges, validated at start, and the ones in ``params.RUNTIME`` changeable while the node runs (`ros2 param set`),
checked by the same table with its messages; every other parameter is read-only (it needs a restart). The node reads
them as one typed :class:`NodeSettings`, rebuilt on every accepted change."""
from __future__ import annotations

from dataclasses import dataclass

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.parameter import Parameter

from dpv_sensor import params as P
from dpv_sensor.stream.estimator import EstimatorConfig


@dataclass(frozen=True)
class NodeSettings:
    """The node's parameters, typed, each setting in one place: ``node`` (``params.NodeConfig``: topics, QoS,
    encodings, the odometry buffer, camera intrinsics, diagnostics) and ``estimator`` (``EstimatorConfig``: the
    estimator and its pose source, the library settings at their defaults)."""
    node: P.NodeConfig
    estimator: EstimatorConfig

    @classmethod
    def from_params(cls, values: dict) -> 'NodeSettings':
        """From the validated parameter dict (:func:`declare_parameters`)."""
        return cls(node=P.NodeConfig.from_params(values), estimator=EstimatorConfig.from_params(values))


def descriptor(spec: P.ParamSpec) -> ParameterDescriptor:
    """The descriptor of one setting. A runtime setting carries its range as text only, so that a value out of
    range reaches the node's own check and is refused with the table's message."""
    runtime = spec.name in P.RUNTIME
    desc = ParameterDescriptor(name=spec.name, description=spec.description, read_only=not runtime)
    if spec.choices:
        desc.additional_constraints = 'one of: ' + ', '.join(map(str, spec.choices))
    if runtime:
        if spec.min_value is not None or spec.max_value is not None:
            desc.additional_constraints = f'range [{spec.min_value}, {spec.max_value}]'
        return desc
    if spec.kind is float and (spec.min_value is not None or spec.max_value is not None):
        desc.floating_point_range = [FloatingPointRange(
            from_value=float(spec.min_value if spec.min_value is not None else -1e300),
            to_value=float(spec.max_value if spec.max_value is not None else 1e300), step=0.0)]
    if spec.kind is int and (spec.min_value is not None or spec.max_value is not None):
        desc.integer_range = [IntegerRange(
            from_value=int(spec.min_value if spec.min_value is not None else -(2 ** 62)),
            to_value=int(spec.max_value if spec.max_value is not None else 2 ** 62), step=1)]
    return desc


def declare_parameters(node) -> dict:
    """Declare every parameter of params.SPECS on `node` and return their validated values.

    A value rclpy refuses (type or range of the descriptor) is checked again with the table, so the node gives
    the same message as the estimator and the tools."""
    for spec in P.SPECS:
        try:
            node.declare_parameter(spec.name, spec.default, descriptor(spec))
        except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
            overrides = getattr(node, '_parameter_overrides', {})
            override = overrides.get(spec.name)
            if override is None:
                raise P.ParameterError(f"parameter '{spec.name}' rejected: {exc}") from None
            value = P.check_value(spec, override.value)     # raises the table's message
            if isinstance(override.value, bool) and isinstance(value, str):
                # `-p pose_refinement:=off` arrives as False: the table reads it as the choice 'off'
                overrides[spec.name] = Parameter(spec.name, Parameter.Type.STRING, value)
                node.declare_parameter(spec.name, spec.default, descriptor(spec))
                continue
            raise P.ParameterError(f"parameter '{spec.name}' rejected: {exc}") from None
    values = {spec.name: node.get_parameter(spec.name).value for spec in P.SPECS}
    return P.validate(values)


class RuntimeParameters:
    """The set-parameters callback: `apply(new_values, changes)` is called with the whole checked dict and the
    changed settings when a change is accepted; a refused change is logged with the table's message."""

    def __init__(self, node, values: dict, apply):
        self._node = node
        self._values = values
        self._apply = apply
        node.add_on_set_parameters_callback(self._on_set)

    def _on_set(self, params) -> SetParametersResult:
        changes = {p.name: p.value for p in params}
        try:
            new = P.check_changes(self._values, changes)
        except P.ParameterError as exc:
            self._node.get_logger().warning(f'parameter change refused: {exc}')
            return SetParametersResult(successful=False, reason=str(exc))
        self._values = new
        self._apply(new, {k: new[k] for k in changes})
        self._node.get_logger().info('parameters changed: ' + ', '.join(f'{k}={new[k]!r}' for k in changes))
        return SetParametersResult(successful=True)
