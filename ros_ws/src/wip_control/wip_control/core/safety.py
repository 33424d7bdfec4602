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

import numpy as np

from . import safety_rules as rules
from .compiled import array_slot, optional_slot, typed_slot
from .eso import StateEstimate
from .mixer import mix
from .position import TRACKING
from .runaway import RunawayParams, RunawayGuard
from .safety_config import SafetyParams, TIME_TOLERANCE
from .safety_rules import (ACTIVE, DEGRADED, DRIVE_INDEX, ESTIMATE, ESTIMATE_INDEX, ESTOP,
                           ESTOP_INDEX, FAULT, INPUTS, SHADOW, STARTING, STATES,
                           YAW_INDEX, YAW_TORQUE, DRIVE_TORQUE)
from .safety_texts import condition_texts

#: States in which the mixed torque is sent (to the base unless in shadow mode).
_TORQUE_STATES = (ACTIVE, DEGRADED, SHADOW)
_TORQUE_CODES = tuple(STATES.index(state) for state in _TORQUE_STATES)
_INDEX = {name: i for i, name in enumerate(INPUTS)}
#: Index of ε in a StateEstimate: inf at the start of the paper's ramp, not checked.
_EPSILON = StateEstimate._fields.index('epsilon')
_NO_PLAN = np.zeros(0)


class DriveStatus(enum.IntEnum):
    """Status of a drive torque: the values of the ``wip_msgs/DriveTorque`` constants."""

    SOLVED = rules.SOLVED
    FALLBACK_SHIFTED_PLAN = rules.FALLBACK_SHIFTED_PLAN
    FAILED_ZERO = rules.FAILED_ZERO
    INPUT_INVALID = rules.INPUT_INVALID
    NOT_READY = rules.NOT_READY


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


def _verdict(name: str, index: int, doc: str) -> property:
    """Return a latched verdict's property (a text or texts), flagged in the state array."""
    def get(self):
        return getattr(self, name)

    def put(self, value) -> None:
        setattr(self, name, value)
        self.numbers[index] = 1.0 if value else 0.0
    return property(get, put, doc=doc)


