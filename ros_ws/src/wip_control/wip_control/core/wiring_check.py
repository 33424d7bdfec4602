"""Wiring checks at engage: the sensors of a real base compared with each other.

Pure numpy/math (no rclpy). The torque_mixer node feeds a :class:`WiringCheck` with the
base's wheel rates (``/joint_states`` after ``left_joint``/``right_joint`` and the wheel
signs), the body's pitch, pitch rate, yaw rate and specific force (``/imu/data`` after
``imu_mounting_rpy``) and the drive torque it sends; on a clear contradiction between them
it returns a :class:`Verdict` naming the parameter to change, with the numbers. The
safety layer (``core.safety.SafetyMonitor.wiring_fault``) then zeroes the torque, latched.

Three checks, each a contradiction that a correctly configured base cannot show:

Yaw (kinematic: wheels against gyro), any time
    On the ground without slip the yaw rate is ϕ̇ = r/d (φ̇r − φ̇l) (nonholonomic rolling;
    the same with encoders relative to the body: θ̇ cancels in the difference). With
    y = gyro ϕ̇, dw = r/d (φ̇r − φ̇l) and sw = r/d (φ̇r + φ̇l) of the CONFIGURED mapping:
    correct wiring gives dw = y; joints swapped (or both signs wrong) dw = −y; the left
    sign wrong sw = y; the right sign wrong sw = −y (a mirrored motor: a yaw torque
    gives the opposite yaw rate, and the drive torque spins the base). Verdict when,
    over a sliding ``window``, the mean |y| is at least ``min_yaw_rate`` (excitation),
    the configured mapping misses by at least 3/4 of it and an alternative fits within
    0.3 of it, for ``hold`` seconds.

Tilt (dynamic: drive torque against pitch response), the first ``tilt_check_time``
after engaging
    Eq. (1): θ̈ = fθ3(θ, ω, θ̇) + g3(θ) τυ + τd3, g3 < 0 (a forward drive torque tilts the
    body back). Integrated from the engagement (a difference of gyro rates: the gyro bias
    cancels, no differentiation of noise): Y = Δθ̇ − ∫ fθ3 dt against X = ∫ g3 τυ dt.
    Correct wiring: Y ≈ X (up to model error and disturbance); tilt sign wrong (IMU
    turned by π about z) or the drive mirrored (both wheels): Y ≈ −X, the controller
    then pushes the robot over. Verdict when |X| >= ``min_tilt_impulse`` and Y/X is
    within [−(k + 0.5), −0.5] for ``hold`` seconds, unless a
    single wheel explains Y better: one wheel mirrored makes the base's drive torque the
    commanded yaw torque (±τω), so Y ≈ ±X' with X' = ∫ g3 τω dt and Y/X is arbitrary;
    while |Y ∓ X'| < |Y + X|, or while the yaw check already sees a wheel wrong, the
    verdict is left to the yaw check, which names the wheel.
    The band: model (1) leaves out the reaction torque of a motor whose stator is fixed
    to the body, which makes the true g3 larger by k = 1 + m_v r / (m_p l) (1.5 with the
    default model; the full plant's g3); the mirrored response is thus −1 (no reaction)
    to −k (hub motors) times X, with 0.5 of model error either side.
    The check runs only the first ``tilt_check_time`` after engaging: a hard push later
    (Y dominated by τd3) must not look like a wiring fault (thresholds and measurements:
    docs/decisions/wiring-checks.md).

Gravity (accelerometer against the mounting), before the first engage
    At rest the specific force is +g along the body's up axis, within the tilt (a robot
    the controllers engage is within ``fall_threshold`` 0.35 rad of upright). An IMU
    upside down or turned by π/2 about x or y puts it on the wrong axis or sign: verdict
    when, with |a| in [0.5 g, 1.5 g] and the gyro still (|rate| < 0.5 rad/s), the angle
    from +z exceeds ``max_gravity_angle`` for ``hold`` seconds. Only until the first
    engage, not again after a reset: a robot lying on its bumper after a fall is at rest
    with gravity far from +z, which is no wiring fault, and nothing in the sensors tells
    it from a body held upright with a wrong mounting. The mounting was judged before
    that engage, and the tilt check judges it again at every engage.

Thresholds (defaults, derived; docs/decisions/wiring-checks.md has the measurements)
----------------------------------------------------------------------------------
``min_yaw_rate`` 0.25 rad/s: a consumer MEMS gyro's bias is below 0.05 rad/s and its
    noise std about 0.01 rad/s (a mean over 10 samples: 0.003); encoder-rate noise is
    smaller. The miss of a correct mapping is then <= 0.06 rad/s < 0.19 (3/4 of 0.25):
    margin 3; the miss of the right alternative <= 0.06 < 0.075 (0.3 of 0.25). The spin
    of a mirrored motor reaches it within about 0.1 s of engaging (the drive torque of
    balancing); the yaw of swapped joints (the yaw loop's sign reversed) grows from the
    first heading error and reaches it in about 0.3 s (measured on the stand-in base).
``min_tilt_impulse`` 0.1 rad/s: 10 gyro noise std of a consumer IMU (the difference of
    two samples, 0.014 rad/s) and 2.5x the integrated effect of a 30 % error of fθ3
    (≈ 21 θ rad/s² at θ = 0.05 rad, over 0.1 s: 0.03 rad/s); reached in about 0.05 s with
    the torques of engaging (g3 = −0.28 rad/s² per N m, τυ of several N m).
``window`` 0.05 s (10 samples at 200 Hz) and ``hold`` 0.03 s (6 samples) of a sustained
    contradiction: one bad sample or a short slip does not trip; a verdict comes about
    0.08 s after the excitation, inside the 0.5 s before a miswired robot falls (0.57 s
    measured with a wrong right_wheel_sign and no check).
"""

