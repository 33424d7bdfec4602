"""The controllers of a re-run, fed tick by tick with a bag's recorded inputs.

The loop's two core objects are built fresh (``core.state_estimation.StateEstimator``,
``core.control_step.ControlStep``: the ones the in-process runner and the controller nodes
drive). Per control tick k (the stamps t_k present on both /joint_states and /imu/data, in
order): the ESO (eqs. (4), (8)) with the measurements of t_k and the torques applied over
[t_{k-1}, t_k); the planar position from odometry and a GPS fix; the trajectory generator
(eq. (9)) with the recorded reference, the ARC (eqs. (12), (13)); the MPC (eqs. (16)-(23))
at its ticks, held in between; the mixer (eq. (24)). docs/recording.md says how
the two timings decide which recorded command and fix a tick uses.
"""

from __future__ import annotations

import bisect
from typing import Any, NamedTuple

from sensor_msgs.msg import NavSatStatus

from wip_control.core.control_step import ControlStep
from wip_control.core.state_estimation import StateEstimator
from wip_control.nodes.conversions import gps_local_position
from wip_runtime.messages import InvalidMessage
from wip_sim.core.scenario import Scenario
from wip_tools.rerun_inputs import RecordedRun, RerunError


class TickOutputs(NamedTuple):
    """What the controllers computed at one tick (core values)."""

    stamp_ns: int
    t: float
    estimate: Any  # core StateEstimate
    x: float
    y: float
    settled: bool
    reference: Any  # core ReferenceState
    command: Any  # core VelocityCommand
    arc: Any  # core ArcOutput
    mpc: Any  # core MpcResult, or None between MPC ticks
    wheels: tuple  # (left, right) [N m]


TIMINGS = ('auto', 'stamps', 'receive')


def resolve_timing(run: RecordedRun, timing: str = 'auto') -> str:
    """Return the timing of a bag: 'stamps' or 'receive'.

    'stamps' for a bag recorded in lockstep simulation time (it holds /clock), else
    'receive'; an explicit 'stamps' or 'receive' is returned as is.
    """
    if timing not in TIMINGS:
        raise ValueError(f'timing {timing!r} is not one of {TIMINGS}')
    if timing == 'auto':
        return 'stamps' if run.has_clock else 'receive'
    return timing


def rerun_controllers(run: RecordedRun, scenario: Scenario,
                      timing: str = 'auto') -> list[TickOutputs]:
    """Feed the recorded inputs to fresh core controllers, tick by tick.

    ``timing`` chooses which recorded command was applied at a tick and when the MPC ran:
    'stamps' (lockstep: the command stamped t_{k-1}; the MPC every ``mpc_decimation``-th
    tick, exactly as the graph and the runner do), 'receive' (real time: the newest
    command the recorder had received before the tick's sensor samples, the MPC at the
    ticks after which the recorder received an MPC output; the controller nodes' own
    receive times are not recorded, so this approximates them by the recorder's), or
    'auto' (:func:`resolve_timing`).

    Raises
    ------
    RerunError
        If the bag has no control tick (no stamp with both joint states and IMU) or no
        reference.
    """
    timing = resolve_timing(run, timing)
    ticks = _control_ticks(run, timing)
    replay = _Replay(run, scenario, timing, ticks)
    outputs = []
    for k, stamp in enumerate(ticks):
        tick = replay.tick(k, stamp, (stamp - ticks[0]) / 1e9)
        if tick is not None:
            outputs.append(tick)
    return outputs


def _control_ticks(run: RecordedRun, timing: str) -> list[int]:
    """Return the control ticks: the stamps with both joint states and IMU samples."""
    ticks = sorted(set(run.joint_states) & set(run.imu))
    if timing == 'receive' and run.outputs['estimate']:
        # The samples the recorded ESO used (in real time it skips a sample whose IMU and
        # encoder messages did not both arrive before the next ones).
        used = set(ticks) & set(run.outputs['estimate'])
        ticks = sorted(used) if used else ticks
    if not ticks:
        raise RerunError('no control tick: the bag has no /joint_states and /imu/data '
                         'messages with equal stamps')
    if not run.reference:
        raise RerunError('the bag has no /wip/reference message')
    return ticks


