"""Fit the identifiable parameters of the paper's model (1) to a recorded run.

    scripts/identify BAG_OR_RECORD [--out FILE] [--write-params] [--params-file FILE]
                     [--source SOURCE] [--model auto|paper|full]

Model (1) of Yue, An, Li (2016), written in its Euler-Lagrange form (the paper plant of
wip_sim/core/plant.py, multiplied out; τυ = τl + τr, τω = τr − τl, REP 103)::

    m_v υ̇ + m_p l (cosθ θ̈ − sinθ θ̇²)         [+ 2 b (υ/r − θ̇) / r] = τυ / r
    m_p l (cosθ υ̇ − g sinθ) + J_θ θ̈ − m_p l² sinθ cosθ ω²           = 0
    J_ϕ ω̇ + m_p l² (sin²θ ω̇ + sin2θ θ̇ ω)           [+ (d/r) b d ω / r] = (d / r) τω

with b the wheels' viscous axle friction (``--friction``; a torque −b × the wheel's rate
against the body, as wip_sim/core/plant.py's ``wheel_friction``) and, also with
``--friction``, the rolling resistance F_rr (a ground torque on each wheel against its
rolling: forward and yaw rows only),

linear in p = (m_v, m_p l, J_θ, m_p l², J_ϕ [, b, F_rr]) with r, d and g known. The three
rows are stacked and solved by weighted linear least squares on low-pass-filtered
signals, outliers left out; see docs/identification.md for the regressors, the method,
the assumptions and the limits. Reads a rosbag2 directory (or .mcap) through
wip_tools.report.record_from_bag, a robot's sensors with its wiring
(:mod:`wip_tools.run_wiring`), or a record saved as timeseries.npz (scripts/simulate
--out). Exit codes: wip_control.tools.cli.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import pathlib
import sys
from typing import Iterable, Mapping

import numpy as np

from wip_control.core.params import WipParameters
from wip_control.tools.cli import add_exit_codes, EXIT_OK, EXIT_USAGE, exit_with

#: The fitted parameters, in the column order of the regressor matrix.
NAMES = ('effective_mass', 'mpl', 'pitch_inertia', 'mpl2', 'yaw_inertia_total', 'friction',
         'rolling_resistance')
SYMBOLS = {'effective_mass': 'm_v [kg]', 'mpl': 'm_p l [kg m]',
           'pitch_inertia': 'J_theta [kg m^2]', 'mpl2': 'm_p l^2 [kg m^2]',
           'yaw_inertia_total': 'J_phi [kg m^2]', 'friction': 'b [N m s/rad]',
           'rolling_resistance': 'F_rr [N]', 'com_height': 'l = m_p l^2 / m_p l [m]'}
#: The friction columns (``friction=True``): viscous axle friction b, rolling resistance.
FRICTION = ('friction', 'rolling_resistance')
#: Wheel ground speed [m/s] at which the rolling resistance's sign is tanh(1) = 0.76 of its
#: full value: a smooth sign, so that encoder noise about a standstill does not toggle it.
SIGN_SPEED = 0.02
#: Low-pass [Hz] of the wheel speeds whose sign the rolling resistance takes (the raw speed
#: from quantised encoders is noisy to about 0.05 m/s at 200 Hz).
SIGN_CUTOFF_HZ = 5.0
#: Smallest RMS excitation [SI] of a regressor signal that counts (about what an IMU and
#: the wheel encoders resolve after the filter): below it the column is noise.
MIN_EXCITATION = {'v_dot': 0.02, 'theta_ddot': 0.02, 'omega_dot': 0.02, 'omega_sq': 0.005}
#: Low-pass cut-off [Hz] (Gaussian, zero phase). The regressors hold differentiated
#: measurements, whose noise power grows as fc³ while the excitation run's content is below
#: about 0.5 Hz (a 20 s lap, the speed varying twice a lap); noise in a regressor biases
#: least squares towards zero (errors in variables). With an IMU's noise (0.002 rad,
#: 0.01 rad/s) 4 Hz gave m_v 10 % low from the sensors, 1 Hz within 1.5 %
#: (docs/identification.md §5).
CUTOFF_HZ = 1.0
#: A sample whose filtered residual in any row is beyond this many robust standard
#: deviations (1.4826 × the median absolute residual) is left out of the fit.
REJECT_SIGMAS = 5.0
MAX_CONDITION = 1e4         #: of the column-scaled, weighted regressor matrix
MAX_RELATIVE_CI = 0.05      #: 95 % half-width / |value| above which a value is not given
MIN_DURATION_S = 5.0
#: A gap between two samples of a stream longer than this many sample periods (a stalled
#: driver, a lost message burst) is not interpolated across: the rows whose filter window
#: reaches into it are left out.
MAX_GAP_PERIODS = 3.0
Z95 = 1.96


class IdentifyError(ValueError):
    """Bad input: the message is one line."""


@dataclasses.dataclass
class Estimate:
    name: str
    value: float | None          # None: not determined
    half_width: float | None     # 95 % confidence half-width
    reason: str = ''             # why not determined


@dataclasses.dataclass
class Identification:
    estimates: dict[str, Estimate]
    condition: float
    residual_rms: dict[str, float]   # per equation, in its own units (N, N m, N m)
    samples: int
    source: str
    #: Fraction of the samples left out as outliers (REJECT_SIGMAS).
    rejected: float = 0.0

    def value(self, name: str) -> float | None:
        return self.estimates[name].value


def _kernel_half(dt: float, cutoff_hz: float) -> tuple[float, int]:
    """(σ [s], half-width [samples]) of :func:`gaussian_lowpass`'s kernel."""
    sigma_t = math.sqrt(math.log(2.0)) / (2.0 * math.pi * cutoff_hz)   # |H| = 1/√2 at fc
    return sigma_t, max(1, int(math.ceil(4.0 * sigma_t / dt)))


