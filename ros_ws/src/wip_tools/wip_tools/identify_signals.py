"""The signals and regressors of the fit of model (1): sampling, low-pass, rows.

Model (1) of Yue, An, Li (2016) in its Euler-Lagrange form is linear in
p = (m_v, m_p l, J_θ, m_p l², J_ϕ [, b, F_rr]) with r, d and g known (the equations are
in :mod:`wip_tools.identify` and docs/identification.md). This module turns a record into
uniformly sampled signals and those into the rows (A, y) of A p = y.
"""

from __future__ import annotations

import math
from typing import Iterable, Mapping

import numpy as np

from wip_description.params import ModelParams

#: Wheel ground speed [m/s] at which the rolling resistance's sign is tanh(1) = 0.76 of its
#: full value: a smooth sign, so that encoder noise about a standstill does not toggle it.
SIGN_SPEED = 0.02
#: Low-pass [Hz] of the wheel speeds whose sign the rolling resistance takes (the raw speed
#: from quantised encoders is noisy to about 0.05 m/s at 200 Hz).
SIGN_CUTOFF_HZ = 5.0
#: Low-pass cut-off [Hz] (Gaussian, zero phase). The regressors hold differentiated
#: measurements, whose noise power grows as fc³ while the excitation run's content is below
#: about 0.5 Hz (a 20 s lap, the speed varying twice a lap); noise in a regressor biases
#: least squares towards zero (errors in variables). With an IMU's noise (0.002 rad,
#: 0.01 rad/s) 4 Hz gave m_v 10 % low from the sensors, 1 Hz within 1.5 %
#: (docs/identification.md §5) while the controller's torque jittered with the noise; with
#: its mean drift (quieter) 1 Hz left m_p l up to 6.8 % low, 0.8 Hz within 5 % (§4).
CUTOFF_HZ = 0.8
MIN_DURATION_S = 5.0
#: A gap between two samples of a stream longer than this many sample periods (a stalled
#: driver, a lost message burst) is not interpolated across: the rows whose filter window
#: reaches into it are left out.
MAX_GAP_PERIODS = 3.0
#: A stamp interval this far (a fraction of the median period) from the median is irregular.
IRREGULAR_STAMP_FRACTION = 0.25
#: scripts/identify notes irregular stamps above this fraction of the intervals.
IRREGULAR_STAMPS_NOTED = 0.01
#: [rad/s] Gyro white noise above which scripts/identify notes the closed loop's bias of
#: J_theta (over 2 % on the shipped excitation; docs/identification.md §7).
GYRO_NOISE_NOTED = 0.005


class IdentifyError(ValueError):
    """Bad input: the message is one line."""


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


def uniform_signals(record: Mapping, source: str,
                    wheel_radius: float = ModelParams().wheel_radius,
                    encoders_relative_to_body: bool = True,
                    motor_lag: float = 0.0) -> dict[str, np.ndarray]:
    """Uniformly sampled (t, θ, θ̇, υ, ω, τl, τr) from the record's ``source`` group.

    truth: the torques of row k were applied over [t_{k−1}, t_k) (wip_sim/core/runner.py), so they
    are shifted back one row to pair with the interval they acted over. estimate and
    sensors: the torques come from the wheels group (applied from its stamp on),
    interpolated.
    """
    group, streams = _state_group(record, source, wheel_radius, encoders_relative_to_body)
    t = np.asarray(group['t'], dtype=float)
    tl, tr, wheels = _torques(record, source, t, streams)
    cols = {'theta': group['theta'], 'theta_dot': group['theta_dot'], 'v': group['v'],
            'omega': group['omega'], 'tau_left': tl, 'tau_right': tr}
    if source != 'truth':
        t, cols = _while_driven(t, cols, wheels)
    if len(t) < 3 or t[-1] - t[0] < MIN_DURATION_S:
        raise IdentifyError(f'too little data: {len(t)} samples over '
                            f'{max(0.0, t[-1] - t[0]) if len(t) else 0.0:.2f} s '
                            f'(at least {MIN_DURATION_S:g} s needed)')
    return _resampled(t, cols, source, streams, motor_lag)


def _state_group(record: Mapping, source: str, wheel_radius: float,
                 encoders_relative_to_body: bool) -> tuple[Mapping, list]:
    """Return the state group of ``source`` and the sample times of the streams it is from."""
    if source == 'sensors':
        group = _sensor_group(record, wheel_radius, encoders_relative_to_body)
        streams = [record['encoders']['t'], record['imu']['t']]
    else:
        group = record[source] if source in record else None
        streams = [group['t']] if group is not None else []
    if group is None or len(group['t']) == 0:
        raise IdentifyError(f'no {source} samples (topic /wip/ground_truth or '
                            '/wip/state_estimate missing)')
    return group, streams


def _torques(record: Mapping, source: str, t: np.ndarray, streams: list) -> tuple:
    """Return (τl, τr, wheels group or None) at the times ``t``; adds the wheels' stream."""
    if source == 'truth':
        group = record['truth']
        tl, tr = np.asarray(group['tau_left'])[1:], np.asarray(group['tau_right'])[1:]
        return np.append(tl, tl[-1:]), np.append(tr, tr[-1:]), None
    wheels = record['wheels'] if 'wheels' in record else None
    if wheels is None or len(wheels['t']) < 2:
        raise IdentifyError('no wheel torques (topic /wip/wheel_torques missing)')
    streams.append(wheels['t'])
    idx = np.clip(np.searchsorted(wheels['t'], t, side='right') - 1, 0,
                  len(wheels['t']) - 1)
    return np.asarray(wheels['tau_left'])[idx], np.asarray(wheels['tau_right'])[idx], wheels


