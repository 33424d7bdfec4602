"""Scenario files: one YAML file describes one run.

A scenario holds the duration, the reference path, the initial state, the true plant
(model and parameter overrides, so the plant can differ from the controllers'
nominal model), the disturbances, the sensors, every controller's parameters and the
rates. Every key is optional: its default is the paper's Section V [1]_ as decoded in
docs/paper.md §6. Unknown keys, values of the wrong
type and values out of range raise :class:`~wip_control.core.config.ConfigError`
whose message starts with the dotted path of the key (``mpc.max_tilt: must be > 0``).

Schema (top level; ``scripts/simulate --list-parameters`` prints every leaf with its
unit, default and range)::

    name: str                     # free text
    description: str
    duration: float [s]
    seed: int                     # seeds sensor and disturbance noise
    rates: {plant_rate, control_rate}           [Hz]
    fall_threshold: float [rad]
    design: robust|paper          # paper: the paper's estimator, ARC, generator, reference
    initial_state: {pose_relative_to_reference, pose, x_v, theta, omega, v, theta_dot}
    plant: {model: paper|full|mujoco, wheel_friction: b, parameters: {<WipParameters field>:
            value}, contact: {friction, rolling_resistance},    # contact, terrain: mujoco only
            terrain: {slope_start, slope_grade, bump_position, bump_height, bump_length,
                      patch_start, patch_end, patch_friction}}
    controller_model: {parameters: {...}}       # nominal model used by the controllers
    reference: {kind: trifolium|circle|line|figure_eight|waypoints, ...}
    disturbances: {yaw: [..], longitudinal: [..], tilt: [..]}
    sensors, eso, position, trajectory_generator, arc, mpc, mixer: component configs

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016, Section V.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
from typing import Any, Mapping


from .arc import ArcConfig
from .config import ConfigError, _show, from_mapping, load_yaml_text, param, to_mapping
from .disturbances import DisturbanceConfig
from .eso import EsoConfig
from .ground import ContactConfig, TerrainConfig
from .mixer import MixerConfig
from .mpc import MpcConfig, PAPER_MPC_SETTINGS, resolves_faster
from .params import WipParameters
from .plant import ENGINE_MODELS, PlantConfig
from .position import PositionConfig
from .references import ReferenceConfig
from .sensors import SensorConfig
from .trajectory_generator import TrajectoryGeneratorConfig


@dataclasses.dataclass(frozen=True)
class RatesConfig:
    """Loop rates shared by the in-process runner and the node graph."""

    plant_rate: float = param(1000.0, 'Hz', 'RK4 integration rate of the plant',
                              minimum=10.0, maximum=100000.0)
    control_rate: float = param(200.0, 'Hz', 'rate of the ESO, trajectory generator, ARC '
                                'and mixer (the encoder/IMU rate)', minimum=1.0,
                                maximum=10000.0)

    def validate(self) -> None:
        ratio = self.plant_rate / self.control_rate
        if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
            raise ConfigError('plant_rate: must be an integer multiple of control_rate '
                              f'({self.plant_rate} / {self.control_rate} = {ratio})')

    @property
    def substeps(self) -> int:
        """Plant RK4 steps per control period."""
        return int(round(self.plant_rate / self.control_rate))


@dataclasses.dataclass(frozen=True)
class InitialStateConfig:
    """Initial state of the true plant; all velocities default to zero (Section V)."""

    pose_relative_to_reference: bool = param(
        True, '-', 'if true, pose is the body-frame error (x_e, y_e, phi_e) to the '
        'reference at t = 0; if false, pose is the absolute (x, y, phi) in the map frame')
    pose: tuple[float, float, float] = param(
        (0.5, 0.5, 0.1), 'm, m, rad', 'initial pose or initial body-frame error, see '
        'pose_relative_to_reference (paper: (x_e, y_e, phi_e)(0) = (0.5, 0.5, 0.1))',
        minimum=-1e4, maximum=1e4)
    x_v: float = param(0.1, 'm', 'initial distance rolled (paper: 0.1)',
                       minimum=-1e4, maximum=1e4)
    theta: float = param(0.05, 'rad', 'initial tilt, positive leaning forward (paper: 0.05)',
                         minimum=-1.2, maximum=1.2)
    omega: float = param(0.0, 'rad/s', 'initial yaw rate', minimum=-10.0, maximum=10.0)
    v: float = param(0.0, 'm/s', 'initial forward speed', minimum=-10.0, maximum=10.0)
    theta_dot: float = param(0.0, 'rad/s', 'initial tilt rate', minimum=-10.0, maximum=10.0)


@dataclasses.dataclass(frozen=True)
class PlantSection:
    """The true plant.

    Model, parameter overrides of :class:`WipParameters` and, for an engine model, the wheel-ground
    contact.
    """

    model: PlantConfig = dataclasses.field(default_factory=PlantConfig)
    parameters: WipParameters = dataclasses.field(default_factory=WipParameters)
    contact: ContactConfig = dataclasses.field(default_factory=ContactConfig)
    terrain: TerrainConfig = dataclasses.field(default_factory=TerrainConfig)


@dataclasses.dataclass(frozen=True)
class ControllerModelSection:
    """The controllers' nominal model (eq. (1)); defaults equal the true plant's."""

    parameters: WipParameters = dataclasses.field(default_factory=WipParameters)


@dataclasses.dataclass(frozen=True)
class Scenario:
    """Everything one run needs.

    Build with :func:`load_scenario` or :func:`scenario_from_mapping`.
    """

    name: str = 'paper_section_v'
    description: str = ('Section V of Yue, An, Li (2016): trifolium, sine yaw disturbance, '
                        'collision pulse at 30 s, 90 s')
    design: str = 'robust'
    duration: float = 90.0
    seed: int = 0
    fall_threshold: float = 0.5
    rates: RatesConfig = dataclasses.field(default_factory=RatesConfig)
    initial_state: InitialStateConfig = dataclasses.field(default_factory=InitialStateConfig)
    plant: PlantSection = dataclasses.field(default_factory=PlantSection)
    controller_model: ControllerModelSection = dataclasses.field(
        default_factory=ControllerModelSection)
    reference: ReferenceConfig = dataclasses.field(default_factory=ReferenceConfig)
    disturbances: DisturbanceConfig = dataclasses.field(default_factory=DisturbanceConfig)
    sensors: SensorConfig = dataclasses.field(default_factory=SensorConfig)
    eso: EsoConfig = dataclasses.field(default_factory=EsoConfig)
    position: PositionConfig = dataclasses.field(default_factory=PositionConfig)
    trajectory_generator: TrajectoryGeneratorConfig = dataclasses.field(
        default_factory=TrajectoryGeneratorConfig)
    arc: ArcConfig = dataclasses.field(default_factory=ArcConfig)
    mpc: MpcConfig = dataclasses.field(default_factory=MpcConfig)
    mixer: MixerConfig = dataclasses.field(default_factory=MixerConfig)

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
        ``mpc.fast_resolve_period`` when set, else ``mpc.sampling_period``
        (``DriveStage.is_tick``).
        """
        fast = self.mpc_fast_decimation
        return fast if fast is not None and fast < self.mpc_decimation else self.mpc_decimation

    @property
    def mpc_fast_decimation(self) -> int | None:
        """Control periods per ``mpc.fast_resolve_period``.

        None: off, 0 or not shorter than ``mpc.sampling_period``.
        """
        if not resolves_faster(self.mpc.sampling_period, self.mpc.fast_resolve_period):
            return None
        return int(round(self.mpc.fast_resolve_period * self.rates.control_rate))


