"""Safety layer of the wheel-torque output: when to send torque to a real base, and how much.

Pure Python (no rclpy): the torque_mixer node feeds a :class:`SafetyMonitor` with its
inputs as they arrive and asks it, once per control tick, for the wheel torques to send.
Not part of the paper [1]_; written for the drop-in use on a real two-wheeled base
(docs/real-base.md), whose ros2_control
``JointGroupEffortController`` holds the last command forever and has no timeout.

Every fault zeroes both wheel torques in the tick it is seen (the fail-safe state is zero
torque); the states STARTING, ACTIVE, DEGRADED, SHADOW, FAULT and ESTOP, the ages of the
inputs, the ride-through of a late input (bounded by :func:`tilt_divergence_rate`) and the
limits: docs/decisions/safety-layer.md.

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import enum
import math
from typing import NamedTuple, Sequence

from .eso import StateEstimate
from .mixer import mix
from .position import FAULT as POSITION_FAULT, NO_FIX, TRACKING
from .runaway import RunawayParams, RunawayGuard
from .safety_config import LATE, lateness, SafetyParams, STALE, TIME_TOLERANCE

STARTING, ACTIVE, DEGRADED, SHADOW, FAULT, ESTOP = (
    'STARTING', 'ACTIVE', 'DEGRADED', 'SHADOW', 'FAULT', 'ESTOP')
STATES = (STARTING, ACTIVE, DEGRADED, SHADOW, FAULT, ESTOP)
#: States in which the mixed torque is sent (to the base unless in shadow mode).
_TORQUE_STATES = (ACTIVE, DEGRADED, SHADOW)

#: Inputs watched by the monitor (the torque_mixer node's subscriptions).
ESTIMATE, YAW_TORQUE, DRIVE_TORQUE, ESTOP_INPUT = ('state_estimate', 'yaw_torque',
                                                   'drive_torque', 'estop')
_CONTROL_INPUTS = (ESTIMATE, YAW_TORQUE, DRIVE_TORQUE)
#: Index of ε in a StateEstimate: inf at the start of the paper's ramp, not checked.
_EPSILON = StateEstimate._fields.index('epsilon')


class DriveStatus(enum.IntEnum):
    """Status of a drive torque: the values of the ``wip_msgs/DriveTorque`` constants."""

    SOLVED = 0
    FALLBACK_SHIFTED_PLAN = 1
    FAILED_ZERO = 2
    INPUT_INVALID = 3
    NOT_READY = 4


class SafetyDecision(NamedTuple):
    """What one tick sends.

    ``tau_left``, ``tau_right`` [N·m]: the torques of this tick after every check and limit
    (zero unless ACTIVE or SHADOW), reported on /wip/wheel_torques; ``command``: what goes
    to the base (zero in shadow mode).
    """

    tau_left: float
    tau_right: float
    zeroed: bool                #: a safety condition forced both torques to zero
    reasons: tuple[str, ...]    #: why (every condition present), empty when ACTIVE
    state: str                  #: one of :data:`STATES`
    shadow: bool = False        #: shadow mode: ``command`` is zero

    @property
    def command(self) -> tuple[float, float]:
        """(τl, τr) [N·m] for the base: zero in shadow mode."""
        return (0.0, 0.0) if self.shadow else (self.tau_left, self.tau_right)

    @property
    def reason(self) -> str:
        """The reasons as one line."""
        return '; '.join(self.reasons)


class _Input:
    """The last valid value of one input, when it arrived, and whether the last was bad."""

    __slots__ = ('value', 'arrival', 'invalid')

    def __init__(self) -> None:
        self.value = None
        self.arrival: float | None = None
        self.invalid = ''


class SafetyMonitor:
    """State machine of the safety layer (docs/decisions/safety-layer.md).

    Feed each input as it arrives (:meth:`estimate`, :meth:`yaw_torque`,
    :meth:`drive_torque`, :meth:`invalid_input`, :meth:`estop`); call :meth:`update` once
    per control tick. Times are seconds of one monotonic clock of the caller's choice.

    Parameters
    ----------
    config : the safety tunables.
    max_wheel_torque : τmax [N·m] of each wheel (``MixerParams.max_wheel_torque``).
    max_wheel_torque_rate : [N·m/s] (``MixerParams.max_wheel_torque_rate``).
    period : nominal tick period [s], the Δt of the rate limit at the first update.
    timing_checks : False in lockstep: no ages, no start-up wait, ``settled`` not required,
        no position checks, no runaway guard.
    runaway : the runaway guard's tunables (``core.runaway.RunawayParams``).
    """

    def __init__(self, config: SafetyParams, max_wheel_torque: float,
                 max_wheel_torque_rate: float, period: float,
                 timing_checks: bool = True, runaway: RunawayParams | None = None) -> None:
        if not (math.isfinite(period) and period > 0.0):
            raise ValueError(f'SafetyMonitor: period must be finite and > 0, got {period!r}')
        self.config = config
        self.set_limits(max_wheel_torque, max_wheel_torque_rate)
        self.period = float(period)
        self.timing_checks = bool(timing_checks)
        self.inputs = {name: _Input() for name in (*_CONTROL_INPUTS, ESTOP_INPUT)}
        self.settled = False
        self.consecutive_fallbacks = 0
        self.drive_plan: tuple[tuple[float, ...], float] = ((), 0.0)
        self.estop_engaged = False      # the e-stop input says engaged now
        self.estop_latched = False
        self.estop_true_at: float | None = None   # when an e-stop last said engaged
        self.heartbeat_at: float | None = None    # when the last heartbeat arrived
        self.fault_latched: tuple[str, ...] = ()
        self.wiring = ''   # a wiring verdict (core.wiring_check): latched until reset()
        self.guard = RunawayGuard(runaway)
        self.runaway = ''  # the guard's verdict: latched until reset()
        self.position_status = TRACKING
        self.pose = (math.nan, math.nan)        # (x̂, ŷ) of the last valid estimate [m]
        self.reference_position: tuple[float, float] | None = None
        self._reference_fresh = False            # a reference arrived since the guard's step
        self._guard_estimate_time: float | None = None
        self.state = STARTING
        self.ready_since: float | None = None
        self.last_update: float | None = None
        self.tau_left = self.tau_right = 0.0   # output of the previous tick
        self.ticks = 0

    # -- limits ----------------------------------------------------------------------------
    def set_limits(self, max_wheel_torque: float, max_wheel_torque_rate: float) -> None:
        """Change τmax [N·m] and the rate limit [N·m/s] (both finite and > 0)."""
        for name, value in (('max_wheel_torque', max_wheel_torque),
                            ('max_wheel_torque_rate', max_wheel_torque_rate)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
                raise ValueError(f'SafetyMonitor: {name} must be finite and > 0, got {value!r}')
        self.max_wheel_torque = float(max_wheel_torque)
        self.max_wheel_torque_rate = float(max_wheel_torque_rate)

    # -- inputs ------------------------------------------------------------------------------
    def _accept(self, name: str, t: float, value) -> None:
        slot = self.inputs[name]
        slot.value, slot.arrival, slot.invalid = value, float(t), ''

    def invalid_input(self, name: str, t: float, reason: str) -> None:
        """Take an unusable message of input ``name`` (e.g. failed to convert).

        It is a fault until the next valid one; the last valid value is kept but not used.
        """
        self.inputs[name].invalid = reason or 'invalid'

    def estimate(self, t: float, estimate: Sequence[float], settled: bool,
                 position_status: int = TRACKING, x: float = math.nan,
                 y: float = math.nan) -> None:
        """Take a state estimate received at ``t`` [s].

        ``estimate``: a ``core.eso.StateEstimate`` or a sequence in its field order;
        ``settled``: the ESO's start-up flag;
        ``position_status``: ``core.position`` NO_FIX ... FAULT; (x, y): the planar
        position [m] (the runaway guard's input).
        """
        n = len(StateEstimate._fields)
        if estimate.__class__ is StateEstimate:   # the estimator's own: numbers already
            values = estimate
        else:
            try:
                values = tuple(float(v) for v in estimate)
            except (TypeError, ValueError) as err:
                self.invalid_input(ESTIMATE, t, f'not a sequence of numbers: {err}')
                return
            if len(values) != n:
                self.invalid_input(ESTIMATE, t, f'{len(values)} values, expected {n}')
                return
            values = StateEstimate(*values)
        # One sum first (NaN and inf propagate; ε may be inf), each value only if it is not
        # finite.
        if not math.isfinite(sum(values) - values[_EPSILON]):
            bad = [f'{k}={v!r}' for i, (k, v) in enumerate(zip(StateEstimate._fields, values))
                   if i != _EPSILON and not math.isfinite(v)]
            if bad:
                self.invalid_input(ESTIMATE, t, f'non-finite {", ".join(bad)}')
                return
        self._accept(ESTIMATE, t, values)
        self.settled = bool(settled)
        self.position_status = int(position_status)
        self.pose = (float(x), float(y))

    def reference(self, t: float, x: float, y: float) -> None:
        """Take the reference position (x_r, y_r) [m] received at ``t`` [s] (runaway guard)."""
        if _is_finite_number(x) and _is_finite_number(y):
            self.reference_position = (float(x), float(y))
            self._reference_fresh = True

    def yaw_torque(self, t: float, tau_omega: float) -> None:
        """τω [N·m] of the ARC, received at ``t`` [s]."""
        if not _is_finite_number(tau_omega):
            self.invalid_input(YAW_TORQUE, t, f'non-finite yaw torque {tau_omega!r}')
            return
        self._accept(YAW_TORQUE, t, float(tau_omega))

    def drive_torque(self, t: float, tau_v: float, status: int = DriveStatus.SOLVED,
                     plan: Sequence[float] = (), plan_period: float = 0.0) -> None:
        """τυ [N·m] and status of the MPC, received at ``t`` [s].

        ``plan``: the MPC's planned τυ for its periods k, k+1, … (held after the last),
        ``plan_period`` [s] apart (``DriveTorque.planned_tau_v``, ``sampling_period``); the
        drive torque follows it when no newer output arrives. Empty: τυ is held. A plan
        that is not finite or has no positive period is ignored (τυ is held).
        """
        if not _is_finite_number(tau_v):
            self.invalid_input(DRIVE_TORQUE, t, f'non-finite drive torque {tau_v!r}')
            return
        try:
            planned = tuple(float(v) for v in plan)
        except (TypeError, ValueError):
            planned = ()
        if not (planned and all(math.isfinite(v) for v in planned)
                and _is_finite_number(plan_period) and plan_period > 0.0):
            planned = ()
        self.drive_plan = (planned, float(plan_period) if planned else 0.0)
        if status == DriveStatus.FALLBACK_SHIFTED_PLAN:
            self.consecutive_fallbacks += 1
        else:
            self.consecutive_fallbacks = 0
        self._accept(DRIVE_TORQUE, t, (float(tau_v), int(status)))

    def estop(self, t: float, engaged: bool) -> None:
        """Take an e-stop message received at ``t`` [s].

        Engaged latches the e-stop; not engaged only allows a later :meth:`reset` (and is
        the heartbeat if ``max_estop_age`` > 0).
        """
        self._accept(ESTOP_INPUT, t, bool(engaged))
        self.estop_engaged = bool(engaged)
        if engaged:
            self.estop_latched = True
            self.estop_true_at = float(t)

    def heartbeat(self, t: float) -> None:
        """Take a heartbeat received at ``t`` [s] (fresh link, see ``max_estop_age``).

        Its own input, not a false on the e-stop topic: a supervisor's heartbeat must not
        release a button that another publisher holds engaged.
        """
        self.heartbeat_at = float(t)

    def wiring_fault(self, reason: str) -> None:
        """Take a wiring contradiction (``core.wiring_check.Verdict.reason``).

        It is a fault from the next tick, latched whatever ``latch_faults`` says (a wrong
        parameter does not go away by itself) until :meth:`reset`.
        """
        self.wiring = str(reason) or 'wiring: contradiction'

    def reset(self, now: float | None = None) -> tuple[bool, str]:
        """Explicit reset of a latched e-stop (and latched faults): (success, message).

        Refused while the e-stop input still says engaged, and (given ``now`` [s]) while
        an engaged e-stop was received within ``estop_hold_time``: the messages of several
        publishers interleave, and a false from one must not undo a button held by
        another. After a reset the monitor re-arms through STARTING (``settle_time``).
        """
        if self.estop_engaged:
            return False, 'e-stop still engaged: release it (publish false) before the reset'
        if (now is not None and self.estop_true_at is not None
                and now - self.estop_true_at < self.config.estop_hold_time):
            return False, (f'e-stop held: an engaged e-stop was received '
                           f'{now - self.estop_true_at:.2f} s ago (< estop_hold_time '
                           f'{self.config.estop_hold_time:g} s); release every e-stop first')
        was = []
        if self.estop_latched:
            was.append('e-stop')
        if self.fault_latched:
            was.append('latched fault (' + '; '.join(self.fault_latched) + ')')
        if self.wiring:
            was.append(self.wiring)
        if self.runaway:
            was.append(self.runaway)
        self.estop_latched = False
        self.fault_latched = ()
        self.wiring = ''
        self.runaway = ''
        self.guard.reset()
        if self.state in (ESTOP, FAULT):
            self.state = STARTING
            self.ready_since = None
        return True, ('reset ' + ' and '.join(was) + '; re-arming' if was
                      else 'nothing to reset')

    # -- the tick ----------------------------------------------------------------------------
    def ages(self, now: float) -> dict[str, float | None]:
        """Seconds since each input's last valid value (None: never received)."""
        return {name: None if slot.arrival is None else now - slot.arrival
                for name, slot in self.inputs.items()}

    def _conditions(self, now: float) -> tuple[list[str], list[str], list[str]]:
        """(faults, not-yet conditions, late inputs within the bridge) at ``now``."""
        # A wiring verdict first: it is the cause, a fall that follows is its effect.
        faults: list[str] = [self.wiring] if self.wiring else []
        if self.runaway:
            faults.append(self.runaway + ' (latched: reset required)')
        waiting: list[str] = []
        late: list[str] = []
        self._input_conditions(now, faults, waiting, late)
        estimate = self.inputs[ESTIMATE]
        if estimate.value is not None and not estimate.invalid:
            faults += self.config.estimate_faults(estimate.value)
            if self.timing_checks and not self.settled:
                waiting.append('ESO not settled')
            if self.timing_checks and self.position_status == POSITION_FAULT:
                faults.append('position source refused by the ESO (its /diagnostics says '
                              'why): check datum.* and position_source')
            elif self.timing_checks and self.position_status == NO_FIX:
                waiting.append('no position fix yet (position_source gps or odometry; '
                               'without GPS set position_source: wheels)')
        self._drive_conditions(faults, waiting)
        return faults, waiting, late

    def _input_conditions(self, now: float, faults: list[str], waiting: list[str],
                          late: list[str]) -> None:
        """Append each watched input's invalid, missing, late or stale condition."""
        cfg = self.config
        max_age = {ESTIMATE: cfg.max_estimate_age, YAW_TORQUE: cfg.max_yaw_torque_age,
                   DRIVE_TORQUE: cfg.max_drive_torque_age, ESTOP_INPUT: cfg.max_estop_age}
        watched = list(_CONTROL_INPUTS)
        if cfg.max_estop_age > 0.0:
            watched.append(ESTOP_INPUT)
        for name in watched:
            slot = self.inputs[name]
            arrival, label = slot.arrival, name
            if name == ESTOP_INPUT:
                # The link is alive if either the heartbeat or an e-stop message came.
                label = 'heartbeat (/wip/heartbeat or /wip/estop)'
                if self.heartbeat_at is not None:
                    arrival = max(self.heartbeat_at,
                                  arrival if arrival is not None else -math.inf)
            if slot.invalid:
                faults.append(f'{name} invalid: {slot.invalid}')
            elif arrival is None:
                if self.timing_checks or name in (YAW_TORQUE, DRIVE_TORQUE):
                    waiting.append(f'no {label} yet')
            elif self.timing_checks:
                age = now - arrival
                bridge = cfg.bridge_time if name != ESTOP_INPUT else 0.0
                verdict = lateness(age, max_age[name], bridge)
                if verdict == LATE:
                    late.append(f'{name} late: {age:.3f} s old > {max_age[name]:g} s, '
                                f'bridged up to {max_age[name] + bridge:g} s')
                elif verdict == STALE:
                    faults.append(f'{label} stale: {age:.3f} s old > '
                                  f'{max_age[name] + bridge:g} s (age limit '
                                  f'{max_age[name]:g} s + bridge {bridge:g} s; publisher '
                                  'stopped?)')

    def _drive_conditions(self, faults: list[str], waiting: list[str]) -> None:
        """Append the MPC status's condition: not ready, too many fallbacks, failed."""
        drive = self.inputs[DRIVE_TORQUE]
        if drive.value is None or drive.invalid:
            return
        status = drive.value[1]
        max_fallbacks = self.config.max_mpc_fallbacks
        if status == DriveStatus.NOT_READY:
            waiting.append('MPC not ready (NOT_READY)')
        elif status == DriveStatus.FALLBACK_SHIFTED_PLAN:
            if self.consecutive_fallbacks > max_fallbacks:
                faults.append(f'MPC failed: {self.consecutive_fallbacks} consecutive '
                              f'FALLBACK_SHIFTED_PLAN outputs > {max_fallbacks}')
        elif status in (DriveStatus.FAILED_ZERO, DriveStatus.INPUT_INVALID):
            faults.append(f'MPC failed: status {DriveStatus(status).name}')
        elif status != DriveStatus.SOLVED:
            faults.append(f'MPC failed: unknown status {status}')

    def update(self, now: float) -> SafetyDecision:
        """Return the torques of the tick at ``now`` [s] (one call per control tick)."""
        self.ticks += 1
        dt = self.period if self.last_update is None else max(0.0, now - self.last_update)
        self.last_update = now
        if self.timing_checks and self.state in _TORQUE_STATES:
            self._guard_step()
        faults, waiting, late = self._conditions(now)
        # The layer itself not run for longer than the bridge covers (its process frozen
        # or starved): the base held the last command that long, blind. A fault even if
        # fresh inputs arrived first on waking up.
        stall_bound = self.config.max_estimate_age + self.config.bridge_time
        if self.timing_checks and self.ticks > 1 and dt > stall_bound + TIME_TOLERANCE:
            faults.append(f'stalled: no safety tick for {dt:.3f} s > {stall_bound:g} s '
                          '(estimate age limit + bridge; this process was not scheduled)')
        if self.fault_latched and not faults:
            faults = [f'latched fault ({"; ".join(self.fault_latched)}): reset required']
        was_active = self.state in _TORQUE_STATES
        reasons: list[str] = []
        if self.estop_latched:
            state = ESTOP
            reasons.append('e-stop engaged' if self.estop_engaged
                           else 'e-stop latched: reset required')
        elif faults or (waiting and (was_active or self.state == FAULT)):
            state = FAULT
        elif waiting or (late and not was_active):
            state = STARTING      # (late before engaging: not yet, never bridged)
        elif was_active:
            state = DEGRADED if late else ACTIVE
        else:
            if self.ready_since is None:
                self.ready_since = now
            settling = now - self.ready_since
            if not self.timing_checks or settling >= self.config.settle_time - TIME_TOLERANCE:
                state = ACTIVE
            else:
                state = STARTING
                reasons.append(f'settling: {settling:.3f} of {self.config.settle_time:g} s')
        reasons += faults + waiting + late
        if state == FAULT and self.config.latch_faults and not self.fault_latched:
            self.fault_latched = tuple(faults + waiting)
        if state != STARTING or faults or waiting or late:
            self.ready_since = None
        if state == ACTIVE and self.config.shadow_mode:
            state = SHADOW
        self.state = state
        if state not in _TORQUE_STATES:
            self.guard.reset()   # re-anchored when torque is sent again
            self.tau_left = self.tau_right = 0.0   # Immediate, not rate limited.
            return SafetyDecision(0.0, 0.0, True, tuple(reasons), state,
                                  self.config.shadow_mode)
        tau_v = self._drive_torque_now(now)
        tau_omega = self.inputs[YAW_TORQUE].value
        left, right = mix(tau_v, tau_omega, self.max_wheel_torque)
        step = self.max_wheel_torque_rate * dt
        self.tau_left = _toward(self.tau_left, left, step)
        self.tau_right = _toward(self.tau_right, right, step)
        return SafetyDecision(self.tau_left, self.tau_right, False, tuple(late), state,
                              self.config.shadow_mode)

    def _guard_step(self) -> None:
        """Feed the runaway guard the newest estimate and reference (once each)."""
        slot = self.inputs[ESTIMATE]
        if (not self.guard.config.enabled or self.runaway or not self._reference_fresh
                or slot.value is None or slot.invalid):
            return
        if slot.arrival == self._guard_estimate_time:
            return   # the same estimate as at the last step (a watchdog tick)
        self._reference_fresh = False
        self._guard_estimate_time = slot.arrival
        est = slot.value
        verdict = self.guard.update(slot.arrival, *self.pose, est.phi, est.v,
                                    *self.reference_position)
        if verdict:
            self.runaway = verdict

    def _drive_torque_now(self, now: float) -> float:
        """τυ of the MPC's last output at ``now``.

        Its plan's entry for the periods elapsed since it arrived (the last entry after the plan),
        or τυ itself without a plan.
        """
        slot = self.inputs[DRIVE_TORQUE]
        planned, period = self.drive_plan
        if not planned:
            return slot.value[0]
        elapsed = max(0.0, now - slot.arrival)
        return planned[min(len(planned) - 1, int(elapsed / period + TIME_TOLERANCE))]


def tilt_divergence_rate(params) -> float:
    """λ [1/s]: the unstable pole of model (1)'s tilt dynamics linearised upright.

    From (1) at θ = θ̇ = ω = 0 with the torque held: θ̈ ≈ (mv mp g l / Ω0) θ, Ω0 = mv Jθ −
    mp² l², so λ = sqrt(mv mp g l / Ω0). A held torque lets a tilt error grow like exp(λ t):
    ``bridge_time`` defaults to ln 4 / λ of the default robot.
    """
    mv, mp, l = params.effective_mass, params.body_mass, params.com_height  # noqa: E741 - the paper's symbol
    omega0 = mv * params.pitch_inertia - (mp * l) ** 2
    return math.sqrt(mv * mp * params.gravity * l / omega0)


def _toward(previous: float, target: float, step: float) -> float:
    """``target`` if within ``step`` of ``previous`` (exactly), else previous ± step."""
    if abs(target - previous) <= step:
        return target
    return previous + math.copysign(step, target - previous)


def _is_finite_number(value) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value))