from __future__ import annotations

import collections
import dataclasses
import math
from typing import NamedTuple, Sequence

from wip_runtime.config import param
from .model import nominal_terms
from wip_description.params import ModelParams

#: Names of the parameters a verdict can point at (the eso and torque_mixer nodes').
LEFT_SIGN, RIGHT_SIGN, JOINTS, MOUNTING = ('left_wheel_sign', 'right_wheel_sign',
                                           'left_joint/right_joint', 'imu_mounting_rpy')
#: Relative misses of the yaw check (see the module docstring).
_YAW_MISS, _YAW_FIT = 0.75, 0.3
#: Model error either side of the mirrored tilt response −1 .. −k (the module docstring).
_TILT_MODEL_ERROR = 0.5
#: Specific force at rest accepted for the gravity check, in g.
_GRAVITY_RANGE = (0.5, 1.5)
#: Gyro rates [rad/s] below which the body counts as at rest for the gravity check.
_AT_REST_RATE = 0.5
#: Longest gap [s] between two IMU samples integrated as one step of the tilt check.
_MAX_STEP = 0.05


@dataclasses.dataclass(frozen=True)
class WiringCheckParams:
    """Tunables of the wiring checks (ROS section ``wiring_check`` of the torque_mixer)."""

    enabled: bool = param(True, '1', 'compare wheels, gyro, accelerometer and drive torque '
                          'at engage and zero the torque (latched) on a wiring contradiction '
                          '(wheel sign, joint names, IMU mounting); real time only')
    window: float = param(0.05, 's', 'yaw check: sliding window of the mean rates',
                          minimum=0.01, maximum=2.0)
    hold: float = param(0.03, 's', 'a contradiction must hold this long for a verdict',
                        minimum=0.0, maximum=2.0)
    min_yaw_rate: float = param(0.25, 'rad/s', 'yaw check: least mean |gyro yaw rate| over '
                                'the window (over gyro bias and noise) for a verdict',
                                minimum=0.0, exclusive_minimum=True, maximum=10.0)
    min_tilt_impulse: float = param(0.1, 'rad/s', 'tilt check: least |integral of g3 '
                                    'tau_v dt| since engaging for a verdict', minimum=0.0,
                                    exclusive_minimum=True, maximum=10.0)
    tilt_check_time: float = param(0.3, 's', 'tilt check: runs this long after engaging '
                                   '(0: off)', minimum=0.0, maximum=60.0)
    max_gravity_angle: float = param(1.0, 'rad', 'gravity check (before the first engage): '
                                     'angle of the measured gravity from the body z axis '
                                     'beyond which the IMU mounting is wrong', minimum=0.4,
                                     maximum=3.2)


def mirrored_tilt_band(params: ModelParams) -> tuple[float, float]:
    """Band of the tilt ratio Y/X [1] that a mirrored drive gives (the module docstring)."""
    reaction = 1.0 + params.effective_mass * params.wheel_radius / (
        params.body_mass * params.com_height)
    return -(reaction + _TILT_MODEL_ERROR), -_TILT_MODEL_ERROR