def gaussian_lowpass(x: np.ndarray, dt: float, cutoff_hz: float = CUTOFF_HZ) -> np.ndarray:
    """Zero-phase low-pass: convolution with a Gaussian.

    The Gaussian's −3 dB point is ``cutoff_hz``. It is pure numpy, with a symmetric kernel
    so that there is no phase lag between regressors and torques.
    """
    sigma_t, half = _kernel_half(dt, cutoff_hz)
    k = np.exp(-0.5 * (np.arange(-half, half + 1) * dt / sigma_t) ** 2)
    k /= k.sum()
    return np.convolve(x, k, mode='same')


def _sensor_group(record: Mapping, wheel_radius: float,
                  encoders_relative_to_body: bool) -> dict[str, np.ndarray]:
    """(t, θ, θ̇, υ, ω) from what the sensors said.

    The IMU's pitch, its pitch and yaw rates (gyro), and υ = r (φ̇ + θ̇) from the mean wheel joint
    angle φ (a joint angle is measured against the body, so the body's tilt rate is added back;
    without it when the encoders measure rolling angles). φ̇ by central differences: the
    regressors' low-pass removes what that amplifies.
    """
    encoders = record['encoders'] if 'encoders' in record else None
    imu = record['imu'] if 'imu' in record else None
    if encoders is None or imu is None or len(encoders['t']) < 3 or len(imu['t']) < 3:
        raise IdentifyError('no sensor samples (a JointState topic naming both wheel '
                            'joints, and an Imu topic with orientation and angular '
                            'velocity)')
    t = np.asarray(imu['t'], dtype=float)
    mean_angle = np.interp(t, encoders['t'], 0.5 * (np.asarray(encoders['left'])
                                                   + np.asarray(encoders['right'])))
    if len(t) < 3 or not np.all(np.diff(t) > 0.0):
        raise IdentifyError('imu time stamps do not increase')
    pitch_rate = np.asarray(imu['pitch_rate'], dtype=float)
    rolling_rate = np.gradient(mean_angle, t)
    if encoders_relative_to_body:
        rolling_rate = rolling_rate + pitch_rate
    return {'t': t, 'theta': imu['pitch'], 'theta_dot': pitch_rate,
            'v': wheel_radius * rolling_rate, 'omega': imu['yaw_rate']}


def motor_lagged(torque: np.ndarray, dt: float, time_constant: float) -> np.ndarray:
    """Mean torque over each interval of a first-order motor lag behind ``torque``.

    ``torque[k]`` is the command held over [t_k, t_k + dt); the motor's torque a relaxes
    towards it as c + (a₀ − c) e^(−t/T). Returns each interval's mean, the torque the
    plant felt (the same form as wip_sim's ``plant.motor_time_constant``).
    """
    if time_constant <= 0.0:
        return torque
    decay = math.exp(-dt / time_constant)
    mean = time_constant / dt * (1.0 - decay)
    out = np.empty_like(torque)
    applied = 0.0
    for k, command in enumerate(torque.tolist()):
        out[k] = command + (applied - command) * mean
        applied = command + (applied - command) * decay
    return out


def _signals(record: Mapping, source: str, wheel_radius: float = WipParameters().wheel_radius,
             encoders_relative_to_body: bool = True,
             motor_lag: float = 0.0) -> dict[str, np.ndarray]:
    """Uniformly sampled (t, θ, θ̇, υ, ω, τl, τr) from the record's ``source`` group.

    truth: the torques of row k were applied over [t_{k−1}, t_k) (wip_sim/core/runner.py), so they
    are shifted back one row to pair with the interval they acted over. estimate and
    sensors: the torques come from the wheels group (applied from its stamp on),
    interpolated.
    """
    if source == 'sensors':
        group = _sensor_group(record, wheel_radius, encoders_relative_to_body)
        streams = [record['encoders']['t'], record['imu']['t']]
    else:
        group = record[source] if source in record else None
        streams = [group['t']] if group is not None else []
    if group is None or len(group['t']) == 0:
        raise IdentifyError(f'no {source} samples (topic /wip/ground_truth or '
                            '/wip/state_estimate missing)')
    t = np.asarray(group['t'], dtype=float)
    if source == 'truth':
        tl, tr = np.asarray(group['tau_left'])[1:], np.asarray(group['tau_right'])[1:]
        tl, tr = np.append(tl, tl[-1:]), np.append(tr, tr[-1:])
    else:
        wheels = record['wheels'] if 'wheels' in record else None
        if wheels is None or len(wheels['t']) < 2:
            raise IdentifyError('no wheel torques (topic /wip/wheel_torques missing)')
        streams.append(wheels['t'])
        idx = np.clip(np.searchsorted(wheels['t'], t, side='right') - 1, 0,
                      len(wheels['t']) - 1)
        tl, tr = np.asarray(wheels['tau_left'])[idx], np.asarray(wheels['tau_right'])[idx]
    cols = {'theta': group['theta'], 'theta_dot': group['theta_dot'], 'v': group['v'],
            'omega': group['omega'], 'tau_left': tl, 'tau_right': tr}
    if source != 'truth':
        # Only while the controllers drove the wheels: between the first and the last
        # non-zero torque, within the torques' record. Before it a robot is held (a hand's
        # forces are not in the model; a stand-in base is frozen), after it it is stopped
        # or caught; outside the record the torque is not known.
        w_t = np.asarray(wheels['t'], dtype=float)
        driven = (np.asarray(tl) != 0.0) | (np.asarray(tr) != 0.0)
        active = np.flatnonzero(driven & (t >= w_t[0]) & (t <= w_t[-1]))
        span = slice(active[0], active[-1] + 1) if len(active) else slice(0, 0)
        t = t[span]
        cols = {name: np.asarray(values)[span] for name, values in cols.items()}
    if len(t) < 3 or t[-1] - t[0] < MIN_DURATION_S:
        raise IdentifyError(f'too little data: {len(t)} samples over '
                            f'{max(0.0, t[-1] - t[0]) if len(t) else 0.0:.2f} s '
                            f'(at least {MIN_DURATION_S:g} s needed)')
    dt = float(np.median(np.diff(t)))
    if not dt > 0.0:
        raise IdentifyError(f'{source} time stamps do not increase')
    grid = np.arange(t[0], t[-1] + 0.5 * dt, dt)
    out = {'t': grid, 'dt': np.array(dt)}
    for name, values in cols.items():
        values = np.asarray(values, dtype=float)
        if not np.all(np.isfinite(values)):
            raise IdentifyError(f'{source}.{name} has non-finite values')
        out[name] = np.interp(grid, t, values) if len(grid) != len(t) or \
            not np.allclose(grid, t) else values
    for name in ('tau_left', 'tau_right'):
        out[name] = motor_lagged(out[name], dt, motor_lag)
    out['valid'] = _without_gaps(grid, streams, MAX_GAP_PERIODS * dt)
    return out