class _Replay:
    """The loop's two core objects and what a tick looks its recorded inputs up in."""

    def __init__(self, run: RecordedRun, scenario: Scenario, timing: str, ticks: list[int]):
        self.run, self.timing = run, timing
        sensors = scenario.sensors
        self.datum = (sensors.gps_datum_latitude, sensors.gps_datum_longitude,
                      sensors.gps_datum_altitude)
        # The loop's two core objects, as the runner and the nodes drive them.
        self.estimator = StateEstimator.from_scenario(scenario, compiled=True)
        self.control = ControlStep.from_scenario(scenario)
        self.torque_stamps = sorted(run.wheel_torques)
        self.reference_stamps = sorted(run.reference)
        receive = run.receive_times
        self.by_receive = sorted((t, s) for s, t in receive.get('wheel_torques', {}).items())
        self.torque_receive_times = [t for t, _ in self.by_receive]
        # Real time: the MPC ran on the estimates its recorded outputs are stamped with, and
        # the mixer used an output from the first command it sent after the output arrived.
        tick_set = set(ticks)
        self.mpc_runs = {s: t for s, t in receive.get('mpc', {}).items() if s in tick_set}
        self.pending = []  # (receive time of the recorded output, tau_v) not yet mixed
        self.gps_order = [s for _, s in sorted((t, s) for s, t in receive.get('gps', {}).items())]
        self.gps_by_receive = [receive['gps'][s] for s in self.gps_order]
        self.last_fix = None

    def tick(self, k: int, stamp: int, t: float) -> TickOutputs | None:
        """Run control tick ``k`` (t: as the nodes' TimeBase, 0 at the first sample)."""
        run, receive = self.run, self.run.receive_times
        left, right = run.joint_states[stamp]
        pitch, yaw = run.imu[stamp]
        tick_receive = max(receive['joint_states'].get(stamp, 0), receive['imu'].get(stamp, 0))
        tau_left, tau_right = self._applied_torques(k, stamp, tick_receive)
        gps = self._gps(stamp, tick_receive)
        pose = self.estimator.update(t, left, right, pitch, yaw, tau_left, tau_right,
                                     run.imu_rates.get(stamp), gps)
        return self._control(k, stamp, t, tick_receive, pose)

    def _applied_torques(self, k: int, stamp: int, tick_receive: int) -> tuple:
        """Step 1: the torques applied over [t_{k-1}, t_k).

        The command stamped t_{k-1}, i.e. the newest recorded before t_k (zero before the
        first).
        """
        run = self.run
        if self.timing == 'receive':
            index = _newest_at_or_before(self.torque_receive_times, tick_receive - 1)
            if index is not None:
                return run.wheel_torques[self.by_receive[index][1]]
        elif k > 0:
            index = _newest_at_or_before(self.torque_stamps, stamp - 1)
            if index is not None:
                return run.wheel_torques[self.torque_stamps[index]]
        return 0.0, 0.0

    def _gps(self, stamp: int, tick_receive: int):
        """Step 2: the fix of the tick in map-frame (x, y), or None.

        As the ESO node, the position starts at the first fix. Lockstep: the fix of t_k;
        real time: the newest fix received before the tick's samples and not used yet (the
        ESO updates when the IMU and encoder samples are in; a fix published with them
        usually arrives just after and is used at the next update).
        """
        run = self.run
        if self.timing == 'receive':
            index = _newest_at_or_before(self.gps_by_receive, tick_receive - 1)
            fix = None
            if index is not None and self.gps_order[index] != self.last_fix:
                self.last_fix = self.gps_order[index]
                fix = run.gps[self.last_fix]
        else:
            fix = run.gps.get(stamp)
        if fix is not None and fix.status.status >= NavSatStatus.STATUS_FIX:
            try:
                return gps_local_position(fix, *self.datum)
            except InvalidMessage:
                run.invalid['gps'] = run.invalid.get('gps', 0) + 1
        return None

    def _control(self, k: int, stamp: int, t: float, tick_receive: int,
                 pose) -> TickOutputs | None:
        """Run steps 3-4: generator with the recorded reference, ARC, MPC (held), mixer.

        Real time: the MPC ran at the ticks of its recorded outputs, and its output was
        mixed from the first command recorded after it arrived, so it is held then.
        """
        control, drive = self.control, self.control.drive
        receive_mode = self.timing == 'receive' and bool(self.mpc_runs)
        mpc_tick = stamp in self.mpc_runs if receive_mode else drive.is_tick(k)
        index = _newest_at_or_before(self.reference_stamps, stamp)
        if index is None:
            return None  # No reference yet: the graph's generator would wait too.
        reference = self.run.reference[self.reference_stamps[index]]
        out = control.step(t, reference, pose, mpc_tick, hold=not receive_mode, k=k,
                           decide=not receive_mode)
        command, arc_out, result = out.command, out.arc, out.mpc
        wheels = (out.tau_left, out.tau_right)
        if receive_mode:
            if result is not None:
                self.pending.append((self.mpc_runs[stamp], result.tau_v))
            mixed_at = self.run.receive_times['wheel_torques'].get(stamp, tick_receive)
            while self.pending and self.pending[0][0] <= mixed_at:
                drive.tau_v = self.pending.pop(0)[1]
            wheels = control.mix(arc_out.tau_omega)
        return TickOutputs(stamp, t, pose.estimate, pose.x, pose.y, pose.settled,
                           reference, command, arc_out, result, wheels)


def _newest_at_or_before(stamps, stamp):
    """Index of the largest element of the sorted ``stamps`` that is <= ``stamp``."""
    index = bisect.bisect_right(stamps, stamp) - 1
    return index if index >= 0 else None
