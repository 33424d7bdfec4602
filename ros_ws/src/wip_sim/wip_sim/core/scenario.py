"""Scenario files: one YAML file describes one run.

A scenario holds the controllers' settings
(:class:`~wip_control.core.controller_settings.ControllerParams`, what a robot reads from
the same file) and the simulation: the duration, the seed, the initial state, the true plant
(model and parameter overrides, so the plant can differ from the controllers' nominal
model) and the disturbances. Every key is optional: its default is the paper's Section V
[1]_ as decoded in docs/paper.md §6. Unknown keys, values of the wrong type and values out
of range raise :class:`~wip_runtime.config.ParamError` whose message starts with the
dotted path of the key (``mpc.max_tilt: must be > 0``).

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
    plant: {model: paper|full|mujoco, wheel_friction: b, parameters: {<ModelParams field>:
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
import pathlib
from typing import Any, Mapping

from wip_runtime.config import ParamError, _show, from_mapping, param
from wip_control.core.controller_settings import (check_controller_consistency,
                                                  checked_scalar, controller_fields,
                                                  CONTROLLER_SCALAR_RANGES, CONTROLLER_SCALARS,
                                                  controller_settings_to_mapping,
                                                  ControllerParams, load_scenario_file,
                                                  section)
from wip_description.params import ModelParams

from .disturbances import DisturbanceParams
from .ground import ContactParams, TerrainParams
from .plant import ENGINE_MODELS, PlantParams


@dataclasses.dataclass(frozen=True)
class InitialStateParams:
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

    Model, parameter overrides of :class:`ModelParams` and, for an engine model, the wheel-ground
    contact.
    """

    model: PlantParams = dataclasses.field(default_factory=PlantParams)
    parameters: ModelParams = dataclasses.field(default_factory=ModelParams)
    contact: ContactParams = dataclasses.field(default_factory=ContactParams)
    terrain: TerrainParams = dataclasses.field(default_factory=TerrainParams)


@dataclasses.dataclass(frozen=True)
class Scenario(ControllerParams):
    """Everything one simulated run needs: the controllers' settings and the simulation.

    Build with :func:`load_scenario` or :func:`scenario_from_mapping`.
    """

    duration: float = 90.0
    seed: int = 0
    fall_threshold: float = 0.5
    initial_state: InitialStateParams = dataclasses.field(default_factory=InitialStateParams)
    plant: PlantSection = dataclasses.field(default_factory=PlantSection)
    disturbances: DisturbanceParams = dataclasses.field(default_factory=DisturbanceParams)


MAX_DURATION_S = 36000.0
MAX_SEED = 2 ** 63 - 1
#: Most control periods one run may have: the in-process record preallocates about
#: 400 bytes per control period, so 1e6 of them (83 min at 200 Hz) stay below 0.5 GB.
MAX_CONTROL_SAMPLES = 1_000_000

#: The simulation's top-level scalars: type and description (the controllers' are in
#: CONTROLLER_SCALARS).
SIMULATION_SCALARS = {
    'duration': (float, 'simulated time [s], in (0, 36000], at most '
                 '1e6 control periods (memory of the in-process record)'),
    'seed': (int, 'seed of every random generator (sensor and disturbance noise), '
             'in [0, 2**63 - 1]'),
    'fall_threshold': (float, '|theta| [rad] beyond which the vehicle counts as fallen and '
                       'the run stops, in (0, 1.5]'),
}
#: Every top-level scalar of a scenario file, for the parameter reference.
TOP_LEVEL_SCALARS = {**CONTROLLER_SCALARS, **SIMULATION_SCALARS}
#: Unit and admissible values of the top-level scalars, as checked in
#: :func:`scenario_from_mapping` (for the parameter reference).
TOP_LEVEL_RANGES = {
    **CONTROLLER_SCALAR_RANGES,
    'duration': ('s', f'(0, {MAX_DURATION_S:g}]'),
    'seed': ('1', '[0, 2**63 - 1]'),
    'fall_threshold': ('rad', '(0, 1.5]'),
}
_SIMULATION_SECTIONS = ('initial_state', 'plant', 'disturbances')


def scenario_from_mapping(data: Mapping[str, Any] | None) -> Scenario:
    """Validate a parsed YAML mapping and build a :class:`Scenario`."""
    data = {} if data is None else data
    fields = controller_fields(data, {*SIMULATION_SCALARS, *_SIMULATION_SECTIONS})
    fields.update({key: checked_scalar(key, data[key], kind)
                   for key, (kind, _) in SIMULATION_SCALARS.items() if key in data})
    if 'duration' in fields and not 0.0 < fields['duration'] <= MAX_DURATION_S:
        raise ParamError(f'duration: must be in (0, {MAX_DURATION_S:g}] s, got '
                          f'{_show(fields["duration"])}')
    if 'fall_threshold' in fields and not 0.0 < fields['fall_threshold'] <= 1.5:
        raise ParamError('fall_threshold: must be in (0, 1.5] rad, got '
                          f'{_show(fields["fall_threshold"])}')
    if 'seed' in fields and not 0 <= fields['seed'] <= MAX_SEED:
        raise ParamError(f'seed: must be in [0, 2**63 - 1], got {_show(fields["seed"])}')
    fields['plant'] = _plant_section(section(data, 'plant'))
    fields['disturbances'] = DisturbanceParams.from_mapping(
        section(data, 'disturbances'), 'disturbances')
    fields['initial_state'] = from_mapping(InitialStateParams, section(data, 'initial_state'),
                                           'initial_state')
    scenario = Scenario(**fields)
    _check_consistency(scenario)
    return scenario