class Verdict(NamedTuple):
    """A wiring contradiction: the parameter to change, what to do, the numbers."""

    parameter: str
    message: str
    evidence: dict

    @property
    def reason(self) -> str:
        """One line for the safety layer's reasons and /diagnostics."""
        numbers = ', '.join(f'{k} {v:.3f}' if isinstance(v, float) else f'{k} {v}'
                            for k, v in self.evidence.items())
        return f'wiring: {self.parameter}: {self.message} ({numbers})'


class WiringCheck:
    """See the module docstring. Times [s] on one monotonic clock of the caller.

    Parameters
    ----------
    config : the tunables; params : the controllers' model (``model.*``);
    period : nominal sensor period [s] (sizes the window); configured : the current
    values of the hardware parameters (names as the node's), quoted in the messages.
    """

    def __init__(self, config: WiringCheckParams, params: ModelParams, period: float,
                 configured: dict | None = None) -> None:
        if not (math.isfinite(period) and period > 0.0):
            raise ValueError(f'WiringCheck: period must be finite and > 0, got {period!r}')
        self.config = config
        self.params = params
        self.period = float(period)
        self.configured = dict(configured or {})
        self.window = max(2, int(round(config.window / self.period)))
        self.tilt_band = mirrored_tilt_band(params)
        # Torque was sent once: the gravity check is over for good (kept by reset()).
        self.ever_engaged = False
        self.reset()

    def reset(self) -> None:
        """Forget everything (after a reset of the safety layer: checked afresh)."""
        self.verdict: Verdict | None = None
        self.wheel_rates: tuple[float, float] | None = None
        self.wheel_time = -math.inf
        self.tau_v = 0.0
        self.tau_omega = 0.0
        self.engaged_at: float | None = None
        # The yaw window's terms per sample [rad/s], a deque each (their sums are the
        # window's, added in order): |y|, |dw − y|, |dw + y|, |sw − y|, |sw + y|.
        self.yaw = tuple(collections.deque(maxlen=self.window) for _ in range(5))
        self.tilt: tuple | None = None   # (t, pitch_rate0, ∫fθ3, X, X', last t)
        self.since: dict[str, float] = {}   # check -> time its contradiction began
        # The margins seen (for /diagnostics): the last tilt ratio Y/X with enough
        # impulse, the largest relative yaw miss of the configured wheels with excitation.
        self.tilt_ratio: float | None = None
        self.yaw_worst_miss: float | None = None

    def summary(self) -> str:
        """Return the margins seen so far, one line (correct wiring: Y/X near 1, misses near 0)."""
        tilt = 'n/a' if self.tilt_ratio is None else f'{self.tilt_ratio:.2f}'
        yaw = 'n/a' if self.yaw_worst_miss is None else f'{self.yaw_worst_miss:.2f}'
        low, high = self.tilt_band
        return (f'tilt Y/X {tilt} (fault in [{low:.3g}, {high:.3g}]); '
                f'largest yaw miss {yaw} of the gyro rate (fault >= {_YAW_MISS:g})')

    @property
    def wants_gravity(self) -> bool:
        """Whether the gravity check still reads the specific force (no torque sent yet)."""
        return not self.ever_engaged

    # -- inputs -------------------------------------------------------------------------------
    def wheels(self, t: float, left_rate: float, right_rate: float) -> None:
        """Wheel rates [rad/s], positive rolling forward AS CONFIGURED (signs applied)."""
        if math.isfinite(left_rate) and math.isfinite(right_rate):
            self.wheel_rates = (float(left_rate), float(right_rate))
            self.wheel_time = float(t)

    def torque(self, t: float, tau_v: float, engaged: bool, tau_omega: float = 0.0) -> None:
        """Take the torques sent to the base now.

        The drive torque τυ = τl + τr and the yaw torque τω = τr − τl [N m] sent to the
        base now; ``engaged``: torque is being sent (the safety layer ACTIVE or DEGRADED,
        not shadow mode).
        """
        sent = engaged and math.isfinite(tau_v + tau_omega)
        self.tau_v = float(tau_v) if sent else 0.0
        self.tau_omega = float(tau_omega) if sent else 0.0
        if engaged and self.engaged_at is None:
            self.engaged_at = float(t)
            self.ever_engaged = True
        elif not engaged:
            self.engaged_at = None
            self.tilt = None

    def imu(self, t: float, pitch: float, pitch_rate: float, yaw_rate: float,
            accel: Sequence[float] | None = None) -> Verdict | None:
        """One IMU sample of the body (after the mounting).

        Pitch θ [rad], Euler rates θ̇, ϕ̇ [rad/s], specific force (x, y, z) [m/s²] in base_link or
        None. Runs the checks; the verdict (once found it stays until :meth:`reset`).
        """
        if self.verdict is not None or not self.config.enabled:
            return self.verdict
        # One sum first (NaN and inf propagate), each value only if it is not finite.
        if not (math.isfinite(pitch + pitch_rate + yaw_rate + (sum(accel) if accel else 0.0))
                or all(map(math.isfinite, (pitch, pitch_rate, yaw_rate, *(accel or ()))))):
            return None
        for name, verdict in (('yaw', self._yaw(t, yaw_rate)),
                              ('tilt', self._tilt(t, pitch, pitch_rate, yaw_rate)),
                              ('gravity', self._gravity(t, pitch_rate, yaw_rate, accel))):
            if verdict is None:
                self.since.pop(name, None)
                continue
            start = self.since.setdefault(name, t)
            if t - start >= self.config.hold - 1e-9:
                self.verdict = verdict
                return verdict
        return None

    # -- the checks ---------------------------------------------------------------------------
    def _yaw(self, t: float, yaw_rate: float) -> Verdict | None:
        gyro, configured, joints, left_sign, right_sign = self.yaw
        if self.wheel_rates is None or t - self.wheel_time > 4.0 * self.period:
            for terms in self.yaw:
                terms.clear()
            return None
        k = self.params.wheel_radius / self.params.track_width
        left, right = self.wheel_rates
        y, dw, sw = yaw_rate, k * (right - left), k * (right + left)
        gyro.append(abs(y))
        configured.append(abs(dw - y))
        joints.append(abs(dw + y))
        left_sign.append(abs(sw - y))
        right_sign.append(abs(sw + y))
        n = len(gyro)
        if n < self.window:
            return None
        excitation = sum(gyro) / n
        if excitation < self.config.min_yaw_rate:
            return None
        miss = {'configured': sum(configured) / n, JOINTS: sum(joints) / n,
                LEFT_SIGN: sum(left_sign) / n, RIGHT_SIGN: sum(right_sign) / n}
        relative = miss['configured'] / excitation
        if self.yaw_worst_miss is None or relative > self.yaw_worst_miss:
            self.yaw_worst_miss = relative
        if miss['configured'] < _YAW_MISS * excitation:
            return None
        suspect = min((h for h in miss if h != 'configured'), key=miss.get)
        if miss[suspect] > _YAW_FIT * excitation:
            return None
        evidence = {'mean |gyro yaw rate| [rad/s]': excitation,
                    'mean |wheel yaw rate - gyro| [rad/s]': miss['configured'],
                    'mean miss if ' + suspect + ' changed [rad/s]': miss[suspect]}
        return Verdict(suspect, self._yaw_advice(suspect), evidence)

    def _yaw_contradicted(self) -> bool:
        """Whether the recent samples show the gyro turning and the configured wheels missing it.

        The recent samples (even fewer than a window) show the gyro turning and the
        configured wheels missing it: the yaw check, not the tilt, has the cause.
        """
        gyro, configured = self.yaw[:2]
        if not gyro:
            return False
        n = len(gyro)
        excitation = sum(gyro) / n
        miss = sum(configured) / n
        return excitation >= self.config.min_yaw_rate and miss >= _YAW_MISS * excitation

    def _yaw_advice(self, suspect: str) -> str:
        c = self.configured
        if suspect == JOINTS:
            left, right = c.get('left_joint', '?'), c.get('right_joint', '?')
            ls, rs = c.get('left_wheel_sign', '?'), c.get('right_wheel_sign', '?')
            return (f'the wheels turn the robot the opposite way to the gyro: swap left_joint '
                    f'and right_joint with their signs (left_joint: {right!r}, right_joint: '
                    f'{left!r}, left_wheel_sign: {rs}, right_wheel_sign: {ls}); if the names '
                    'are right, both left_wheel_sign and right_wheel_sign are wrong')
        sign = c.get(suspect, '?')
        other = -sign if isinstance(sign, (int, float)) else '?'
        side = 'right' if suspect == RIGHT_SIGN else 'left'
        return (f'the {side} wheel turns the other way than configured (a mirrored motor): '
                f'set {suspect} to {other:g}' if isinstance(other, (int, float)) else
                f'the {side} wheel turns the other way than configured: flip {suspect}')

    def _tilt(self, t: float, pitch: float, pitch_rate: float,
              yaw_rate: float) -> Verdict | None:
        cfg = self.config
        if self.engaged_at is None or t - self.engaged_at > cfg.tilt_check_time:
            return None
        try:
            terms = nominal_terms(self.params, pitch, yaw_rate, pitch_rate)
        except (OverflowError, ValueError, ZeroDivisionError):
            return None     # rates beyond any physical value: the ESO checks report them
        if self.tilt is None:
            self.tilt = (t, pitch_rate, 0.0, 0.0, 0.0, t)
            return None
        t0, rate0, drift, impulse, yaw_impulse, last = self.tilt
        dt = min(max(0.0, t - last), _MAX_STEP)
        # Rectangle rule with the torque held since the last sample: what the base got.
        drift += terms.f3 * dt
        impulse += terms.g3 * self.tau_v * dt
        yaw_impulse += terms.g3 * self.tau_omega * dt
        self.tilt = (t0, rate0, drift, impulse, yaw_impulse, t)
        if abs(impulse) < cfg.min_tilt_impulse:
            return None
        response = (pitch_rate - rate0) - drift
        ratio = response / impulse
        self.tilt_ratio = ratio
        if not self.tilt_band[0] <= ratio <= self.tilt_band[1]:
            return None
        # One wheel sign wrong turns the yaw torque into the base's drive torque: the tilt
        # then contradicts too, with Y ≈ ±X' instead of −X. If that explains Y better, or
        # the yaw check already sees the wheels miss the gyro, the yaw check names the
        # wheel; wait for it (docs/decisions/wiring-checks.md).
        mirrored_drive = abs(response + impulse)
        one_wheel = min(abs(response - yaw_impulse), abs(response + yaw_impulse))
        if one_wheel < mirrored_drive or self._yaw_contradicted():
            return None
        mount = self.configured.get('imu_mounting_rpy')
        change = ''
        if isinstance(mount, (tuple, list)) and len(mount) == 3:
            yaw = mount[2] + math.pi if mount[2] <= 0.0 else mount[2] - math.pi
            change = (f' (imu_mounting_rpy: [{mount[0]:.4g}, {mount[1]:.4g}, '
                      f'{yaw:.4g}])')
        return Verdict(MOUNTING,
                       'the body tilts the way the drive torque should push it back: the '
                       'IMU and the wheels disagree on which way is forward; turn the IMU '
                       f'mounting by pi about z{change}, or, if the IMU is right, the wheels '
                       'are backwards (both wheel signs wrong, or left_joint/right_joint '
                       'swapped without their signs)',
                       {'time since engaging [s]': t - t0,
                        'predicted pitch rate change [rad/s]': impulse,
                        'measured [rad/s]': response, 'ratio': ratio})

    def _gravity(self, t: float, pitch_rate: float, yaw_rate: float,
                 accel: Sequence[float] | None) -> Verdict | None:
        if accel is None or not self.wants_gravity:
            return None
        ax, ay, az = (float(a) for a in accel)
        norm = math.sqrt(ax * ax + ay * ay + az * az)
        g = self.params.gravity
        if not (_GRAVITY_RANGE[0] * g <= norm <= _GRAVITY_RANGE[1] * g):
            return None
        if max(abs(pitch_rate), abs(yaw_rate)) > _AT_REST_RATE:
            return None
        angle = math.acos(max(-1.0, min(1.0, az / norm)))
        if angle <= self.config.max_gravity_angle:
            return None
        axis = max(range(3), key=lambda i: abs((ax, ay, az)[i]))
        along = ('-' if (ax, ay, az)[axis] < 0 else '+') + 'xyz'[axis]
        mount = self.configured.get('imu_mounting_rpy', '?')
        return Verdict(MOUNTING,
                       f'at rest gravity reads along base_link {along}, not +z: the IMU '
                       f'is mounted {"upside down" if along == "-z" else "on its side"} '
                       f'relative to imu_mounting_rpy {_angles(mount)}; correct its roll '
                       f'or pitch (by pi for -z, pi/2 for x or y)',
                       {'gravity angle from +z [rad]': angle,
                        'specific force x,y,z [m/s^2]':
                            f'{ax:.2f},{ay:.2f},{az:.2f}'})


def _angles(value) -> str:
    try:
        return '[' + ', '.join(f'{float(v):.4g}' for v in value) + ']'
    except (TypeError, ValueError):
        return repr(value)
