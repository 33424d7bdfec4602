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
import time
from typing import Callable

from wip_control.core import control_step
from wip_control.core.control_step import ControlStep
from wip_control.core.references import make_loop_reference
from wip_control.core.obstacle import ObstacleState
from wip_control.core.state_estimation import StateEstimator

from .record import GROUPS, RecordBuffer, RunRecord
from .scenario import Scenario
from .simulation import Simulation


@dataclasses.dataclass
class RunResult:
    """Outcome of :func:`run_scenario`."""

    record: RunRecord
    fell: bool
    fall_time: float | None
    wall_time_s: float
    simulated_time_s: float
    mpc_inputs: list[dict] | None = None
    #: The first time the estimator found the wheels blocked by an obstacle, and why
    #: (core/obstacle.py); None if never (or the monitor is off).
    obstacle: ObstacleState | None = None


ProgressCallback = Callable[[float, float], None]

#: The record's groups, in the order of the record.
RECORDED_GROUPS = ('truth', 'reference', 'estimate', 'command', 'arc', 'wheels', 'mpc',
                   'encoders', 'imu')
#: The groups with a row at every control tick, in the order of their columns in the one
#: wide row per tick the loop appends (the time once, then each group's other columns).
TICK_GROUPS = ('encoders', 'imu', 'reference', 'estimate', 'command', 'arc', 'wheels')


class _Recorder:
    """The run's record buffers.

    Appenders: ``truth`` and ``mpc`` (a row of their group) and ``tick`` (one wide row of
    every group of :data:`TICK_GROUPS`: one tuple and one append per tick instead of
    seven; docs/runner-speed.md). The rows become numpy blocks every
    ``RecordBuffer.BLOCK_ROWS`` ticks; :meth:`arrays` splits the wide rows into their
    groups.
    """

    def __init__(self) -> None:
        self.buffers = {group: RecordBuffer(group) for group in ('truth', 'mpc')}
        self.truth = self.buffers['truth'].appender()
        self.mpc = self.buffers['mpc'].appender()
        self._tick_columns: dict[str, list[int]] = {}
        wide = ['t']
        for group in TICK_GROUPS:
            columns = GROUPS[group]
            self._tick_columns[group] = [0, *range(len(wide), len(wide) + len(columns) - 1)]
            wide.extend(f'{group}.{name}' for name in columns[1:])
        self._ticks = RecordBuffer('tick', columns=tuple(wide))
        self.buffers['tick'] = self._ticks
        self.tick = self._ticks.appender()

    def tick_done(self, k: int) -> None:
        # At most one row per buffer and tick: a flush every BLOCK_ROWS ticks suffices.
        if k % RecordBuffer.BLOCK_ROWS == RecordBuffer.BLOCK_ROWS - 1:
            for buffer in self.buffers.values():
                buffer.flush()

    def arrays(self) -> dict:
        wide = self._ticks.to_matrix()
        groups = {'truth': self.buffers['truth'].to_arrays(),
                  'mpc': self.buffers['mpc'].to_arrays()}
        for group, indices in self._tick_columns.items():
            groups[group] = {name: wide[:, i].copy()
                             for name, i in zip(GROUPS[group], indices)}
        return {group: groups[group] for group in RECORDED_GROUPS}


