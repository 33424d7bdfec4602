"""In-process closed loop: the plant, the sensors and the loop's two core objects.

Per control period k (t_k = k / control_rate, default 5 ms): the sensors sample the true
state (GPS every control_rate / gps_rate periods); ``StateEstimator`` (steps 1-3:
odometry, ESO with the torques applied over [t_{k−1}, t_k), position) gives the estimate;
``ControlStep`` (steps 4-7: generator, ARC, MPC every ``mpc_decimation``-th period and
held, mixer) gives (τl, τr), held while the plant integrates ``substeps`` RK4 steps
(step 8). The node graph in lockstep drives the same objects in the same order
(docs/control-loop.md).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable

import numpy as np

from . import control_step
from .control_step import ControlStep
from .disturbances import Disturbances
from .model import PHI, THETA
from .plant import scenario_plant
from .record import RecordBuffer, RunRecord
from .references import make_reference
from .scenario import Scenario
from .sensors import Sensors
from .state_estimation import StateEstimator


def initial_state(scenario: Scenario, reference_state) -> np.ndarray:
    """True initial state from the scenario; a relative pose is a body-frame error.

    With (x_e, y_e, ϕ_e) defined as in eq. (9) (body frame), the pose is
    ϕ = ϕr − ϕe and (x, y) = (xr, yr) − R(ϕ) (x_e, y_e). Section V's ϕ(0) = 0.5
    contradicts ϕr(0) − ϕe(0); docs/paper.md §6 adopts ϕ(0) = ϕr(0) − 0.1.
    """
    init = scenario.initial_state
    a, b, c = init.pose
    if init.pose_relative_to_reference:
        phi = reference_state.phi - c
        cos_phi, sin_phi = math.cos(phi), math.sin(phi)
        x = reference_state.x - (cos_phi * a - sin_phi * b)
        y = reference_state.y - (sin_phi * a + cos_phi * b)
    else:
        x, y, phi = a, b, c
    return np.array([x, y, phi, init.x_v, init.theta, init.omega, init.v, init.theta_dot])


@dataclasses.dataclass
class RunResult:
    """Outcome of :func:`run_scenario`."""

    record: RunRecord
    fell: bool
    fall_time: float | None
    wall_time_s: float
    simulated_time_s: float
    mpc_inputs: list[dict] | None = None


ProgressCallback = Callable[[float, float], None]


def run_scenario(scenario: Scenario, progress: ProgressCallback | None = None,
                 record_mpc_inputs: bool = False) -> RunResult:
    """Simulate ``scenario`` in one Python loop and record everything.

    Parameters
    ----------
    progress : called as ``progress(t, duration)`` about once per simulated second.
    record_mpc_inputs : keep the arguments of every MPC call (for ``scripts/bench``).
    """
    wall_start = time.perf_counter()
    true_params = scenario.plant.parameters
    plant = scenario_plant(scenario)
    disturbances = Disturbances(scenario.disturbances, seed=scenario.seed)
    reference = make_reference(scenario.reference)
    # The state is a float tuple in the loop (indexing a tuple is cheaper than an array).
    state = tuple(initial_state(scenario, reference.sample(0.0)).tolist())

    sensors = Sensors(true_params, scenario.sensors, initial_yaw=float(state[PHI]),
                      seed=scenario.seed)
    # The estimator starts from the first measurements and the first GPS fix, as the ESO
    # node does (core/state_estimation.py).
    estimator = StateEstimator.from_scenario(scenario)
    control = ControlStep.from_scenario(scenario)
    drive = control.drive

    dt_control = scenario.control_period
    substeps = scenario.rates.substeps
    dt_plant = dt_control / substeps
    n_ticks = int(round(scenario.duration / dt_control))
    gps_every = max(1, int(round(scenario.rates.control_rate / scenario.sensors.gps_rate)))

    buffers = {g: RecordBuffer(g) for g in
               ('truth', 'reference', 'estimate', 'command', 'arc', 'wheels', 'mpc',
                'encoders', 'imu')}
    # The rows go straight into the buffers' lists; every BLOCK_ROWS ticks (at most one
    # row per group and tick) they become numpy blocks.
    record_truth, record_reference, record_estimate, record_command, record_arc, \
        record_wheels, record_mpc, record_encoders, record_imu = (
            b.appender() for b in buffers.values())
    flush_every = RecordBuffer.BLOCK_ROWS
    mpc_inputs: list[dict] | None = [] if record_mpc_inputs else None

    tau_left = tau_right = 0.0          # applied over the previous control period
    fell, fall_time = False, None
    next_progress = 1.0

    # Disturbances on the plant's time grid t_k + j dt_plant (the times simulate_hold
    # would use), evaluated a block of ticks at a time: row j = 0 is the one recorded.
    block = _DisturbanceBlocks(disturbances, dt_control, dt_plant, substeps)
    hold = plant.hold_floats

    fall_threshold = scenario.fall_threshold
    for k in range(n_ticks + 1):
        t = k * dt_control
        d_tick, d_now = block.rows(k)
        record_truth((t, *state, *d_now, tau_left, tau_right))
        if abs(state[THETA]) >= fall_threshold:
            fell, fall_time = True, t
            break
        if k == n_ticks:
            break

        # 1-3: measurements -> estimates. The gyro rates are always sampled (as the
        # plant node publishes them); the 'paper' estimator ignores them.
        sensed, gps_seen = sensors.delayed(state)
        fix = (sensors.gps(gps_seen) if k % gps_every == 0 and sensors.gps_fix_available()
               else None)
        encoders, imu = sensors.encoders(sensed), sensors.imu(sensed)
        imu_rates = sensors.imu_rates(sensed)
        pose = estimator.update(t, *encoders, *imu, tau_left, tau_right, imu_rates, fix)
        record_encoders((t, *encoders))
        record_imu((t, *imu, *imu_rates))

        # 4-7: reference, generator, ARC, MPC at its own period (held), mixer.
        ref = reference.sample(t)
        tau_v_held = drive.tau_v
        out = control.step(t, ref, pose, drive.is_tick(k), k=k)
        tau_left, tau_right = out.tau_left, out.tau_right
        if out.mpc is not None:
            result, est = out.mpc, pose.estimate
            if mpc_inputs is not None:
                mpc_inputs.append(dict(
                    v_hat=est.v, theta_hat=est.theta, theta_dot_hat=est.theta_dot,
                    f2_hat=est.f2, f3_hat=est.f3, v_d=out.command.v_d,
                    tau_limit=drive.limit(out.arc.tau_omega),
                    tau_previous=tau_v_held))
            record_mpc((t, result.tau_v, result.delta_tau, result.status,
                        result.iterations, result.solve_time_s, float(result.used_fallback),
                        result.slack_v, result.slack_theta))

        # The named tuples' fields are in the record's column order (record.GROUPS; a
        # test checks it): (x, y, phi, v, omega) of the reference, the estimate but ε,
        # every field of the command and of the ARC's output.
        record_reference((t, *ref[:5]))
        record_estimate((t, *pose.estimate[:9], pose.x, pose.y))
        record_command((t, *out.command))
        record_arc((t, *out.arc))
        record_wheels((t, tau_left, tau_right))
        if k % flush_every == flush_every - 1:
            for buffer in buffers.values():
                buffer.flush()

        # 8: the plant, RK4 at plant_rate with the torques held.
        state = hold(state, tau_left, tau_right, d_tick, dt_plant)
        # One sum (a NaN or inf propagates), each value only if that is not finite.
        if not (math.isfinite(sum(state)) or all(map(math.isfinite, state))):
            raise ValueError(f'plant state became non-finite at t = {t + dt_control:.3f} s: '
                             f'{state} (check the disturbances)')
        if progress is not None and t >= next_progress:
            progress(t, scenario.duration)
            next_progress += 1.0

    groups = {name: buf.to_arrays() for name, buf in buffers.items()}
    record = RunRecord(groups, attributes={'scenario': scenario.name})
    return RunResult(record=record, fell=fell, fall_time=fall_time,
                     wall_time_s=time.perf_counter() - wall_start,
                     simulated_time_s=float(groups['truth']['t'][-1]),
                     mpc_inputs=mpc_inputs)


def initial_alpha(scenario: Scenario) -> float:
    """α̂(0) of the scenario's yaw stage (``control_step.initial_alpha``)."""
    return control_step.initial_alpha(scenario.controller_model.parameters,
                                      scenario.eso.yaw_input_gain_scale)