def _without_gaps(grid: np.ndarray, streams: Iterable[np.ndarray], gap: float) -> np.ndarray:
    """Whether each grid time lies between two samples of every stream at most ``gap`` apart."""
    valid = np.ones(len(grid), dtype=bool)
    for t in streams:
        t = np.asarray(t, dtype=float)
        if len(t) < 2:
            continue
        i = np.clip(np.searchsorted(t, grid, side='right'), 1, len(t) - 1)
        valid &= (t[i] - t[i - 1] <= gap) | (grid < t[0]) | (grid > t[-1])
    return valid


def regressors(sig: Mapping[str, np.ndarray], params: WipParameters,
               cutoff_hz: float = CUTOFF_HZ,
               model: str = 'paper') -> tuple[np.ndarray, np.ndarray, dict]:
    """Rows (A, y) of the three equations, each of n rows, stacked (3n × 7, 3n).

    ``model='full'``: the rows of the full plant (wip_sim/core/plant.py) instead of (1): the
    centrifugal −m_p l sinθ ω² in the forward row, the motor reaction −τυ on the right of
    the pitch row, the Coriolis m_p l sinθ υ ω in the yaw row and the yaw gain d/(2r).

    Derivatives are forward differences over one sample interval (the torque held over it
    is the one paired), the other signals are the interval's midpoints. Each column of
    A and y is then low-pass filtered with the same zero-phase filter: the equations are
    linear in p, so F(A) p = F(y) holds exactly where A p = y did; only noise is removed.
    """
    dt = float(sig['dt'])
    th, thd, v, om = (np.asarray(sig[k]) for k in ('theta', 'theta_dot', 'v', 'omega'))
    mid = lambda x: 0.5 * (x[1:] + x[:-1])  # noqa: E731
    vd, thdd, omd = np.diff(v) / dt, np.diff(thd) / dt, np.diff(om) / dt
    th, thd, v, om = mid(th), mid(thd), mid(v), mid(om)
    tau_v = (sig['tau_left'] + sig['tau_right'])[:-1]
    tau_w = (sig['tau_right'] - sig['tau_left'])[:-1]
    s, c = np.sin(th), np.cos(th)
    g, r, d = params.gravity, params.wheel_radius, params.track_width
    z = np.zeros_like(th)
    # Rolling resistance F_rr [N] (both wheels, equal loads): a ground torque on each wheel
    # against its rolling, F_rr r/2 · sgn(wheel ground speed). It acts on the wheels from
    # the ground, so unlike the motors and the axle friction it has no reaction on the body:
    # no pitch-row term.
    v_smooth = gaussian_lowpass(v, dt, SIGN_CUTOFF_HZ)
    om_smooth = gaussian_lowpass(om, dt, SIGN_CUTOFF_HZ)
    sign_l = np.tanh((v_smooth - 0.5 * d * om_smooth) / SIGN_SPEED)
    sign_r = np.tanh((v_smooth + 0.5 * d * om_smooth) / SIGN_SPEED)
    # Columns: m_v, m_p l, J_θ, m_p l², J_ϕ, b, F_rr.
    full = 1.0 if model == 'full' else 0.0
    yaw_gain = d / (r * (2.0 if full else 1.0))
    # Axle friction b acts as the motors do: τυ loses 2b (υ/r − θ̇) and τω loses b d ω / r
    # (wip_sim/core/plant.py); moved to the left, those are b's columns in each row.
    slip_v = 2.0 * (v / r - thd)
    lon = np.stack([vd, c * thdd - s * (thd ** 2 + full * om ** 2), z, z, z, slip_v / r,
                    0.5 * (sign_l + sign_r)], axis=1)
    pitch = np.stack([z, c * vd - g * s, thdd, -s * c * om ** 2, z, -full * slip_v, z],
                     axis=1)
    yaw = np.stack([z, full * s * v * om, z, s * s * omd + 2.0 * s * c * thd * om, omd,
                    yaw_gain * d * om / r, 0.5 * yaw_gain * r * (sign_r - sign_l)], axis=1)
    ys = (tau_v / r, -full * tau_v, yaw_gain * tau_w)
    # Rows whose filter window reaches a gap in the data are left out (after filtering:
    # the filter needs the uniform grid).
    valid = np.asarray(sig.get('valid', np.ones(len(sig['t']), dtype=bool)))
    bad = ~(valid[1:] & valid[:-1])
    half = _kernel_half(dt, cutoff_hz)[1]
    keep_rows = np.convolve(bad.astype(float), np.ones(2 * half + 1), mode='same') == 0.0
    blocks, outs = [], []
    for a, y in zip((lon, pitch, yaw), ys):
        af = np.stack([gaussian_lowpass(a[:, j], dt, cutoff_hz) for j in range(a.shape[1])],
                      axis=1)
        yf = gaussian_lowpass(y, dt, cutoff_hz)
        # Drop the filter's edges (the kernel runs off the record there).
        edge = min(len(yf) // 4, int(math.ceil(1.0 / (cutoff_hz * dt))))
        rows = keep_rows[edge:len(yf) - edge]
        blocks.append(af[edge:len(af) - edge][rows])
        outs.append(yf[edge:len(yf) - edge][rows])
    excitation = {'v_dot': _rms(gaussian_lowpass(vd, dt, cutoff_hz)),
                  'theta_ddot': _rms(gaussian_lowpass(thdd, dt, cutoff_hz)),
                  'omega_dot': _rms(gaussian_lowpass(omd, dt, cutoff_hz)),
                  'omega_sq': _rms(s * c * om ** 2)}
    return np.vstack(blocks), np.concatenate(outs), excitation


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else 0.0


def _has(record: Mapping, group: str) -> bool:
    return group in record and len(record[group]['t']) > 0


def _best_source(record: Mapping) -> str:
    """Return the best source of the signals.

    truth (a simulation's), else the sensors, else the state estimate (which the ESOs'
    lag and filtering bias: docs/identification.md).
    """
    if _has(record, 'truth'):
        return 'truth'
    if _has(record, 'encoders') and _has(record, 'imu'):
        return 'sensors'
    return 'estimate'


def identify(record: Mapping, params: WipParameters | None = None, source: str = 'auto',
             friction: bool = False, cutoff_hz: float = CUTOFF_HZ,
             model: str = 'paper', encoders_relative_to_body: bool = True,
             motor_lag: float = 0.0) -> Identification:
    """Fit p = (m_v, m_p l, J_θ, m_p l², J_ϕ[, b]) of eq. (1) to ``record``.

    ``params`` supplies the known r, d, g (default: the nominal ones). ``source``:
    'truth', 'sensors', 'estimate' or 'auto' (the first the record has, in that order).
    ``model``: fit the rows of eq. (1) ('paper') or of the full plant ('full', see
    :func:`regressors`). ``encoders_relative_to_body``: the wheel joint angles are measured
    against the body (a robot's joints), not against the ground. ``motor_lag`` [s]: the
    torques recorded are commands that the motors follow with this first-order lag.
    """
    if model not in ('paper', 'full'):
        raise IdentifyError(f"model {model!r}: expected 'paper' or 'full'")
    params = WipParameters() if params is None else params
    if source == 'auto':
        source = _best_source(record)
    if not (math.isfinite(motor_lag) and 0.0 <= motor_lag <= 1.0):
        raise IdentifyError(f'motor lag {motor_lag!r} s: expected 0 to 1 s')
    sig = _signals(record, source, params.wheel_radius, encoders_relative_to_body, motor_lag)
    a, y, excitation = regressors(sig, params, cutoff_hz, model)
    n = len(y) // 3
    if n < 10:
        raise IdentifyError(f'too little data after filtering: {n} samples')
    used = list(range(7 if friction else 5))
    a = a[:, used]
    names = [NAMES[j] for j in used]
    # Which columns carry enough excitation (physical floors, MIN_EXCITATION).
    why: dict[str, str] = {}
    if excitation['v_dot'] < MIN_EXCITATION['v_dot']:
        why['effective_mass'] = (f'forward acceleration RMS {excitation["v_dot"]:.3g} m/s^2 '
                                 f'< {MIN_EXCITATION["v_dot"]}')
    if excitation['theta_ddot'] < MIN_EXCITATION['theta_ddot']:
        why['pitch_inertia'] = why['mpl'] = (
            f'tilt acceleration RMS {excitation["theta_ddot"]:.3g} rad/s^2 '
            f'< {MIN_EXCITATION["theta_ddot"]}')
    if excitation['omega_dot'] < MIN_EXCITATION['omega_dot']:
        why['yaw_inertia_total'] = (f'yaw acceleration RMS {excitation["omega_dot"]:.3g} '
                                    f'rad/s^2 < {MIN_EXCITATION["omega_dot"]}')
    if excitation['omega_sq'] < MIN_EXCITATION['omega_sq']:
        why['mpl2'] = (f'turning at a tilt too small (RMS sinθcosθω² '
                       f'{excitation["omega_sq"]:.3g} < {MIN_EXCITATION["omega_sq"]})')
    if 'effective_mass' in why:
        for name in FRICTION:
            why.setdefault(name, why['effective_mass'])
    keep = [j for j, name in enumerate(names)
            if name not in why and np.any(a[:, j] != 0.0)]
    estimates = {name: Estimate(name, None, None, why.get(name, 'no excitation'))
                 for name in names}
    residual_rms = {'forward': math.nan, 'pitch': math.nan, 'yaw': math.nan}
    condition = math.inf
    # A column left out is not dropped (that would bias the others by its term) but fixed
    # at its nominal value and moved to the right-hand side; m_p l² at (m_p l)·l_nominal
    # once m_p l is fitted (its term is small: sin²θ, sinθ cosθ).
    nominal = true_values(params)
    fixed = [j for j in range(len(names)) if j not in keep]
    y = y - a[:, fixed] @ np.array([nominal[names[j]] for j in fixed]) if fixed else y
    if keep and 3 in fixed and 1 in keep:
        sol, *_ = np.linalg.lstsq(a[:, keep], y, rcond=None)
        mpl2_fixed = float(sol[keep.index(1)]) * params.com_height
        y = y - a[:, 3] * (mpl2_fixed - nominal['mpl2'])
    inlier = np.ones(n, dtype=bool)
    if keep:
        # Passes: ordinary LS, then each equation weighted by 1/its residual RMS (the rows
        # are in different units: N, N·m, N·m), then twice without the samples whose
        # residual in any row is beyond REJECT_SIGMAS robust standard deviations (what the
        # model does not describe: a hand, a bump, a stalled driver's aftermath).
        w = np.ones(3)
        for pass_ in range(4):
            rows = np.tile(inlier, 3)
            aw = (a[:, keep] * np.repeat(w, n)[:, None])[rows]
            yw = (y * np.repeat(w, n))[rows]
            scale = np.linalg.norm(aw, axis=0)
            scale[scale == 0.0] = 1.0
            sol, *_ = np.linalg.lstsq(aw / scale, yw, rcond=None)
            p = sol / scale
            res = y - a[:, keep] @ p
            blocks = [res[i * n:(i + 1) * n] for i in range(3)]
            rms = np.array([_rms(b[inlier]) for b in blocks])
            floor = max(1e-12, 1e-9 * _rms(y))
            w = 1.0 / np.maximum(rms, floor)
            if pass_ >= 1:
                sigma = [1.4826 * float(np.median(np.abs(b[inlier]))) for b in blocks]
                inlier = np.all([np.abs(b) <= REJECT_SIGMAS * max(sd, floor)
                                 for b, sd in zip(blocks, sigma)], axis=0)
                if inlier.sum() < max(10, n // 2):     # not outliers: the model is wrong
                    inlier = np.ones(n, dtype=bool)
        condition = float(np.linalg.cond(aw / scale))
        residual_rms = dict(zip(('forward', 'pitch', 'yaw'), map(float, rms)))
        # Covariance from the weighted residual variance and (AᵀA)⁻¹. The filtered
        # residuals are correlated over about 1/(2 fc): count independent samples only.
        rw = yw - aw @ p
        dt = float(sig['dt'])
        independent = max(len(keep) + 1.0, len(yw) * 2.0 * cutoff_hz * dt)
        sigma2 = float(rw @ rw) / len(yw) * independent / (independent - len(keep))
        an = aw / scale
        try:
            cov = np.linalg.inv(an.T @ an) * sigma2 * (len(yw) / independent)
            cov = cov / np.outer(scale, scale)
        except np.linalg.LinAlgError:
            cov = np.full((len(keep), len(keep)), math.inf)
        for i, j in enumerate(keep):
            name, value = names[j], float(p[i])
            hw = Z95 * math.sqrt(max(cov[i, i], 0.0))
            if condition > MAX_CONDITION:
                estimates[name] = Estimate(name, None, None,
                                           f'condition number {condition:.3g} > '
                                           f'{MAX_CONDITION:g}')
            elif name in FRICTION:
                # Their true value may be 0: judged by their forward-row force at 1 m/s
                # (2b/r² × 1 m/s for b, F_rr itself) against m_v × 1 m/s² instead.
                mv = float(p[keep.index(0)]) if 0 in keep else params.effective_mass
                radius = params.wheel_radius
                force = 2.0 * hw / radius ** 2 if name == 'friction' else hw
                ok = force <= MAX_RELATIVE_CI * abs(mv)
                unit = 'N m s/rad: 2b/r² × 1 m/s' if name == 'friction' else 'N:'
                estimates[name] = (Estimate(name, value, hw) if ok else Estimate(
                    name, None, None, f'95 % CI ±{hw:.3g} {unit} uncertain by more than '
                    f'{MAX_RELATIVE_CI:.0%} of m_v × 1 m/s^2'))
            elif value <= 0.0 or hw > MAX_RELATIVE_CI * abs(value):
                estimates[name] = Estimate(name, None, None,
                                           f'relative 95 % CI {hw / max(abs(value), 1e-300):.1%}'
                                           f' > {MAX_RELATIVE_CI:.0%}')
            else:
                estimates[name] = Estimate(name, value, hw)
    # l = m_p l² / m_p l (delta method on the two relative CIs, assumed independent).
    e1, e2 = estimates.get('mpl'), estimates.get('mpl2')
    if e1 and e2 and e1.value and e2.value:
        val = e2.value / e1.value
        rel = math.hypot(e1.half_width / e1.value, e2.half_width / e2.value)
        estimates['com_height'] = Estimate('com_height', val, rel * val)
    else:
        estimates['com_height'] = Estimate('com_height', None, None,
                                           'needs m_p l and m_p l^2')
    return Identification(estimates, condition, residual_rms, n, source,
                          float(1.0 - inlier.mean()))


def to_parameters(result: Identification, nominal: WipParameters) -> tuple[dict, list[str]]:
    """Return overrides of :class:`WipParameters` for the controllers' model and notes on them.

    r, d, g, m_w, J_w are kept (assumed known); what was not determined keeps its
    nominal value. m_p = (m_p l)/l, I_c = J_θ − m_p l², m_c = m_v − m_p − 2(m_w + J_w/r²),
    J_υ = J_ϕ − d²(m_w + J_w/r²)/2 (the inverse of WipParameters' derived values).
    """
    notes = []
    l = result.value('com_height') or nominal.com_height  # noqa: E741 - the paper's symbol
    if not result.value('com_height'):
        notes.append(f'com_height kept at the nominal {nominal.com_height:g} m')
    mpl = result.value('mpl')
    mp = mpl / l if mpl else nominal.body_mass
    jt = result.value('pitch_inertia') or nominal.pitch_inertia
    mv = result.value('effective_mass') or nominal.effective_mass
    jphi = result.value('yaw_inertia_total') or nominal.yaw_inertia_total
    wheel = nominal.wheel_mass + nominal.wheel_inertia / nominal.wheel_radius ** 2
    out = {'body_mass': mp, 'com_height': l, 'body_pitch_inertia_com': jt - mp * l * l,
           'chassis_mass': mv - mp - 2.0 * wheel,
           'yaw_inertia': jphi - nominal.track_width ** 2 * wheel / 2.0}
    for name in list(out):
        if not out[name] > 0.0:
            notes.append(f'{name} would be {out[name]:.4g} <= 0: kept at the nominal '
                         f'{getattr(nominal, name):g}')
            out[name] = getattr(nominal, name)
    for name, value in zip(('effective_mass', 'mpl', 'pitch_inertia', 'yaw_inertia_total'),
                           (mv, mpl, jt, jphi)):
        if value is None or result.value(name) is None:
            notes.append(f'{name} not determined: nominal kept')
    return {k: float(v) for k, v in out.items()}, notes


def true_values(params: WipParameters) -> dict[str, float]:
    """Return the combinations of ``params`` that :func:`identify` estimates."""
    mp, l = params.body_mass, params.com_height  # noqa: E741 - the paper's symbol
    return {'effective_mass': params.effective_mass, 'mpl': mp * l,
            'pitch_inertia': params.pitch_inertia, 'mpl2': mp * l * l,
            'yaw_inertia_total': params.yaw_inertia_total, 'friction': 0.0,
            'rolling_resistance': 0.0, 'com_height': l}


def table(result: Identification, truth: Mapping[str, float] | None = None) -> str:
    lines = [f'identify: {result.samples} samples per equation from {result.source} '
             f'({result.rejected:.1%} left out as outliers); '
             f'condition number {result.condition:.3g}; residual RMS forward '
             f'{result.residual_rms["forward"]:.3g} N, pitch {result.residual_rms["pitch"]:.3g}'
             f' N m, yaw {result.residual_rms["yaw"]:.3g} N m']
    head = f'{"parameter":<26} {"value":>10} {"95% CI ±":>10}'
    lines.append(head + (f' {"true":>10} {"error":>8}' if truth else ''))
    for name, e in result.estimates.items():
        label = SYMBOLS[name]
        if e.value is None:
            lines.append(f'{label:<26} {"not determined":>21}  ({e.reason})')
            continue
        row = f'{label:<26} {e.value:>10.4g} {e.half_width:>10.2g}'
        if truth and name in truth:
            err = ((e.value - truth[name]) / truth[name]) if truth[name] else math.nan
            row += f' {truth[name]:>10.4g} {err:>+8.1%}'
        lines.append(row)
    return '\n'.join(lines)


def _ros_double(value: float) -> str:
    """``value`` to 6 significant digits, always as a floating-point literal."""
    text = f'{value:.6g}'
    if 'n' in text or '.' in text:   # inf, nan, or a dot already
        return text
    mantissa, e, exponent = text.partition('e')
    return f'{mantissa}.0{e}{exponent}'   # '25.0', '1.0e-05' (YAML 1.1 needs the dot)


def model_yaml(overrides: Mapping[str, float], notes: Iterable[str], params_file: bool) -> str:
    """Return a scenario's ``controller_model`` section, or a ROS params file (``model.*``)."""
    head = ''.join(f'# {n}\n' for n in notes)
    if params_file:
        # A ROS double must be written as one: '25.0', not '25' (an integer to ROS).
        body = ''.join(f'    model.{k}: {_ros_double(v)}\n' for k, v in overrides.items())
        return f'{head}/**:\n  ros__parameters:\n{body}'
    body = ''.join(f'    {k}: {v:.6g}\n' for k, v in overrides.items())
    return f'{head}controller_model:\n  parameters:\n{body}'


#: The bag topics a fit reads: default name -> (group, message type).
BAG_TOPICS = {'/wip/ground_truth': ('truth', 'wip_msgs/msg/GroundTruth'),
              '/wip/state_estimate': ('estimate', 'wip_msgs/msg/StateEstimate'),
              '/wip/wheel_torques': ('wheels', 'wip_msgs/msg/WheelTorques'),
              '/joint_states': ('encoders', 'sensor_msgs/msg/JointState'),
              '/imu/data': ('imu', 'sensor_msgs/msg/Imu')}


def _sensor_converters(wiring):
    """Return the (encoders, imu) row functions: the ESO node's conversions for ``wiring``.

    A message they cannot read (the joints absent, no orientation...) gives None: the row
    is skipped, as the ESO node drops it.
    """
    from wip_control.nodes.conversions import InvalidMessage
    from wip_control.nodes.hardware_inputs import (body_pitch_yaw, body_pitch_yaw_rates,
                                                   mounting_inverse, signed_efforts,
                                                   signed_wheel_angles)
    inverse = mounting_inverse(wiring.imu_mounting_rpy)

    def encoders(m):
        try:
            return signed_wheel_angles(m, wiring.left_joint, wiring.right_joint,
                                       wiring.left_wheel_sign, wiring.right_wheel_sign)
        except (InvalidMessage, ValueError, IndexError):
            return None

    def imu(m):
        try:
            pitch, yaw = body_pitch_yaw(m, inverse)
            return (pitch, yaw, *body_pitch_yaw_rates(m, inverse, pitch))
        except (InvalidMessage, ValueError):
            return None

    def efforts(m):
        # The joints' effort state, in their own signs: the sign maps both ways.
        names = list(m.name)
        if len(m.effort) != len(names) or wiring.left_joint not in names or \
                wiring.right_joint not in names:
            return None
        left = float(m.effort[names.index(wiring.left_joint)])
        right = float(m.effort[names.index(wiring.right_joint)])
        if not math.isfinite(left + right):
            return None
        return signed_efforts(left, right, wiring.left_wheel_sign, wiring.right_wheel_sign)
    return encoders, imu, efforts


#: Where a bag's wheel torques come from (``torques``): the base's joint effort state, or
#: the controllers' commands.
TORQUE_SOURCES = ('auto', 'efforts', 'commands')


def load_record(path: str | pathlib.Path, wiring=None,
                remaps: Iterable[tuple[str, str]] = (), torques: str = 'auto') -> dict:
    """Return a record from a bag (directory or .mcap) or a timeseries.npz of scripts/simulate.

    A bag's /joint_states and /imu/data are read with ``wiring`` (a
    :class:`wip_tools.run_wiring.Wiring`, default the project's conventions) by the ESO
    node's own conversions; its topics are found as :func:`run_wiring.sensor_topic` says.
    ``torques``: the wheels group from the JointState efforts ('efforts': what the motors
    applied, the effort of a sample taken as the torque over the period that ended at
    it), from /wip/wheel_torques ('commands': stamped with the sensor sample they answer,
    so they lag the motors by the controllers' latency and the motor lag), or 'auto'
    (efforts where the base reports non-zero ones). The record's ``torque_source`` says
    which.
    """
    if torques not in TORQUE_SOURCES:
        raise IdentifyError(f'torques {torques!r}: expected one of {list(TORQUE_SOURCES)}')
    path = pathlib.Path(path)
    if not path.exists():
        raise IdentifyError(f'{path}: no such file or directory')
    if path.is_dir() and (path / 'timeseries.npz').exists() and not any(path.glob('*.mcap')):
        path = path / 'timeseries.npz'
    if path.suffix == '.npz':
        from wip_sim.core.record import RunRecord
        try:
            return RunRecord.load_npz(path)
        except (OSError, ValueError, KeyError) as err:
            raise IdentifyError(f'{path}: not a readable timeseries.npz ({err})') from err
    from wip_bag.bag_reader import BagReadError, read_topics
    from wip_tools import report  # rosbag2
    from wip_tools.run_wiring import sensor_topic, Wiring, WiringError
    wiring = Wiring() if wiring is None else wiring
    try:
        kinds = {name: meta.type_name for name, meta in read_topics(path).items()}
    except BagReadError as err:
        raise IdentifyError(str(err)) from err
    encoders, imu, efforts = _sensor_converters(wiring)
    convert = dict(report.TOPICS, **{'/joint_states': ('encoders', encoders),
                                     '/imu/data': ('imu', imu)})
    topics = {}
    for default, (group, type_name) in BAG_TOPICS.items():
        try:
            name = sensor_topic(default, type_name, kinds, list(remaps))
        except WiringError as err:
            raise IdentifyError(str(err)) from err
        if name is not None:
            topics[name] = (group, convert[default][1])
    if not topics:
        raise IdentifyError(f'{path}: none of the topics {sorted(BAG_TOPICS)} (or of their '
                            'types) is in the bag')
    try:
        record = report.record_from_bag(path, topics)
    except report.ReportError as err:
        raise IdentifyError(str(err)) from err
    out = {g: record[g] for g in ('truth', 'estimate', 'wheels', 'encoders', 'imu')
           if g in record}
    out['torque_source'] = 'commands'
    joint_topic = next((n for n, (g, _) in topics.items() if g == 'encoders'), None)
    if torques != 'commands' and joint_topic is not None:
        try:
            applied = report.record_from_bag(path, {joint_topic: ('wheels', efforts)})
        except report.ReportError:
            applied = None
        wheels = applied['wheels'] if applied is not None else None
        usable = wheels is not None and len(wheels['t']) > 2 and (
            np.any(wheels['tau_left'] != 0.0) or np.any(wheels['tau_right'] != 0.0))
        if usable:
            # The same time origin as the rest; each effort acted over the period that
            # ended at its sample: it is stamped with the sample before.
            t = wheels['t'] + (applied.attributes['time_origin_ns']
                               - record.attributes['time_origin_ns']) * 1e-9
            period = float(np.median(np.diff(t)))
            out['wheels'] = {'t': np.concatenate([[t[0] - period], t[:-1]]),
                             'tau_left': wheels['tau_left'], 'tau_right': wheels['tau_right']}
            out['torque_source'] = 'efforts'
        elif torques == 'efforts':
            raise IdentifyError(f'{joint_topic}: no effort of both wheel joints (the base '
                                'does not report its effort state); use the commands')
    return out


def run_plant_model(run: str | pathlib.Path) -> str | None:
    """Return the plant model of a simulated run's scenario.yaml (in the bag or beside it)."""
    run = pathlib.Path(run)
    directory = run if run.is_dir() else run.parent
    for candidate in (directory / 'scenario.yaml', directory.parent / 'scenario.yaml'):
        if candidate.is_file():
            try:
                from wip_sim.core.scenario import load_scenario
                return load_scenario(candidate).plant.model.model
            except (ValueError, OSError):
                return None
    return None


def choose_model(record: Mapping, run: str | pathlib.Path, source: str) -> str:
    """'paper' or 'full' for ``--model auto``.

    Without ground truth the record is a robot's (or a base's): the full plant's rows. A
    simulation's rows are those of its plant, from its scenario.yaml ('paper' if none).
    """
    if source != 'truth' and not _has(record, 'truth'):
        return 'full'
    model = run_plant_model(run)
    return 'paper' if model in (None, 'paper') else 'full'


def main(argv: Iterable[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='scripts/identify', description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog="""\
Examples
--------
    scripts/identify robot_run/bag --out my_robot.yaml      # a scenario controller_model
    scripts/identify robot_run/bag --out my_robot_params.yaml --write-params
    scripts/identify robot_run/bag --params-file my_base.yaml   # the robot's wiring
    scripts/identify out/sim/timeseries.npz --source truth  # a simulated run""")
    parser.add_argument('run', help='rosbag2 directory, .mcap file, or timeseries.npz '
                        '(or a scripts/simulate output directory)')
    parser.add_argument('--out', help='write the identified model here: a scenario '
                        'controller_model section (.yaml), see --write-params')
    parser.add_argument('--write-params', action='store_true',
                        help='write --out as a ROS params file (/**: model.*) instead')
    parser.add_argument('--params-file', action='append', default=[], metavar='FILE',
                        dest='params_files',
                        help="the robot's ROS params file (joint names, wheel signs, "
                        'imu_mounting_rpy, encoders_relative_to_body), as given to '
                        'run_graph; repeatable, later wins; default: the params.yaml the '
                        'run left in the bag (or beside it)')
    parser.add_argument('--remap', action='append', default=[], metavar='FROM:=TO',
                        dest='remaps', help='the bag topic of a sensor topic, as run_graph '
                        "'s --remap (e.g. /joint_states:=/base/joint_states); default: the "
                        "bag's only topic of that type")
    parser.add_argument('--source', choices=('auto', 'truth', 'sensors', 'estimate'),
                        default='auto',
                        help='state signals: ground truth (a simulation), the sensors '
                        '(/joint_states and /imu/data: a robot) or the state estimate; '
                        'default: the first of these the run has')
    parser.add_argument('--rolling-encoders', action='store_true',
                        help='the wheel angles are rolling angles (against the ground), not '
                        "joint angles against the body (default: the wiring's "
                        'encoders_relative_to_body)')
    parser.add_argument('--model', choices=('auto', 'paper', 'full'), default='auto',
                        help="rows to fit: eq. (1) ('paper') or the full plant's (motor "
                        'reaction torque, centrifugal and Coriolis terms, yaw gain d/(2r): a '
                        "robot); auto: 'full' without ground truth, else the simulated "
                        "plant's (its scenario.yaml)")
    parser.add_argument('--friction', action=argparse.BooleanOptionalAction, default=None,
                        help="also fit the wheels' viscous axle friction b and the rolling "
                        "resistance F_rr (not in eq. (1)); default: with the full rows")
    parser.add_argument('--torques', choices=TORQUE_SOURCES, default='auto',
                        help="a bag's wheel torques: the joints' effort state on "
                        "/joint_states (what the motors applied), the controllers' commands "
                        "(/wip/wheel_torques), or auto: the efforts where the base reports "
                        'them')
    parser.add_argument('--motor-lag', type=float, default=0.0, metavar='S',
                        help='time constant [s] of a first-order lag of the motors behind '
                        'the torques recorded (default 0; docs/identification.md §7)')
    parser.add_argument('--scenario', help='scenario YAML whose controller_model gives '
                        'the known r, d, g, m_w, J_w (default: the nominal parameters)')
    add_exit_codes(parser)
    args = parser.parse_args(None if argv is None else list(argv))
    try:
        from wip_tools.run_wiring import (load_wiring, parse_remaps, run_params_files,
                                          WiringError)
        nominal = WipParameters()
        if args.scenario:
            from wip_control.core.config import ConfigError
            from wip_sim.core.scenario import load_scenario
            try:
                nominal = load_scenario(args.scenario).controller_model.parameters
            except (ConfigError, OSError) as err:
                raise IdentifyError(f'--scenario {args.scenario}: {err}') from err
        try:
            files = args.params_files or run_params_files(args.run)
            wiring = load_wiring(files)
            remaps = parse_remaps(args.remaps)
        except WiringError as err:
            raise IdentifyError(str(err)) from err
        record = load_record(args.run, wiring, remaps, args.torques)
        source = _best_source(record) if args.source == 'auto' else args.source
        model = choose_model(record, args.run, source) if args.model == 'auto' \
            else args.model
        friction = (model == 'full') if args.friction is None else args.friction
        relative = wiring.encoders_relative_to_body and not args.rolling_encoders
        try:
            result = identify(record, nominal, source, friction, model=model,
                              encoders_relative_to_body=relative,
                              motor_lag=args.motor_lag)
        except IdentifyError as err:
            if source == 'sensors' or 'sensor' in str(err):
                raise IdentifyError(f'{err}; wiring read: {wiring.describe()}') from err
            raise
    except IdentifyError as err:
        print(f'ERROR: {" ".join(str(err).split())}', file=sys.stderr)
        return EXIT_USAGE
    torque_source = record.get('torque_source', 'commands') if isinstance(record, dict) \
        else 'commands'
    print(f'rows: {model}{" with friction" if friction else ""}; torques: '
          + ('the joint efforts' if torque_source == 'efforts' else 'the commands')
          + (f'; sensors read with {wiring.describe()}' if source == 'sensors' else ''))
    print(table(result))
    overrides, notes = to_parameters(result, nominal)
    if args.out:
        text = model_yaml(overrides, notes, args.write_params)
        try:
            pathlib.Path(args.out).write_text(text, encoding='utf-8')
        except OSError as err:
            print(f'ERROR: --out {args.out}: {err.strerror}', file=sys.stderr)
            return EXIT_USAGE
        print(f'wrote {args.out}')
    else:
        print(model_yaml(overrides, notes, args.write_params), end='')
    return EXIT_OK


if __name__ == '__main__':
    exit_with(main, 'identify')