MAX_DURATION_S = 36000.0
MAX_SEED = 2 ** 63 - 1
#: Most control periods one run may have: the in-process record preallocates about
#: 400 bytes per control period, so 1e6 of them (83 min at 200 Hz) stay below 0.5 GB.
MAX_CONTROL_SAMPLES = 1_000_000
#: A scenario file is a few kB; a larger one is not a scenario (and YAML parsing is slow).
MAX_SCENARIO_FILE_BYTES = 4 * 1024 * 1024

_TOP_LEVEL_SCALARS = {
    'name': (str, 'free-text name of the scenario'),
    'description': (str, 'free-text description'),
    'duration': (float, 'simulated time [s], in (0, 36000], at most '
                 '1e6 control periods (memory of the in-process record)'),
    'seed': (int, 'seed of every random generator (sensor and disturbance noise), '
             'in [0, 2**63 - 1]'),
    'fall_threshold': (float, '|theta| [rad] beyond which the vehicle counts as fallen and '
                       'the run stops, in (0, 1.5]'),
    'design': (str, "'robust' (default: what a real robot needs) or 'paper': the defaults "
               "of PAPER_DESIGN (the paper's ESOs, adaptation law (13), lambda1, lambda2 "
               'and a reference without time scaling); keys given explicitly still apply'),
}

