"""MPC node: the longitudinal/tilt model predictive controller, eqs. (16)–(23) in [1]_.

Topics
------
Subscribes ``/wip/state_estimate`` (υ̂, θ̂, θ̂̇, f̂2, f̂3), ``/wip/velocity_command`` (υd) and
``/wip/yaw_torque`` (τω, which sets the drive torque bound
``core.mixer.drive_torque_limit(τω, mixer.max_wheel_torque)`` = 2 τmax − |τω|).
Publishes ``/wip/drive_torque`` (wip_msgs/DriveTorque: τυ, Δτ, status, iterations, build +
solve time, slacks, predicted υ/θ/θ̇) every ``mpc.sampling_period``, and ``/diagnostics``.

Per tick: the drive stage of the loop, ``core.control_step.DriveControllerStage.step`` (as the
runner's ``ControlStep``): ``core.mpc.LongitudinalMpc``, or the LQR baseline
``core.lqr.LongitudinalLqr`` when ``mpc.controller`` is ``lqr`` (same interface and
message). The core keeps
τυ(k−1). Status: SOLVED; FALLBACK_SHIFTED_PLAN on any solver failure (``status_text`` is
the core's status name); INPUT_INVALID when an input is not finite (the core then ramps
τυ toward 0) or, in real time, older than the safety layer's whole ride-through; NOT_READY
(τυ = 0) in real time before every input has arrived once. Unknown slacks are sent as 0
and unknown predictions as empty arrays, never NaN.

Ticks
-----
lockstep: t_k is a tick when k = round(t_k / h) is a multiple of
round(``mpc.sampling_period`` / h), or of round(``mpc.fast_resolve_period`` / h) when that
is set (every k with ``mpc.push_trigger``, which looks for a push at every control tick),
h = 1/``rates.control_rate`` (the runner's ``DriveControllerStage.is_tick(k)``, t = 0
included); the tick is computed as soon as estimate(t_k), command(t_k) and yaw_torque(t_k)
have all arrived, in any order. Inputs at other stamps are not needed. (Not a sim-time
timer: see ``wip_runtime.clock``.) At a tick of the re-solve grid where the stage does not
solve (``DriveControllerStage.solves``, which needs the estimate only: no push), the held
τυ is published (status SOLVED, ``status_text`` HELD, no plan) as soon as estimate(t_k)
has arrived, so the mixer gets an answer at every tick of the grid.
realtime: a tick every ``mpc.sampling_period`` (``mpc.fast_resolve_period`` when set,
h with ``mpc.push_trigger``; then only the ticks at which the stage solves publish)
computes with the latest inputs. Alone in its process the tick is a timer of the node
clock. Composed, it runs when the mixer's wheel torques end the chain of a sensor sample
at least a tick period less half a control period after the last tick, and on a deadline
that the spin loop keeps (an adopted ``wip_runtime.executors.Watchdog``, half a control
period late) for a chain that does not come: the same inputs as a timer firing between
that chain and the next (either way the drive torque is applied from the next chain on),
without a wake-up of its own. If an input is missing (NOT_READY) the tick publishes
τυ = 0 and tells the core that 0 was applied. Lateness is the safety layer's to judge, by
its rule and values (``safety.max_estimate_age``, ``safety.bridge_time``; ages since the
inputs were received, as the mixer counts them): when the oldest input is late (older than
the age limit) the tick is held, not run: nothing is published (the mixer bridges along
the last plan), ``/diagnostics`` says WARN, and the next chain's end (composed) or timer
tick (alone) runs it. A deadline that a stall of the process left past due fires before
the executor takes the chain queued during the stall, so without the hold a stall the
mixer rides through would become a fault. Older than the whole ride-through (age limit +
bridge time) the tick publishes τυ = 0 with INPUT_INVALID, as the mixer faults then. The
node also subscribes ``/wip/wheel_torques`` and, before each tick, gives the core the drive
torque τυ = τl + τr the mixer last applied (``LongitudinalMpc.set_previous_torque``): when
the safety layer holds the torque at zero (start-up, a fault) or limits it, the next plan
starts from what the wheels really got, not from the MPC's own unapplied output. Without
this, an MPC that runs for seconds while the mixer waits for the ESO to settle (a robot
held by hand before it is released) starts with a torque step when the mixer engages.
(lockstep reproduces the in-process runner, where the applied torque is the MPC's.)

Parameters (all read-only): sections ``mpc``, ``model`` (the nominal model), ``mixer``
(max_wheel_torque), ``rates`` (control_rate, for the tick grid), ``safety``
(max_estimate_age, bridge_time: the mixer's values), ``clock_mode``, ``diagnostics_period``.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016.
"""