class SafetyMonitor:
    """State machine of the safety layer (docs/decisions/safety-layer.md).

    Feed each input as it arrives (:meth:`estimate`, :meth:`yaw_torque`,
    :meth:`drive_torque`, :meth:`invalid_input`, :meth:`estop`); call :meth:`update` once
    per control tick. Times are seconds of one monotonic clock of the caller's choice.
    The state is kept in a float64 array (``numbers``, the slots of ``safety_rules``), so
    that a compiled tick (:meth:`use_compiled`) and the interpreter share it.

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

    ticks = typed_slot('numbers', rules.TICKS, int, 'updates so far')
    last_update = optional_slot('numbers', rules.LAST_UPDATE, 'time of the last update [s]')
    ready_since = optional_slot('numbers', rules.READY_SINCE,
                                'since when every input is ready [s]')
    tau_left = array_slot('numbers', rules.TAU_LEFT,
                          'left wheel torque of the previous tick [N m]')
    tau_right = array_slot('numbers', rules.TAU_RIGHT,
                           'right wheel torque of the previous tick [N m]')
    settled = typed_slot('numbers', rules.SETTLED, bool, "the ESO's start-up flag")
    position_status = typed_slot('numbers', rules.POSITION_STATUS, int,
                                 'core.position NO_FIX ... FAULT of the last estimate')
    consecutive_fallbacks = typed_slot('numbers', rules.CONSECUTIVE_FALLBACKS, int,
                                       'MPC outputs in a row with FALLBACK_SHIFTED_PLAN')
    estop_latched = typed_slot('numbers', rules.ESTOP_LATCHED, bool,
                               'an e-stop latched until reset')
    heartbeat_at = optional_slot('numbers', rules.HEARTBEAT_AT,
                                 'when the last heartbeat arrived [s]')
    wiring = _verdict('_wiring', rules.WIRING,
                      'a wiring verdict (core.wiring_check): latched until reset()')
    runaway = _verdict('_runaway', rules.RUNAWAY,
                       "the runaway guard's verdict: latched until reset()")
    fault_latched = _verdict('_fault_latched', rules.FAULT_LATCHED,
                             'the faults latched (latch_faults) until reset()')

    def __init__(self, config: SafetyParams, max_wheel_torque: float,
                 max_wheel_torque_rate: float, period: float,
                 timing_checks: bool = True, runaway: RunawayParams | None = None) -> None:
        if not (math.isfinite(period) and period > 0.0):
            raise ValueError(f'SafetyMonitor: period must be finite and > 0, got {period!r}')
        self.numbers = np.zeros(rules.SIZE)
        self.numbers[[rules.LAST_UPDATE, rules.READY_SINCE, rules.HEARTBEAT_AT, rules.POSE_X,
                      rules.POSE_Y, rules.GUARD_ESTIMATE_TIME]] = math.nan
        self.numbers[rules.ARRIVAL:rules.ARRIVAL + len(INPUTS)] = math.nan
        self.numbers[rules.POSITION_STATUS] = TRACKING
        self.plan = _NO_PLAN                    # the MPC's planned τυ (drive_torque)
        self.period = float(period)
        self.timing_checks = bool(timing_checks)
        self.guard = RunawayGuard(runaway)
        self._config = config
        self.set_limits(max_wheel_torque, max_wheel_torque_rate)
        self.invalid_reasons = [''] * len(INPUTS)   # why each input's last message was bad
        self.estop_engaged = False      # the e-stop input says engaged now
        self.estop_true_at: float | None = None   # when an e-stop last said engaged
        self.fault_latched: tuple[str, ...] = ()
        self.wiring = ''
        self.runaway = ''
        self._kernel = None                      # the compiled tick (use_compiled)

    @property
    def config(self) -> SafetyParams:
        """The safety tunables."""
        return self._config

    @config.setter
    def config(self, config: SafetyParams) -> None:
        self._config = config
        self._make_constants()

    @property
    def state(self) -> str:
        """One of :data:`STATES`."""
        return STATES[int(self.numbers[rules.STATE])]

    @state.setter
    def state(self, state: str) -> None:
        self.numbers[rules.STATE] = STATES.index(state)

    # -- limits ----------------------------------------------------------------------------
    def set_limits(self, max_wheel_torque: float, max_wheel_torque_rate: float) -> None:
        """Change τmax [N·m] and the rate limit [N·m/s] (both finite and > 0)."""
        for name, value in (('max_wheel_torque', max_wheel_torque),
                            ('max_wheel_torque_rate', max_wheel_torque_rate)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
                raise ValueError(f'SafetyMonitor: {name} must be finite and > 0, got {value!r}')
        self.max_wheel_torque = float(max_wheel_torque)
        self.max_wheel_torque_rate = float(max_wheel_torque_rate)
        self._make_constants()

    def _make_constants(self) -> None:
        self.constants = np.array(rules.constants(
            self._config, self.max_wheel_torque, self.max_wheel_torque_rate,
            self.timing_checks, self.guard.config.enabled))

    # -- inputs ------------------------------------------------------------------------------
    def _accept(self, index: int, t: float) -> None:
        n = self.numbers
        n[rules.ARRIVAL + index] = t
        n[rules.INVALID + index] = 0.0
        self.invalid_reasons[index] = ''

    def invalid_input(self, name: str, t: float, reason: str) -> None:
        """Take an unusable message of input ``name`` (e.g. failed to convert).

        It is a fault until the next valid one; the last valid value is kept but not used.
        """
        index = _INDEX[name]
        self.invalid_reasons[index] = reason or 'invalid'
        self.numbers[rules.INVALID + index] = 1.0

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
        self._accept(ESTIMATE_INDEX, t)
        numbers = self.numbers
        numbers[rules.ESTIMATE_VALUES:] = values
        numbers[rules.SETTLED] = 1.0 if settled else 0.0
        numbers[rules.POSITION_STATUS] = int(position_status)
        numbers[rules.POSE_X], numbers[rules.POSE_Y] = float(x), float(y)

    def reference(self, t: float, x: float, y: float) -> None:
        """Take the reference position (x_r, y_r) [m] received at ``t`` [s] (runaway guard)."""
        if _is_finite_number(x) and _is_finite_number(y):
            n = self.numbers
            n[rules.REFERENCE_X], n[rules.REFERENCE_Y] = float(x), float(y)
            n[rules.REFERENCE_FRESH] = 1.0

    def yaw_torque(self, t: float, tau_omega: float) -> None:
        """τω [N·m] of the ARC, received at ``t`` [s]."""
        if not _is_finite_number(tau_omega):
            self.invalid_input(YAW_TORQUE, t, f'non-finite yaw torque {tau_omega!r}')
            return
        self._accept(YAW_INDEX, t)
        self.numbers[rules.YAW_TAU] = tau_omega

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
        n = self.numbers
        self.plan = np.array(planned) if planned else _NO_PLAN
        n[rules.PLAN_LENGTH] = len(planned)
        n[rules.PLAN_PERIOD] = float(plan_period) if planned else 0.0
        n[rules.CONSECUTIVE_FALLBACKS] = (n[rules.CONSECUTIVE_FALLBACKS] + 1.0
                                          if status == DriveStatus.FALLBACK_SHIFTED_PLAN
                                          else 0.0)
        self._accept(DRIVE_INDEX, t)
        n[rules.DRIVE_TAU] = tau_v
        n[rules.DRIVE_STATUS] = int(status)

    def estop(self, t: float, engaged: bool) -> None:
        """Take an e-stop message received at ``t`` [s].

        Engaged latches the e-stop; not engaged only allows a later :meth:`reset` (and is
        the heartbeat if ``max_estop_age`` > 0).
        """
        self._accept(ESTOP_INDEX, t)
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
        arrivals = self.numbers[rules.ARRIVAL:rules.ARRIVAL + len(INPUTS)].tolist()
        return {name: None if math.isnan(arrival) else now - arrival
                for name, arrival in zip(INPUTS, arrivals)}

    def use_compiled(self) -> str:
        """Take the steady ticks with the compiled kernel (``safety_kernel.py``).

        The kernel is compared with the interpreter on scratch monitors of the same
        settings first. Return '' when it is used, else why not. The decisions are the
        same floats either way.
        """
        from .compiled import load_checked, SAFETY_KERNEL
        module, difference = load_checked(SAFETY_KERNEL, lambda m: m.difference(self._scratch))
        if difference:
            return f'the compiled safety tick differs from the interpreted one {difference}'
        self._kernel = module.tick
        return ''

    def _scratch(self) -> 'SafetyMonitor':
        """Return a new monitor of the same settings."""
        return SafetyMonitor(self._config, self.max_wheel_torque, self.max_wheel_torque_rate,
                             self.period, self.timing_checks, self.guard.config)

    def update(self, now: float) -> SafetyDecision:
        """Return the torques of the tick at ``now`` [s] (one call per control tick)."""
        if self._kernel is not None:
            # The steady tick (a torque state, no condition), the guard's step only (with
            # a runaway found: its text is made here), or nothing changed.
            guard = self.guard
            status, tau_left, tau_right = self._kernel(
                now, self.numbers, self.constants, self.plan, guard.state, guard.history,
                guard.constants)
            if status == rules.TICK_TAKEN:
                return SafetyDecision(tau_left, tau_right, False, (), self.state,
                                      self._config.shadow_mode)
            if status == rules.RUNAWAY_FOUND:
                self.runaway = guard.verdict()
        if self.timing_checks and self.numbers[rules.STATE] in _TORQUE_CODES:
            self._guard_step()
        return self._interpreted_update(now)

    def _interpreted_update(self, now: float) -> SafetyDecision:
        n = self.numbers
        ticks = self.ticks + 1
        n[rules.TICKS] = ticks
        last = self.last_update
        dt = self.period if last is None else max(0.0, now - last)
        n[rules.LAST_UPDATE] = now
        values, c = n.tolist(), self.constants.tolist()
        codes = rules.condition_codes(now, dt, ticks, values, c)
        faults, waiting, late = (condition_texts(self, codes, now, dt, values, c) if codes
                                 else ([], [], []))
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
            n[rules.TAU_LEFT] = n[rules.TAU_RIGHT] = 0.0   # Immediate, not rate limited.
            return SafetyDecision(0.0, 0.0, True, tuple(reasons), state,
                                  self.config.shadow_mode)
        tau_v = rules.drive_torque_now(now, values, self.plan.tolist())
        left, right = mix(tau_v, values[rules.YAW_TAU], self.max_wheel_torque)
        step = self.max_wheel_torque_rate * dt
        tau_left = rules.toward(values[rules.TAU_LEFT], left, step)
        tau_right = rules.toward(values[rules.TAU_RIGHT], right, step)
        n[rules.TAU_LEFT], n[rules.TAU_RIGHT] = tau_left, tau_right
        return SafetyDecision(tau_left, tau_right, False, tuple(late), state,
                              self.config.shadow_mode)

    def _guard_step(self) -> None:
        """Feed the runaway guard the newest estimate and reference (once each)."""
        if rules.guard_due(self.numbers, self.constants):
            self.guard.make_room()
            guard = self.guard
            if rules.step_guard(self.numbers, guard.state, guard.history,
                                guard.constants_list):
                self.runaway = guard.verdict()


def tilt_divergence_rate(params) -> float:
    """λ [1/s]: the unstable pole of model (1)'s tilt dynamics linearised upright.

    From (1) at θ = θ̇ = ω = 0 with the torque held: θ̈ ≈ (mv mp g l / Ω0) θ, Ω0 = mv Jθ −
    mp² l², so λ = sqrt(mv mp g l / Ω0). A held torque lets a tilt error grow like exp(λ t):
    ``bridge_time`` defaults to ln 4 / λ of the default robot.
    """
    mv, mp, l = params.effective_mass, params.body_mass, params.com_height  # noqa: E741 - the paper's symbol
    omega0 = mv * params.pitch_inertia - (mp * l) ** 2
    return math.sqrt(mv * mp * params.gravity * l / omega0)


def _is_finite_number(value) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value))