def _plant_section(plant: Any) -> PlantSection:
    if not isinstance(plant, Mapping):
        raise ParamError(f'plant: expected a mapping, got {plant!r}')
    config_keys = tuple(field.name for field in dataclasses.fields(PlantParams))
    for key in plant:
        if key not in (*config_keys, 'parameters', 'contact', 'terrain'):
            raise ParamError(f'plant.{key}: unknown key; expected one of '
                              f'{sorted([*config_keys, "parameters", "contact", "terrain"])}')
    model = from_mapping(PlantParams, {key: plant[key] for key in config_keys if key in plant},
                         'plant')
    for key in ('contact', 'terrain'):
        if key in plant and model.model not in ENGINE_MODELS:
            # The equation plants roll without slip on flat ground: a friction or a
            # terrain would silently do nothing.
            raise ParamError(f'plant.{key}: only used by the plant models '
                              f'{sorted(ENGINE_MODELS)}, not by {model.model!r}')
    return PlantSection(
        model=model,
        parameters=from_mapping(ModelParams, plant.get('parameters'), 'plant.parameters'),
        contact=from_mapping(ContactParams, plant.get('contact'), 'plant.contact'),
        terrain=from_mapping(TerrainParams, plant.get('terrain'), 'plant.terrain'))


def with_duration(scenario: Scenario, duration: float) -> Scenario:
    """``scenario`` with another duration [s], checked as a scenario file's would be.

    Range, at least one control tick, the most control periods a run may have; ParamError
    otherwise.
    """
    if not 0.0 < duration <= MAX_DURATION_S:
        raise ParamError(f'duration: must be in (0, {MAX_DURATION_S:g}] s, got '
                          f'{_show(duration)}')
    scenario = dataclasses.replace(scenario, duration=float(duration))
    _check_consistency(scenario)
    return scenario


def _check_consistency(scenario: Scenario) -> None:
    """Cross-section checks: run size, initial tilt, then the controllers' own."""
    samples = scenario.duration * scenario.rates.control_rate
    if round(samples) < 1:
        raise ParamError(f'duration: {scenario.duration:g} s is less than one control '
                          f'period ({scenario.control_period:g} s at rates.control_rate '
                          f'{scenario.rates.control_rate:g} Hz): the run would have no '
                          'control tick')
    if samples > MAX_CONTROL_SAMPLES:
        raise ParamError(f'duration: {scenario.duration:g} s at rates.control_rate '
                          f'{scenario.rates.control_rate:g} Hz is {samples:.3g} control '
                          f'periods, more than the {MAX_CONTROL_SAMPLES:.0e} one run may have '
                          '(memory); shorten the run or lower the rate')
    if abs(scenario.initial_state.theta) >= scenario.fall_threshold:
        raise ParamError(f'initial_state.theta: |{scenario.initial_state.theta:g}| rad is at '
                          f'or beyond fall_threshold {scenario.fall_threshold:g} rad: the run '
                          'would count as a fall before it starts')
    check_controller_consistency(scenario)


def paper_scenario(overrides: Mapping[str, Any] | None = None) -> Scenario:
    """Section V with the paper's design (``design: paper``), plus ``overrides``."""
    return scenario_from_mapping({**(overrides or {}), 'design': 'paper'})


def load_scenario(path: str | pathlib.Path | None = None) -> Scenario:
    """Load and validate a scenario file; ``None`` gives the paper's Section V.

    A file without a ``name`` is named after itself (its stem), not after the default.
    """
    if path is None:
        return Scenario()
    return load_scenario_file(path, scenario_from_mapping)


def scenario_to_mapping(scenario: Scenario) -> dict[str, Any]:
    """Plain-data form of a scenario (round-trips through :func:`scenario_from_mapping`)."""
    out = controller_settings_to_mapping(scenario)
    out['plant'] = {**dataclasses.asdict(scenario.plant.model),
                    'parameters': dataclasses.asdict(scenario.plant.parameters)}
    if scenario.plant.model.model in ENGINE_MODELS:
        out['plant']['contact'] = dataclasses.asdict(scenario.plant.contact)
        out['plant']['terrain'] = dataclasses.asdict(scenario.plant.terrain)
    out['disturbances'] = scenario.disturbances.to_mapping()
    return out