from __future__ import annotations

import functools
import math
import sys
import time

from wip_msgs.msg import (YawTorque, DriveTorque, StateEstimate as StateEstimateMsg,
                          VelocityCommand as VelocityCommandMsg, WheelTorques)

from ..core.arc import ArcOutput
from ..core.control_step import DriveControllerStage
from ..core.safety import SafetyDecision
from ..core.safety_config import LATE, lateness, STALE
from ..core.mpc_config import MpcParams, resolves_faster
from wip_description.params import ModelParams
from ..core.controller_settings import RatesParams
from ..core.state_estimation import PoseEstimate
from ..core.trajectory_generator import VelocityCommand
from .common import ControllerNode
from wip_runtime.node_main import run_node
from wip_runtime.qos import RELIABLE_QOS
from wip_runtime.stamps import stamp_to_ns
from .conversions import (applied_torques, arc_from_msg, command_from_msg, estimate_from_msg,
                          mpc_hold_msg, mpc_idle_msg, mpc_to_msg, wheel_torques_from_msg)
from wip_runtime.diagnostics import OK, WARN
from wip_runtime.executors import Watchdog
from wip_runtime.parameters import RosParams
from .settings import SafetyRideThrough, WheelTorqueLimit
from wip_runtime.sync import decimation, ExactTimeSync, tick_index

_INPUTS = ('state_estimate', 'velocity_command', 'yaw_torque')