#: Unit and admissible values of the top-level scalars, as checked in
#: :func:`scenario_from_mapping` (for the parameter reference).
TOP_LEVEL_RANGES = {
    'name': ('-', 'any'), 'description': ('-', 'any'),
    'design': ('-', 'one of: robust, paper'),
    'duration': ('s', f'(0, {MAX_DURATION_S:g}]'),
    'seed': ('1', '[0, 2**63 - 1]'),
    'fall_threshold': ('rad', '(0, 1.5]'),
}

#: Designs selectable with the top-level key ``design``.
DESIGNS = ('robust', 'paper')
#: What ``design: paper`` changes in the component defaults: the paper's Section V
#: estimator, adaptation law, heading gains and reference timing (docs/estimation.md).
PAPER_DESIGN: dict[str, dict[str, Any]] = {
    'eso': {'estimator': 'paper', 'speed_start': 'zero'},
    'arc': {'adaptation_dead_zone': 0.0, 'adaptation_normalisation': 0.0,
            'adaptation_leakage': 0.0, 'adapt_while_saturated': True},
    'trajectory_generator': {'heading_design': 'paper'},
    'reference': {'time_scaling': False},
    'mpc': dict(PAPER_MPC_SETTINGS),
}


def _parameters_from_mapping(mapping: Any, path: str) -> WipParameters:
    return from_mapping(WipParameters, mapping, path)


def _section(mapping: Mapping[str, Any], key: str) -> Any:
    value = mapping.get(key)
    return {} if value is None else value


