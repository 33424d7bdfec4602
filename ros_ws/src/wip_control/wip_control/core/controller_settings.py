"""The controllers' settings: the sections of a scenario file that a robot uses.

A scenario file (``wip_sim.core.scenario``) describes one simulated run; most of it is the
controllers' configuration, and that part is all hardware mode and ``check_base`` read from
it. :class:`ControllerParams` holds it: the design, the loop rates, the nominal model
(eq. (1) of [1]_), the reference, the sensors as the estimators read them, and the ESO,
position, trajectory generator, ARC, MPC and mixer sections. Every key is optional: its
default is the paper's Section V as decoded in docs/paper.md §6. Unknown keys, values of the
wrong type and values out of range raise :class:`~wip_runtime.config.ParamError`
whose message starts with the dotted path of the key (``mpc.max_tilt: must be > 0``).

:func:`load_controller_settings` reads a whole scenario file and skips the keys that describe
only the simulation (:data:`SIMULATION_KEYS`); the simulator validates those.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016, Section V.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any, Callable, Mapping

from .arc import ArcParams
from wip_runtime.config import (check_number, from_mapping, load_yaml_text, param, ParamError,
                                to_mapping)
from .eso import EsoParams
from .mixer import MixerParams
from .mpc_config import (drive_tick_decimation, MpcParams, PAPER_MPC_SETTINGS,
                         resolves_faster)
from wip_description.params import ModelParams
from .position import PositionParams
from .references import ReferenceParams
from wip_description.sensors import SensorParams
from .trajectory_generator import TrajectoryGeneratorParams


@dataclasses.dataclass(frozen=True)
class RatesParams:
    """Loop rates shared by the in-process runner and the node graph."""

    plant_rate: float = param(1000.0, 'Hz', 'RK4 integration rate of the plant',
                              minimum=10.0, maximum=100000.0)
    control_rate: float = param(200.0, 'Hz', 'rate of the ESO, trajectory generator, ARC '
                                'and mixer (the encoder/IMU rate)', minimum=1.0,
                                maximum=10000.0)

    def validate(self) -> None:
        ratio = self.plant_rate / self.control_rate
        if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
            raise ParamError('plant_rate: must be an integer multiple of control_rate '
                              f'({self.plant_rate} / {self.control_rate} = {ratio})')

    @property
    def substeps(self) -> int:
        """Plant RK4 steps per control period."""
        return int(round(self.plant_rate / self.control_rate))


@dataclasses.dataclass(frozen=True)
class ControllerModelParams:
    """The controllers' nominal model (eq. (1)); defaults equal the true plant's."""

    parameters: ModelParams = dataclasses.field(default_factory=ModelParams)


@dataclasses.dataclass(frozen=True)
class ControllerParams:
    """What the controllers of one run need.

    Build with :func:`controller_settings_from_mapping` or :func:`load_controller_settings`.
    """

    name: str = 'paper_section_v'
    description: str = ('Section V of Yue, An, Li (2016): trifolium, sine yaw disturbance, '
                        'collision pulse at 30 s, 90 s')
    design: str = 'robust'
    rates: RatesParams = dataclasses.field(default_factory=RatesParams)
    controller_model: ControllerModelParams = dataclasses.field(
        default_factory=ControllerModelParams)
    reference: ReferenceParams = dataclasses.field(default_factory=ReferenceParams)
    sensors: SensorParams = dataclasses.field(default_factory=SensorParams)
    eso: EsoParams = dataclasses.field(default_factory=EsoParams)
    position: PositionParams = dataclasses.field(default_factory=PositionParams)
    trajectory_generator: TrajectoryGeneratorParams = dataclasses.field(
        default_factory=TrajectoryGeneratorParams)
    arc: ArcParams = dataclasses.field(default_factory=ArcParams)
    mpc: MpcParams = dataclasses.field(default_factory=MpcParams)
    mixer: MixerParams = dataclasses.field(default_factory=MixerParams)

    @property
    def control_period(self) -> float:
        """Period of the ESO/generator/ARC/mixer loop [s]."""
        return 1.0 / self.rates.control_rate

    @property
    def mpc_decimation(self) -> int:
        """Control periods per MPC sampling period."""
        return int(round(self.mpc.sampling_period * self.rates.control_rate))

    @property
    def drive_decimation(self) -> int:
        """Control periods between the drive stage's ticks.

        Where it takes its inputs and (lockstep) publishes a drive torque:
        ``mpc.fast_resolve_period`` when set (every control period with ``mpc.push_trigger``),
        else ``mpc.sampling_period`` (``DriveControllerStage.is_tick``).
        """
        return drive_tick_decimation(self.mpc_decimation, self.mpc_fast_decimation,
                                     self.mpc.push_trigger)

    @property
    def mpc_fast_decimation(self) -> int | None:
        """Control periods per ``mpc.fast_resolve_period``.

        None: off, 0 or not shorter than ``mpc.sampling_period``.
        """
        if not resolves_faster(self.mpc.sampling_period, self.mpc.fast_resolve_period):
            return None
        return int(round(self.mpc.fast_resolve_period * self.rates.control_rate))


#: A scenario file is a few kB; a larger one is not a scenario (and YAML parsing is slow).
MAX_SCENARIO_FILE_BYTES = 4 * 1024 * 1024

#: The top-level scalars of the controllers: type and description (for the parameter
#: reference).
CONTROLLER_SCALARS = {
    'name': (str, 'free-text name of the scenario'),
    'description': (str, 'free-text description'),
    'design': (str, "'robust' or 'paper': the paper's ESOs (4), (8), adaptation law (13), "
               'lambda1-3 of (9), MPC, no time scaling; explicit keys still apply '
               '(docs/decisions/reference-parameters.md)'),
}
#: Unit and admissible values of those scalars.
CONTROLLER_SCALAR_RANGES = {
    'name': ('-', 'any'), 'description': ('-', 'any'),
    'design': ('-', 'one of: robust, paper'),
}
#: The sections of the controllers and their dataclasses (``controller_model`` apart).
CONTROLLER_SECTIONS: dict[str, type] = {
    'rates': RatesParams, 'reference': ReferenceParams, 'sensors': SensorParams,
    'eso': EsoParams, 'position': PositionParams,
    'trajectory_generator': TrajectoryGeneratorParams, 'arc': ArcParams, 'mpc': MpcParams,
    'mixer': MixerParams}
#: The keys of a scenario file that describe only the simulation (the true plant, its
#: initial state, disturbances and the run's length): the simulator's to check.
SIMULATION_KEYS = ('duration', 'seed', 'fall_threshold', 'initial_state', 'plant',
                   'disturbances')

#: Designs selectable with the top-level key ``design``.
DESIGNS = ('robust', 'paper')
#: What ``design: paper`` changes in the component defaults: the paper's Section V
#: estimator, adaptation law, heading gains and reference timing (docs/estimation.md).
PAPER_DESIGN: dict[str, dict[str, Any]] = {
    'eso': {'estimator': 'paper', 'speed_start': 'zero'},
    'arc': {'adaptation_dead_zone': 0.0, 'adaptation_normalisation': 0.0,
            'adaptation_leakage': 0.0, 'adapt_while_saturated': True},
    'trajectory_generator': {'heading_design': 'paper', 'lambda3': 1.0},
    'reference': {'time_scaling': False},
    'mpc': dict(PAPER_MPC_SETTINGS),
}


def section(mapping: Mapping[str, Any], key: str) -> Any:
    """Return ``mapping[key]``, an empty mapping when the key is absent or null."""
    value = mapping.get(key)
    return {} if value is None else value


def checked_scalar(key: str, value: Any, kind: type) -> Any:
    """``value`` of the top-level scalar ``key`` as ``kind``; ParamError if it is not one."""
    if kind is str and not isinstance(value, str):
        raise ParamError(f'{key}: expected a string, got {value!r}')
    if kind in (int, float):
        return check_number(key, value, {}, want_int=kind is int)
    return value


def controller_fields(data: Mapping[str, Any] | None,
                      other_keys: frozenset[str] | set[str] = frozenset()) -> dict[str, Any]:
    """Return the :class:`ControllerParams` fields of a parsed scenario mapping, validated.

    ``other_keys`` are the further top-level keys the caller reads itself; any other unknown
    key is an error.
    """
    data = {} if data is None else data
    if not isinstance(data, Mapping):
        raise ParamError('scenario: expected a mapping at the top level, '
                          f'got {type(data).__name__}')
    known = set(CONTROLLER_SCALARS) | set(CONTROLLER_SECTIONS) | {'controller_model'} \
        | set(other_keys)
    for key in data:
        if key not in known:
            raise ParamError(f'{key}: unknown key; expected one of {sorted(known)}')
    fields = {key: checked_scalar(key, data[key], kind)
              for key, (kind, _) in CONTROLLER_SCALARS.items() if key in data}
    design = fields.get('design', 'robust')
    if design not in DESIGNS:
        raise ParamError(f'design: {design!r} is not one of {list(DESIGNS)}')
    if design == 'paper':
        data = dict(data)
        for name, defaults in PAPER_DESIGN.items():
            given = section(data, name)
            if not isinstance(given, Mapping):
                raise ParamError(f'{name}: expected a mapping, got {given!r}')
            data[name] = {**defaults, **given}
    nominal = section(data, 'controller_model')
    if not isinstance(nominal, Mapping):
        raise ParamError(f'controller_model: expected a mapping, got {nominal!r}')
    for key in nominal:
        if key != 'parameters':
            raise ParamError(f"controller_model.{key}: unknown key; expected ['parameters']")
    fields['controller_model'] = ControllerModelParams(parameters=from_mapping(
        ModelParams, nominal.get('parameters'), 'controller_model.parameters'))
    for key, cls in CONTROLLER_SECTIONS.items():
        fields[key] = from_mapping(cls, section(data, key), key)
    return fields


def check_controller_consistency(settings: ControllerParams) -> None:
    """Cross-section checks: periods that must divide each other, reference within limits."""
    period = settings.control_period
    ratio = settings.mpc.sampling_period * settings.rates.control_rate
    if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
        raise ParamError('mpc.sampling_period: must be an integer multiple of the control '
                          f'period 1/rates.control_rate = {period} s')
    ratio = settings.mpc.fast_resolve_period * settings.rates.control_rate
    if (resolves_faster(settings.mpc.sampling_period, settings.mpc.fast_resolve_period)
            and (abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1)):
        raise ParamError('mpc.fast_resolve_period: must be 0 or an integer multiple of '
                          f'the control period 1/rates.control_rate = {period} s')
    ref, generator = settings.reference, settings.trajectory_generator
    if ref.time_scaling:
        if ref.path_max_speed > generator.max_speed:
            raise ParamError(f'reference.path_max_speed: must not exceed '
                              f'trajectory_generator.max_speed = {generator.max_speed} m/s '
                              f'(the generator saturates there), got {ref.path_max_speed}')
        if ref.path_max_yaw_rate > generator.max_yaw_rate:
            raise ParamError(f'reference.path_max_yaw_rate: must not exceed '
                              f'trajectory_generator.max_yaw_rate = {generator.max_yaw_rate} '
                              f'rad/s, got {ref.path_max_yaw_rate}')
    eso_period = settings.eso.sample_period
    if abs(eso_period - period) > 1e-12:
        raise ParamError(f'eso.sample_period: must equal 1/rates.control_rate = '
                          f'{period} s (the ESO runs at the sensor rate), got {eso_period}')


def controller_settings_from_mapping(data: Mapping[str, Any] | None) -> ControllerParams:
    """Validate the controller part of a parsed scenario mapping; skip its simulation keys."""
    settings = ControllerParams(**controller_fields(data, set(SIMULATION_KEYS)))
    check_controller_consistency(settings)
    return settings


def read_scenario_file(path: str | pathlib.Path) -> Any:
    """Return the parsed content of a scenario file, not yet validated.

    Strict YAML, size-checked; ParamError naming the file on any problem.
    """
    path = pathlib.Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise ParamError(f'scenario file {str(path)!r}: {err.strerror}') from err
    if len(raw) > MAX_SCENARIO_FILE_BYTES:
        raise ParamError(f'scenario file {str(path)!r}: {len(raw)} bytes, more than the '
                          f'{MAX_SCENARIO_FILE_BYTES} a scenario file may have')
    return load_yaml_text(raw, f'scenario file {str(path)!r}')


def load_scenario_file(path: str | pathlib.Path, from_mapping: Callable[[Any], Any]) -> Any:
    """Read a scenario file and build it with ``from_mapping``; errors name the file.

    A file without a ``name`` is named after itself (its stem), not after the default.
    """
    path = pathlib.Path(path)
    data = read_scenario_file(path)
    if isinstance(data, Mapping) and 'name' not in data:
        data = {**data, 'name': path.stem}
    elif data is None:
        data = {'name': path.stem}
    try:
        return from_mapping(data)
    except ParamError as err:
        raise ParamError(f'{path}: {err}') from err


def load_controller_settings(path: str | pathlib.Path | None = None) -> ControllerParams:
    """Load the controller settings of a scenario file; ``None``: the paper's Section V."""
    if path is None:
        return ControllerParams()
    return load_scenario_file(path, controller_settings_from_mapping)


def controller_settings_to_mapping(settings: ControllerParams) -> dict[str, Any]:
    """Plain-data form (round-trips through :func:`controller_settings_from_mapping`)."""
    out = to_mapping(settings)
    out['controller_model'] = {
        'parameters': dataclasses.asdict(settings.controller_model.parameters)}
    return out