class _DisturbanceBlocks:
    """(d1, d2, d3) at t_k + j dt_plant, j < substeps, computed ``ticks`` ticks at a time.

    The same scalar functions at the same float times as ``Plant.simulate_hold``
    (t0 + j dt with t0 = k dt_control), so the values are identical; batching only
    saves building a small array per tick (and the recorded row j = 0 is kept as Python
    floats, cheaper to record than numpy scalars).
    """

    def __init__(self, disturbances: Disturbances, dt_control: float, dt_plant: float,
                 substeps: int, ticks: int = 200) -> None:
        self._disturbances = disturbances
        self._dt_control, self._dt_plant = dt_control, dt_plant
        self._substeps, self._ticks = substeps, ticks
        self._first = -1
        self._table = np.empty((0, substeps, 3))
        self._now: list[list[float]] = []

    def rows(self, k: int) -> tuple[np.ndarray, list[float]]:
        """The (substeps, 3) rows of tick ``k`` (a view) and its row 0, (d1, d2, d3) at
        t_k, as floats."""
        i = k - self._first
        if self._first < 0 or i >= self._ticks:
            self._fill(k)
            i = 0
        return self._table[i], self._now[i]

    def _fill(self, first: int) -> None:
        dt_control, dt_plant = self._dt_control, self._dt_plant
        steps = range(self._substeps)
        times = [k * dt_control + j * dt_plant
                 for k in range(first, first + self._ticks) for j in steps]
        self._table = self._disturbances.sample_many(times).reshape(
            self._ticks, self._substeps, 3)
        if not np.all(np.isfinite(self._table)):
            raise ValueError(f'disturbances must be finite (ticks from t = {first * dt_control} s)')
        self._now = self._table[:, 0, :].tolist()
        self._first = first