def _while_driven(t: np.ndarray, cols: dict, wheels: Mapping) -> tuple[np.ndarray, dict]:
    """Return the samples between the first and the last non-zero torque.

    Only while the controllers drove the wheels, within the torques' record. Before it a
    robot is held (a hand's forces are not in the model; a stand-in base is frozen), after
    it it is stopped or caught; outside the record the torque is not known.
    """
    w_t = np.asarray(wheels['t'], dtype=float)
    driven = (np.asarray(cols['tau_left']) != 0.0) | (np.asarray(cols['tau_right']) != 0.0)
    active = np.flatnonzero(driven & (t >= w_t[0]) & (t <= w_t[-1]))
    span = slice(active[0], active[-1] + 1) if len(active) else slice(0, 0)
    return t[span], {name: np.asarray(values)[span] for name, values in cols.items()}


def _resampled(t: np.ndarray, cols: dict, source: str, streams: list,
               motor_lag: float) -> dict[str, np.ndarray]:
    """Return ``cols`` on a uniform grid at the median period, with the motors' lag."""
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


def regressors(sig: Mapping[str, np.ndarray], params: ModelParams,
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
    rows, ys = _equation_rows(params, model, dt, (th, thd, v, om), (vd, thdd, omd),
                              tau_v, tau_w)
    keep_rows = _rows_clear_of_gaps(sig, dt, cutoff_hz)
    blocks, outs = [], []
    for a, y in zip(rows, ys):
        af = np.stack([gaussian_lowpass(a[:, j], dt, cutoff_hz) for j in range(a.shape[1])],
                      axis=1)
        yf = gaussian_lowpass(y, dt, cutoff_hz)
        # Drop the filter's edges (the kernel runs off the record there).
        edge = min(len(yf) // 4, int(math.ceil(1.0 / (cutoff_hz * dt))))
        kept = keep_rows[edge:len(yf) - edge]
        blocks.append(af[edge:len(af) - edge][kept])
        outs.append(yf[edge:len(yf) - edge][kept])
    s, c = np.sin(th), np.cos(th)
    excitation = {'v_dot': root_mean_square(gaussian_lowpass(vd, dt, cutoff_hz)),
                  'theta_ddot': root_mean_square(gaussian_lowpass(thdd, dt, cutoff_hz)),
                  'omega_dot': root_mean_square(gaussian_lowpass(omd, dt, cutoff_hz)),
                  'omega_sq': root_mean_square(s * c * om ** 2)}
    return np.vstack(blocks), np.concatenate(outs), excitation


def _equation_rows(params: ModelParams, model: str, dt: float, states: tuple,
                   rates: tuple, tau_v: np.ndarray, tau_w: np.ndarray) -> tuple:
    """Return the unfiltered (A, y) of the forward, pitch and yaw rows at the midpoints."""
    th, thd, v, om = states
    vd, thdd, omd = rates
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
    return (lon, pitch, yaw), (tau_v / r, -full * tau_v, yaw_gain * tau_w)


def _rows_clear_of_gaps(sig: Mapping[str, np.ndarray], dt: float, cutoff_hz: float):
    """Return which rows' filter window reaches no gap in the data.

    Applied after filtering: the filter needs the uniform grid.
    """
    valid = np.asarray(sig.get('valid', np.ones(len(sig['t']), dtype=bool)))
    bad = ~(valid[1:] & valid[:-1])
    half = _kernel_half(dt, cutoff_hz)[1]
    return np.convolve(bad.astype(float), np.ones(2 * half + 1), mode='same') == 0.0


def irregular_stamps(record: Mapping, group: str = 'encoders') -> float:
    """Return the fraction of ``group``'s stamp intervals a quarter off the median period.

    A driver that stamps a sample when it publishes it, not when it read it, gives
    stamps jittered against the instants the values stand for; the speeds differentiated
    over them are then wrong sample by sample and the estimates' intervals widen
    (docs/identification.md §7).
    """
    if group not in record or len(record[group]['t']) < 3:
        return 0.0
    gaps = np.diff(np.asarray(record[group]['t'], dtype=float))
    period = float(np.median(gaps))
    if not period > 0.0:
        return 0.0
    return float(np.mean(np.abs(gaps - period) > IRREGULAR_STAMP_FRACTION * period))


def gyro_white_noise(record: Mapping) -> float:
    """Return the std [rad/s] of the white noise on the IMU's pitch rate (0 without one).

    From the second differences of the samples: white noise of std σ gives them the
    variance 6σ², the body's motion next to nothing at a sensor's rate; the median
    absolute deviation (× 1.4826) keeps bursts out of it.
    """
    if 'imu' not in record or len(record['imu']['t']) < 3:
        return 0.0
    second = np.diff(np.asarray(record['imu']['pitch_rate'], dtype=float), 2)
    second = second[np.isfinite(second)]
    if not len(second):
        return 0.0
    return robust_std(second - np.median(second)) / math.sqrt(6.0)


def robust_std(deviations: np.ndarray) -> float:
    """1.4826 × the median |deviation|: the std of normal deviations, outliers aside."""
    return 1.4826 * float(np.median(np.abs(deviations)))


def root_mean_square(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else 0.0