def run_scenario(scenario: Scenario, progress: ProgressCallback | None = None,
                 record_mpc_inputs: bool = False) -> RunResult:
    """Simulate ``scenario`` in one Python loop and record everything.

    Parameters
    ----------
    progress : called as ``progress(t, duration)`` about once per simulated second.
    record_mpc_inputs : keep the arguments of every MPC call (for ``scripts/bench``).
    """
    wall_start = time.perf_counter()
    reference, _ = make_loop_reference(scenario.reference)
    sim = Simulation(scenario, reference)
    # The estimator starts from the first measurements and the first GPS fix, as the ESO
    # node does (core/state_estimation.py).
    estimator = StateEstimator.from_scenario(scenario, compiled=True)
    control = ControlStep.from_scenario(scenario)
    rec = _Recorder()
    mpc_inputs: list[dict] | None = [] if record_mpc_inputs else None
    dt_control, n_ticks, drive = sim.dt_control, sim.n_ticks, control.drive
    # Bound once: the loop runs at 100x real time, 18 000 ticks for the paper's run.
    read_sensors, disturbance, step = sim.read_sensors, sim.disturbance, sim.step
    sample_reference = (_ReferenceBlocks(reference, dt_control).at if reference.pure
                        else lambda k: reference.sample(k * dt_control))
    tau_left = tau_right = 0.0          # applied over the previous control period
    fell, fall_time = False, None
    next_progress = 1.0
    for k in range(n_ticks + 1):
        t = k * dt_control
        rec.truth((t, *sim.state, *disturbance(k), tau_left, tau_right))
        if sim.fallen():
            fell, fall_time = True, t
            break
        if k == n_ticks:
            break
        # 1-3: measurements -> estimates. The gyro rates are always sampled (as the
        # plant node publishes them); the 'paper' estimator ignores them.
        reading = read_sensors(k, wheel_rates=False)
        pose = estimator.update(t, *reading.encoders, *reading.imu, tau_left, tau_right,
                                reading.imu_rates, reading.gps)
        # 4-7: reference, generator, ARC, MPC at its own period (held), mixer.
        ref = sample_reference(k)
        tau_v_held = drive.tau_v
        out = control.step(t, ref, pose, drive.is_tick(k), k=k)
        tau_left, tau_right = out.tau_left, out.tau_right
        _record_tick(rec, t, reading, ref, pose, out)
        if out.mpc is not None and mpc_inputs is not None:
            mpc_inputs.append(_mpc_call(control, pose, out, tau_v_held))
        rec.tick_done(k)
        # 8: the plant, RK4 at plant_rate with the torques held.
        step(k, tau_left, tau_right)
        if progress is not None and t >= next_progress:
            progress(t, scenario.duration)
            next_progress += 1.0
    groups = rec.arrays()
    return RunResult(record=RunRecord(groups, attributes={'scenario': scenario.name}),
                     fell=fell, fall_time=fall_time,
                     wall_time_s=time.perf_counter() - wall_start,
                     simulated_time_s=float(groups['truth']['t'][-1]),
                     mpc_inputs=mpc_inputs,
                     obstacle=estimator.obstacle.first if estimator.obstacle else None)


class _ReferenceBlocks:
    """The reference's samples at t_k = k · dt, computed ``ticks`` ticks at a time.

    The same calls at the same float times as sampling at each tick (a pure reference,
    ``Reference.pure``), so the same values; in a block the reference's code and data
    stay in the CPU caches, where interleaved with the rest of the loop they would not
    (docs/runner-speed.md).
    """

    def __init__(self, reference, dt: float, ticks: int = 200) -> None:
        self._sample, self._dt, self._ticks = reference.sample, dt, ticks
        self._first = 0
        self._block: list = []

    def at(self, k: int):
        i = k - self._first
        if not 0 <= i < len(self._block):
            sample, dt = self._sample, self._dt
            self._block = [sample(j * dt) for j in range(k, k + self._ticks)]
            self._first, i = k, 0
        return self._block[i]


def _record_tick(rec: _Recorder, t: float, reading, ref, pose, out) -> None:
    """Record one control tick's rows.

    The named tuples' fields are in the record's column order (record.GROUPS; a test
    checks it), and the wide row's groups in the order of :data:`TICK_GROUPS`: the
    encoders, the IMU (angles, rates), (x, y, phi, v, omega) of the reference, the estimate
    but ε, every field of the command and of the ARC's output, the wheel torques.
    """
    if out.mpc is not None:
        result = out.mpc
        rec.mpc((t, result.tau_v, result.delta_tau, result.status, result.iterations,
                 result.solve_time_s, float(result.used_fallback), result.slack_v,
                 result.slack_theta))
    rec.tick((t, *reading.encoders, *reading.imu, *reading.imu_rates, *ref[:5],
              *pose.estimate[:9], pose.x, pose.y, *out.command, *out.arc, out.tau_left,
              out.tau_right))


def _mpc_call(control: ControlStep, pose, out, tau_previous: float) -> dict:
    """Return the arguments of this tick's MPC call (``record_mpc_inputs``)."""
    est = pose.estimate
    return dict(v_hat=est.v, theta_hat=est.theta, theta_dot_hat=est.theta_dot,
                f2_hat=est.f2, f3_hat=est.f3, v_d=out.command.v_d,
                tau_limit=control.drive.limit(out.arc.tau_omega), tau_previous=tau_previous)


def initial_alpha(scenario: Scenario) -> float:
    """α̂(0) of the scenario's yaw stage (``control_step.initial_alpha``)."""
    return control_step.initial_alpha(scenario.controller_model.parameters,
                                      scenario.eso.yaw_input_gain_scale)