def scenario_from_mapping(data: Mapping[str, Any] | None) -> Scenario:
    """Validate a parsed YAML mapping and build a :class:`Scenario`."""
    data = {} if data is None else data
    if not isinstance(data, Mapping):
        raise ConfigError('scenario: expected a mapping at the top level, '
                          f'got {type(data).__name__}')
    sections = {'rates', 'initial_state', 'plant', 'controller_model', 'reference',
                'disturbances', 'sensors', 'eso', 'position', 'trajectory_generator', 'arc',
                'mpc', 'mixer'}
    known = set(_TOP_LEVEL_SCALARS) | sections
    for key in data:
        if key not in known:
            raise ConfigError(f'{key}: unknown key; expected one of {sorted(known)}')
    kwargs: dict[str, Any] = {}
    for key, (kind, _) in _TOP_LEVEL_SCALARS.items():
        if key not in data:
            continue
        value = data[key]
        if kind is str and not isinstance(value, str):
            raise ConfigError(f'{key}: expected a string, got {value!r}')
        if kind in (int, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or (isinstance(value, float) and not math.isfinite(value)):
                raise ConfigError(f'{key}: expected a finite number, got {_show(value)}')
            if kind is int and isinstance(value, float) and not value.is_integer():
                raise ConfigError(f'{key}: expected an integer, got {_show(value)}')
            if kind is float and isinstance(value, int) and abs(value) > 1e300:
                raise ConfigError(f'{key}: out of range, got {_show(value)}')
            value = kind(value)
        kwargs[key] = value
    if 'duration' in kwargs and not 0.0 < kwargs['duration'] <= MAX_DURATION_S:
        raise ConfigError(f'duration: must be in (0, {MAX_DURATION_S:g}] s, got '
                          f'{_show(kwargs["duration"])}')
    if 'fall_threshold' in kwargs and not 0.0 < kwargs['fall_threshold'] <= 1.5:
        raise ConfigError('fall_threshold: must be in (0, 1.5] rad, got '
                          f'{_show(kwargs["fall_threshold"])}')
    if 'seed' in kwargs and not 0 <= kwargs['seed'] <= MAX_SEED:
        raise ConfigError(f'seed: must be in [0, 2**63 - 1], got {_show(kwargs["seed"])}')
    design = kwargs.get('design', 'robust')
    if design not in DESIGNS:
        raise ConfigError(f'design: {design!r} is not one of {list(DESIGNS)}')
    if design == 'paper':
        data = dict(data)
        for section, defaults in PAPER_DESIGN.items():
            given = _section(data, section)
            if not isinstance(given, Mapping):
                raise ConfigError(f'{section}: expected a mapping, got {given!r}')
            data[section] = {**defaults, **given}

    plant = _section(data, 'plant')
    if not isinstance(plant, Mapping):
        raise ConfigError(f'plant: expected a mapping, got {plant!r}')
    config_keys = tuple(field.name for field in dataclasses.fields(PlantConfig))
    for key in plant:
        if key not in (*config_keys, 'parameters', 'contact', 'terrain'):
            raise ConfigError(f'plant.{key}: unknown key; expected one of '
                              f'{sorted([*config_keys, "parameters", "contact", "terrain"])}')
    model = from_mapping(PlantConfig, {key: plant[key] for key in config_keys if key in plant},
                         'plant')
    for key in ('contact', 'terrain'):
        if key in plant and model.model not in ENGINE_MODELS:
            # The equation plants roll without slip on flat ground: a friction or a
            # terrain would silently do nothing.
            raise ConfigError(f'plant.{key}: only used by the plant models '
                              f'{sorted(ENGINE_MODELS)}, not by {model.model!r}')
    kwargs['plant'] = PlantSection(
        model=model,
        parameters=_parameters_from_mapping(plant.get('parameters'), 'plant.parameters'),
        contact=from_mapping(ContactConfig, plant.get('contact'), 'plant.contact'),
        terrain=from_mapping(TerrainConfig, plant.get('terrain'), 'plant.terrain'))
    nominal = _section(data, 'controller_model')
    if not isinstance(nominal, Mapping):
        raise ConfigError(f'controller_model: expected a mapping, got {nominal!r}')
    for key in nominal:
        if key != 'parameters':
            raise ConfigError(f"controller_model.{key}: unknown key; expected ['parameters']")
    kwargs['controller_model'] = ControllerModelSection(
        parameters=_parameters_from_mapping(nominal.get('parameters'),
                                            'controller_model.parameters'))
    kwargs['disturbances'] = DisturbanceConfig.from_mapping(
        _section(data, 'disturbances'), 'disturbances')
    for key, cls in (('rates', RatesConfig), ('initial_state', InitialStateConfig),
                     ('reference', ReferenceConfig), ('sensors', SensorConfig),
                     ('eso', EsoConfig), ('position', PositionConfig),
                     ('trajectory_generator', TrajectoryGeneratorConfig), ('arc', ArcConfig),
                     ('mpc', MpcConfig), ('mixer', MixerConfig)):
        kwargs[key] = from_mapping(cls, _section(data, key), key)
    scenario = Scenario(**kwargs)
    _check_consistency(scenario)
    return scenario


def with_duration(scenario: Scenario, duration: float) -> Scenario:
    """``scenario`` with another duration [s], checked as a scenario file's would be.

    ``scenario`` with another duration [s], checked as a scenario file's would be
    (range, at least one control tick, the most control periods a run may have);
    ConfigError otherwise.
    """
    if not 0.0 < duration <= MAX_DURATION_S:
        raise ConfigError(f'duration: must be in (0, {MAX_DURATION_S:g}] s, got '
                          f'{_show(duration)}')
    scenario = dataclasses.replace(scenario, duration=float(duration))
    _check_consistency(scenario)
    return scenario


def _check_consistency(scenario: Scenario) -> None:
    """Cross-section checks: rates that must divide each other, run size, initial tilt."""
    samples = scenario.duration * scenario.rates.control_rate
    if round(samples) < 1:
        raise ConfigError(f'duration: {scenario.duration:g} s is less than one control '
                          f'period ({scenario.control_period:g} s at rates.control_rate '
                          f'{scenario.rates.control_rate:g} Hz): the run would have no '
                          'control tick')
    if samples > MAX_CONTROL_SAMPLES:
        raise ConfigError(f'duration: {scenario.duration:g} s at rates.control_rate '
                          f'{scenario.rates.control_rate:g} Hz is {samples:.3g} control '
                          f'periods, more than the {MAX_CONTROL_SAMPLES:.0e} one run may have '
                          '(memory); shorten the run or lower the rate')
    if abs(scenario.initial_state.theta) >= scenario.fall_threshold:
        raise ConfigError(f'initial_state.theta: |{scenario.initial_state.theta:g}| rad is at '
                          f'or beyond fall_threshold {scenario.fall_threshold:g} rad: the run '
                          'would count as a fall before it starts')
    ratio = scenario.mpc.sampling_period * scenario.rates.control_rate
    if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
        raise ConfigError('mpc.sampling_period: must be an integer multiple of the control '
                          f'period 1/rates.control_rate = {scenario.control_period} s')
    ratio = scenario.mpc.fast_resolve_period * scenario.rates.control_rate
    if (resolves_faster(scenario.mpc.sampling_period, scenario.mpc.fast_resolve_period)
            and (abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1)):
        raise ConfigError('mpc.fast_resolve_period: must be 0 or an integer multiple of '
                          f'the control period 1/rates.control_rate = '
                          f'{scenario.control_period} s')
    ref, generator = scenario.reference, scenario.trajectory_generator
    if ref.time_scaling:
        if ref.path_max_speed > generator.max_speed:
            raise ConfigError(f'reference.path_max_speed: must not exceed '
                              f'trajectory_generator.max_speed = {generator.max_speed} m/s '
                              f'(the generator saturates there), got {ref.path_max_speed}')
        if ref.path_max_yaw_rate > generator.max_yaw_rate:
            raise ConfigError(f'reference.path_max_yaw_rate: must not exceed '
                              f'trajectory_generator.max_yaw_rate = {generator.max_yaw_rate} '
                              f'rad/s, got {ref.path_max_yaw_rate}')
    eso_period = scenario.eso.sample_period
    if abs(eso_period - scenario.control_period) > 1e-12:
        raise ConfigError(f'eso.sample_period: must equal 1/rates.control_rate = '
                          f'{scenario.control_period} s (the ESO runs at the sensor rate), '
                          f'got {eso_period}')


def paper_scenario(overrides: Mapping[str, Any] | None = None) -> Scenario:
    """Section V with the paper's design (``design: paper``), plus ``overrides``."""
    return scenario_from_mapping({**(overrides or {}), 'design': 'paper'})


def load_scenario(path: str | pathlib.Path | None = None) -> Scenario:
    """Load and validate a scenario file; ``None`` gives the paper's Section V.

    A file without a ``name`` is named after itself (its stem), not after the default.
    """
    if path is None:
        return Scenario()
    path = pathlib.Path(path)
    data = read_scenario_file(path)
    if isinstance(data, Mapping) and 'name' not in data:
        data = {**data, 'name': path.stem}
    elif data is None:
        data = {'name': path.stem}
    try:
        return scenario_from_mapping(data)
    except ConfigError as err:
        raise ConfigError(f'{path}: {err}') from err


def read_scenario_file(path: str | pathlib.Path) -> Any:
    """Return the parsed content of a scenario file, not yet validated.

    The parsed content of a scenario file, not yet validated (strict YAML, size-checked);
    ConfigError naming the file on any problem.
    """
    path = pathlib.Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise ConfigError(f'scenario file {str(path)!r}: {err.strerror}') from err
    if len(raw) > MAX_SCENARIO_FILE_BYTES:
        raise ConfigError(f'scenario file {str(path)!r}: {len(raw)} bytes, more than the '
                          f'{MAX_SCENARIO_FILE_BYTES} a scenario file may have')
    return load_yaml_text(raw, f'scenario file {str(path)!r}')


def scenario_to_mapping(scenario: Scenario) -> dict[str, Any]:
    """Plain-data form of a scenario (round-trips through :func:`scenario_from_mapping`)."""
    out = to_mapping(scenario)
    out['plant'] = {**dataclasses.asdict(scenario.plant.model),
                    'parameters': dataclasses.asdict(scenario.plant.parameters)}
    if scenario.plant.model.model in ENGINE_MODELS:
        out['plant']['contact'] = dataclasses.asdict(scenario.plant.contact)
        out['plant']['terrain'] = dataclasses.asdict(scenario.plant.terrain)
    out['controller_model'] = {
        'parameters': dataclasses.asdict(scenario.controller_model.parameters)}
    out['disturbances'] = scenario.disturbances.to_mapping()
    return out