class MpcNode(ControllerNode):
    """See the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('mpc', 'longitudinal/tilt MPC (16)-(23)', _INPUTS, **kwargs)
        self.config = RosParams(self, 'mpc', MpcParams).config
        self.model = RosParams(self, 'model', ModelParams).config
        self.max_wheel_torque = RosParams(self, 'mixer',
                                                 WheelTorqueLimit).config.max_wheel_torque
        self.rates = RosParams(self, 'rates', RatesParams).config
        #: The safety layer's ride-through (docs/decisions/safety-layer.md): late past the
        #: estimate's age limit, stale past the bridge too (``core.safety.lateness``).
        self.ride = RosParams(self, 'safety', SafetyRideThrough).config
        self.late_after = self.ride.max_estimate_age
        self.stale_after = self.ride.max_estimate_age + self.ride.bridge_time
        self.sampling_period = self.config.sampling_period
        self.control_period = 1.0 / self.rates.control_rate
        fast = self.config.fast_resolve_period
        # The drive stage of the loop (core/control_step.py): the MPC or the LQR, and its
        # grid (core.mpc_config.drive_tick_decimation).
        self.stage = DriveControllerStage(self.model, self.config, self.max_wheel_torque,
                                decimation(self.sampling_period, self.control_period),
                                decimation(fast, self.control_period)
                                if resolves_faster(self.sampling_period, fast) else None)
        self.every = self.stage.every
        self.tick_period = self.every * self.control_period
        self.realtime_k = 0   # realtime: the control tick of the next timer tick
        self.mpc = self.stage.controller
        self.latest: dict[str, tuple[int, object]] = {}
        self._held_stamp: int | None = None   # lockstep: the last tick answered HELD early
        self.publisher = self.create_publisher(DriveTorque, 'wip/drive_torque', RELIABLE_QOS)
        if self.lockstep:
            self.sync = ExactTimeSync(_INPUTS, self._tick)
        else:
            # The tick's deadline; composed, the chain's end runs the tick (_on_applied).
            self.chain_slack = 0.5 * self.control_period
            self.watchdog = Watchdog(self, self.tick_period, self._realtime_tick,
                                     clock=self.get_clock(), grace=self.chain_slack)
            self.ticked_at = -math.inf   # steady time [s] of the last tick
            self.received: dict[str, float] = {}   # steady time [s] of each input's arrival
            self.subscribe(WheelTorques, 'wip/wheel_torques', 'wheel_torques',
                           self._on_applied, direct=self._on_applied_value,
                           value_type=SafetyDecision)
        self.applied_drive_torque: float | None = None
        self._subscribe_input(StateEstimateMsg, 'wip/state_estimate', 'state_estimate',
                              estimate_from_msg, PoseEstimate)
        self._subscribe_input(VelocityCommandMsg, 'wip/velocity_command', 'velocity_command',
                              command_from_msg, VelocityCommand)
        self._subscribe_input(YawTorque, 'wip/yaw_torque', 'yaw_torque', arc_from_msg,
                              ArcOutput)
        self.diagnostics.state(OK, 'waiting for the first tick')
        self._shown_rate = None   # the rate limit last put in /diagnostics' values

    def is_tick(self, stamp_ns: int) -> bool:
        """Whether ``stamp_ns`` is an MPC tick of the lockstep grid (from t = 0)."""
        return self.stage.is_tick(tick_index(stamp_ns, self.control_period))

    def _subscribe_input(self, msg_type, topic: str, name: str, convert, value_type) -> None:
        """Take an input from a message (not checked: see _on_value) or from the chain."""
        self.subscribe(msg_type, topic, name,
                       lambda msg: self._on_input(name, msg, convert(msg, check=False)),
                       direct=functools.partial(self._on_value, name), value_type=value_type)

    def _on_input(self, name: str, msg, value) -> None:
        self._on_value(name, stamp_to_ns(msg.header.stamp), value)

    def _on_value(self, name: str, stamp: int, value) -> None:
        # Non-finite values are passed on: the core answers INPUT_INVALID with a finite
        # torque, and in lockstep the tick must be answered or the graph would stop.
        self.diagnostics.input(name, stamp)
        if self.lockstep:
            if self.is_tick(stamp) and not self._held_early(name, stamp, value):
                self.feed(name, stamp, value)
        else:
            self.latest[name] = (stamp, value)
            self.received[name] = time.monotonic()

    def _held_early(self, name: str, stamp: int, value) -> bool:
        """Lockstep: answer a tick where the stage does not solve as soon as its estimate comes.

        Whether it solves depends on the estimate alone (``DriveControllerStage.solves``),
        so the HELD answer need not wait for the command and the yaw torque, which come
        after the estimate: with the push trigger the mixer awaits a drive torque at every
        control tick, and this keeps the MPC node off that tick's critical path. True when
        the input is not needed (the tick is answered).
        """
        if stamp == self._held_stamp:
            return True
        if name != 'state_estimate':
            return False
        k = tick_index(stamp, self.control_period)
        estimate = value.estimate
        self.stage.observe(k, estimate.theta, estimate.f2, estimate.f3)
        if self.stage.solves(k, estimate.theta, estimate.f2, estimate.f3):
            return False
        self.sync.discard(stamp)
        self._held_stamp = stamp
        self.publisher.publish(mpc_hold_msg(stamp, self.stage.tau_v, self.sampling_period))
        return True

    def _on_applied(self, msg: WheelTorques) -> None:
        """realtime: the torques the mixer applied (ValueError on non-finite: dropped)."""
        self._applied(*wheel_torques_from_msg(msg))

    def _on_applied_value(self, _stamp: int, decision: SafetyDecision) -> None:
        """realtime: the mixer's decision of the same process (the message's rule)."""
        self._applied(*applied_torques(decision))

    def _applied(self, left: float, right: float) -> None:
        """Take the applied torques; composed, the end of a sensor sample's chain.

        A tick due within half a control period runs now, with that chain's inputs and
        applied torque, as a timer firing between this chain and the next would have run it.
        """
        self.applied_drive_torque = left + right
        watchdog = self.watchdog
        if (watchdog.adopted
                and time.monotonic() - self.ticked_at >= self.tick_period - self.chain_slack):
            # The deadline (half a control period late: the grace) is for a chain that
            # does not come, so a chain a little late never meets a tick just run.
            watchdog.kick()
            self._realtime_tick()

    def _realtime_tick(self) -> None:
        # One rule of lateness, the safety layer's: a late input is bridged by the mixer
        # (DEGRADED, along the last plan), so merely late inputs hold the tick; only past
        # the whole ride-through, where the mixer faults anyway, is it INPUT_INVALID.
        ages = {n: time.monotonic() - t for n, t in self.received.items()}
        verdict = lateness(max(ages.values(), default=0.0), self.ride.max_estimate_age,
                           self.ride.bridge_time)
        if verdict == LATE and len(ages) == len(_INPUTS):
            self._hold(ages)
            return
        self.ticked_at = time.monotonic()
        k = self.realtime_k
        self.realtime_k += self.every
        try:
            if self.applied_drive_torque is not None:
                self.mpc.set_previous_torque(self.applied_drive_torque)
            now = self.now_ns()
            latest = self.latest
            if len(latest) < len(_INPUTS):
                missing = [n for n in _INPUTS if n not in latest]
                self._idle(now, DriveTorque.NOT_READY, f'NOT_READY: no {", ".join(missing)} yet')
                return
            if verdict == STALE:
                stale = [f'{n} received {age:.3f} s ago' for n, age in ages.items()
                         if age > self.stale_after]
                self._idle(now, DriveTorque.INPUT_INVALID,
                           f'INPUT_INVALID: stale {stale} > {self.stale_after:g} s (safety '
                           'age limit + bridge)')
                return
            estimate, command, yaw = (latest[n] for n in _INPUTS)
            self._tick(estimate[0], {'state_estimate': estimate[1],
                                     'velocity_command': command[1], 'yaw_torque': yaw[1]}, k)
        except Exception as err:  # noqa: BLE001 - a timer callback must not stop the node
            self.diagnostics.drop('tick', 'error', f'{type(err).__name__}: {err}')

    def _hold(self, ages: dict[str, float]) -> None:
        """realtime: hold the tick on late inputs; the safety layer bridges them.

        Not a tick (the last tick's time and the tick count stay): composed, the next
        chain's end runs it with the inputs it brings; alone, the next timer tick.
        """
        late = ', '.join(f'{n} {age:.3f} s' for n, age in ages.items()
                         if age > self.late_after)
        self.diagnostics.state(WARN, f'late inputs (received {late} ago > '
                                     f'{self.late_after:g} s): tick held, the mixer bridges '
                                     f'up to {self.stale_after:g} s')

    def _idle(self, stamp: int, status: int, text: str) -> None:
        """Publish τυ = 0 without solving; the core's τυ(k−1) becomes the applied 0."""
        self.mpc.set_previous_torque(0.0)
        self.publisher.publish(mpc_idle_msg(stamp, status, text, self.sampling_period))
        self.diagnostics.output(stamp, 0.0)
        self.diagnostics.state(WARN, text)

    def _tick(self, stamp: int, values, k: int | None = None) -> None:
        start = time.perf_counter()
        estimate = values['state_estimate'].estimate
        tau_omega = values['yaw_torque'].tau_omega
        if k is None:   # lockstep: the stamp's control tick
            k = tick_index(stamp, self.control_period)
        self.stage.observe(k, estimate.theta, estimate.f2, estimate.f3)
        if not self.stage.solves(k, estimate.theta, estimate.f2, estimate.f3):
            # A tick of the re-solve grid without a push: the torque stays held (lockstep
            # answers it, as the mixer awaits a drive torque at each tick of the grid).
            if self.lockstep:
                self.publisher.publish(mpc_hold_msg(stamp, self.stage.tau_v,
                                                    self.sampling_period))
            return
        result = self.stage.step(estimate.v, estimate.theta, estimate.theta_dot, estimate.f2,
                                 estimate.f3, values['velocity_command'].v_d, tau_omega,
                                 k=k)
        self.publisher.publish(mpc_to_msg(result, stamp, self.sampling_period))
        self.diagnostics.output(stamp, time.perf_counter() - start)
        self.diagnostics.state(OK if not result.used_fallback else WARN,
                               f'{result.status.name}: tau_v {result.tau_v:.4g} N m, '
                               f'|tau_v| limit {self._limit(tau_omega):.4g} N m')
        self.diagnostics.values['last solve [us]'] = (
            f'{1e6 * (result.solve_time_s + result.build_time_s):.1f}')
        if self.stage.rate != self._shown_rate:
            self._shown_rate = self.stage.rate
            self.diagnostics.values['|delta tau_v| limit per Ts [N m]'] = (
                f'{self.stage.rate:g}' + (' (lifted: an obstacle stops the base)'
                                          if self.stage.rate > self.config.max_delta_torque
                                          else ''))

    def _limit(self, tau_omega: float) -> float:
        return min(self.stage.limit(tau_omega), self.config.max_drive_torque)


def main(args=None) -> int:
    """Entry point ``mpc``."""
    return run_node(MpcNode, 'mpc', args)


if __name__ == '__main__':
    sys.exit(main())
