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
--out). Exit codes: wip_runtime.cli.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import pathlib
import sys
from typing import Iterable, Mapping

import numpy as np

from wip_description.params import ModelParams
from wip_runtime.cli import add_exit_codes, EXIT_OK, EXIT_USAGE, exit_with
from wip_tools.identify_record import best_source, choose_model, load_record, TORQUE_SOURCES
from wip_tools.identify_signals import (CUTOFF_HZ, GYRO_NOISE_NOTED, IRREGULAR_STAMPS_NOTED,
                                        IdentifyError, gyro_white_noise, irregular_stamps,
                                        regressors, robust_std, root_mean_square,
                                        uniform_signals)

#: The fitted parameters, in the column order of the regressor matrix.
NAMES = ('effective_mass', 'mpl', 'pitch_inertia', 'mpl2', 'yaw_inertia_total', 'friction',
         'rolling_resistance')
SYMBOLS = {'effective_mass': 'm_v [kg]', 'mpl': 'm_p l [kg m]',
           'pitch_inertia': 'J_theta [kg m^2]', 'mpl2': 'm_p l^2 [kg m^2]',
           'yaw_inertia_total': 'J_phi [kg m^2]', 'friction': 'b [N m s/rad]',
           'rolling_resistance': 'F_rr [N]', 'com_height': 'l = m_p l^2 / m_p l [m]'}
#: The friction columns (``friction=True``): viscous axle friction b, rolling resistance.
FRICTION = ('friction', 'rolling_resistance')
#: Smallest RMS excitation [SI] of a regressor signal that counts (about what an IMU and
#: the wheel encoders resolve after the filter): below it the column is noise.
MIN_EXCITATION = {'v_dot': 0.02, 'theta_ddot': 0.02, 'omega_dot': 0.02, 'omega_sq': 0.005}
#: A sample whose filtered residual in any row is beyond this many robust standard
#: deviations (1.4826 × the median absolute residual) is left out of the fit.
REJECT_SIGMAS = 5.0
MAX_CONDITION = 1e4         #: of the column-scaled, weighted regressor matrix
MAX_RELATIVE_CI = 0.05      #: 95 % half-width / |value| above which a value is not given
Z95 = 1.96


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


def identify(record: Mapping, params: ModelParams | None = None, source: str = 'auto',
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
    params = ModelParams() if params is None else params
    if source == 'auto':
        source = best_source(record)
    if not (math.isfinite(motor_lag) and 0.0 <= motor_lag <= 1.0):
        raise IdentifyError(f'motor lag {motor_lag!r} s: expected 0 to 1 s')
    sig = uniform_signals(record, source, params.wheel_radius, encoders_relative_to_body,
                          motor_lag)
    a, y, excitation = regressors(sig, params, cutoff_hz, model)
    n = len(y) // 3
    if n < 10:
        raise IdentifyError(f'too little data after filtering: {n} samples')
    used = list(range(7 if friction else 5))
    a = a[:, used]
    names = [NAMES[j] for j in used]
    why = _unexcited(excitation)
    keep = [j for j, name in enumerate(names)
            if name not in why and np.any(a[:, j] != 0.0)]
    estimates = {name: Estimate(name, None, None, why.get(name, 'no excitation'))
                 for name in names}
    residual_rms = {'forward': math.nan, 'pitch': math.nan, 'yaw': math.nan}
    condition = math.inf
    y = _unfitted_moved_right(a, y, names, keep, params)
    inlier = np.ones(n, dtype=bool)
    if keep:
        p, aw, yw, scale, rms, inlier = _weighted_fit(a[:, keep], y, n)
        condition = float(np.linalg.cond(aw / scale))
        residual_rms = dict(zip(('forward', 'pitch', 'yaw'), map(float, rms)))
        cov = _covariance(aw, yw, p, scale, len(keep), float(sig['dt']), cutoff_hz)
        for i, j in enumerate(keep):
            estimates[names[j]] = _judged(names[j], float(p[i]), cov[i, i], condition,
                                          p, keep, params)
    estimates['com_height'] = _com_height(estimates)
    return Identification(estimates, condition, residual_rms, n, source,
                          float(1.0 - inlier.mean()))


def _unexcited(excitation: Mapping[str, float]) -> dict[str, str]:
    """Return why each column without enough excitation is not fitted (MIN_EXCITATION)."""
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
    return why


def _unfitted_moved_right(a: np.ndarray, y: np.ndarray, names: list[str], keep: list[int],
                          params: ModelParams) -> np.ndarray:
    """Return y with the terms of the columns not fitted moved to it.

    A column left out is not dropped (that would bias the others by its term) but fixed
    at its nominal value and moved to the right-hand side; m_p l² at (m_p l)·l_nominal
    once m_p l is fitted (its term is small: sin²θ, sinθ cosθ).
    """
    nominal = true_values(params)
    fixed = [j for j in range(len(names)) if j not in keep]
    y = y - a[:, fixed] @ np.array([nominal[names[j]] for j in fixed]) if fixed else y
    if keep and 3 in fixed and 1 in keep:
        sol, *_ = np.linalg.lstsq(a[:, keep], y, rcond=None)
        mpl2_fixed = float(sol[keep.index(1)]) * params.com_height
        y = y - a[:, 3] * (mpl2_fixed - nominal['mpl2'])
    return y


def _weighted_fit(a: np.ndarray, y: np.ndarray, n: int) -> tuple:
    """Return (p, weighted A, weighted y, column scale, residual RMS per row, inliers).

    Passes: ordinary LS, then each equation weighted by 1/its residual RMS (the rows are in
    different units: N, N·m, N·m), then twice without the samples whose residual in any
    row is beyond REJECT_SIGMAS robust standard deviations (what the model does not
    describe: a hand, a bump, a stalled driver's aftermath).
    """
    w = np.ones(3)
    inlier = np.ones(n, dtype=bool)
    for pass_ in range(4):
        rows = np.tile(inlier, 3)
        aw = (a * np.repeat(w, n)[:, None])[rows]
        yw = (y * np.repeat(w, n))[rows]
        scale = np.linalg.norm(aw, axis=0)
        scale[scale == 0.0] = 1.0
        sol, *_ = np.linalg.lstsq(aw / scale, yw, rcond=None)
        p = sol / scale
        res = y - a @ p
        blocks = [res[i * n:(i + 1) * n] for i in range(3)]
        rms = np.array([root_mean_square(b[inlier]) for b in blocks])
        floor = max(1e-12, 1e-9 * root_mean_square(y))
        w = 1.0 / np.maximum(rms, floor)
        if pass_ >= 1:
            sigma = [robust_std(b[inlier]) for b in blocks]
            inlier = np.all([np.abs(b) <= REJECT_SIGMAS * max(sd, floor)
                             for b, sd in zip(blocks, sigma)], axis=0)
            if inlier.sum() < max(10, n // 2):     # not outliers: the model is wrong
                inlier = np.ones(n, dtype=bool)
    return p, aw, yw, scale, rms, inlier


def _covariance(aw: np.ndarray, yw: np.ndarray, p: np.ndarray, scale: np.ndarray,
                columns: int, dt: float, cutoff_hz: float) -> np.ndarray:
    """Return the covariance of p from the weighted residual variance and (AᵀA)⁻¹.

    The filtered residuals are correlated over about 1/(2 fc): only independent samples
    are counted.
    """
    rw = yw - aw @ p
    independent = max(columns + 1.0, len(yw) * 2.0 * cutoff_hz * dt)
    sigma2 = float(rw @ rw) / len(yw) * independent / (independent - columns)
    an = aw / scale
    try:
        cov = np.linalg.inv(an.T @ an) * sigma2 * (len(yw) / independent)
        return cov / np.outer(scale, scale)
    except np.linalg.LinAlgError:
        return np.full((columns, columns), math.inf)


def _judged(name: str, value: float, variance: float, condition: float, p: np.ndarray,
            keep: list[int], params: ModelParams) -> Estimate:
    """Return the estimate of ``name``, or why it is not given (condition, CI)."""
    hw = Z95 * math.sqrt(max(variance, 0.0))
    if condition > MAX_CONDITION:
        return Estimate(name, None, None,
                        f'condition number {condition:.3g} > {MAX_CONDITION:g}')
    if name in FRICTION:
        # Their true value may be 0: judged by their forward-row force at 1 m/s
        # (2b/r² × 1 m/s for b, F_rr itself) against m_v × 1 m/s² instead.
        mv = float(p[keep.index(0)]) if 0 in keep else params.effective_mass
        radius = params.wheel_radius
        force = 2.0 * hw / radius ** 2 if name == 'friction' else hw
        ok = force <= MAX_RELATIVE_CI * abs(mv)
        unit = 'N m s/rad: 2b/r² × 1 m/s' if name == 'friction' else 'N:'
        return (Estimate(name, value, hw) if ok else Estimate(
            name, None, None, f'95 % CI ±{hw:.3g} {unit} uncertain by more than '
            f'{MAX_RELATIVE_CI:.0%} of m_v × 1 m/s^2'))
    if value <= 0.0 or hw > MAX_RELATIVE_CI * abs(value):
        return Estimate(name, None, None,
                        f'relative 95 % CI {hw / max(abs(value), 1e-300):.1%}'
                        f' > {MAX_RELATIVE_CI:.0%}')
    return Estimate(name, value, hw)


def _com_height(estimates: Mapping[str, Estimate]) -> Estimate:
    """Return l = m_p l² / m_p l (delta method on the two relative CIs, assumed independent)."""
    e1, e2 = estimates.get('mpl'), estimates.get('mpl2')
    if e1 and e2 and e1.value and e2.value:
        val = e2.value / e1.value
        rel = math.hypot(e1.half_width / e1.value, e2.half_width / e2.value)
        return Estimate('com_height', val, rel * val)
    return Estimate('com_height', None, None, 'needs m_p l and m_p l^2')


def to_parameters(result: Identification, nominal: ModelParams) -> tuple[dict, list[str]]:
    """Return overrides of :class:`ModelParams` for the controllers' model and notes on them.

    r, d, g, m_w, J_w are kept (assumed known); what was not determined keeps its
    nominal value. m_p = (m_p l)/l, I_c = J_θ − m_p l², m_c = m_v − m_p − 2(m_w + J_w/r²),
    J_υ = J_ϕ − d²(m_w + J_w/r²)/2 (the inverse of ModelParams' derived values).
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


def true_values(params: ModelParams) -> dict[str, float]:
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


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='scripts/identify', formatter_class=argparse.RawDescriptionHelpFormatter,
        description='Fit the identifiable parameters of model (1) (m_v, m_p l, J_theta, '
        'J_phi,\noptionally the friction) to a recorded run, with 95 % confidence intervals, '
        "and\nwrite the controllers' model. Equations, method and limits: "
        'docs/identification.md.', epilog="""\
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
    return parser


def main(argv: Iterable[str] | None = None) -> int:
    args = _parser().parse_args(None if argv is None else list(argv))
    try:
        record, wiring, nominal = _inputs(args)
        source = best_source(record) if args.source == 'auto' else args.source
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
    if source == 'sensors':
        _print_sensor_notes(record)
    print(table(result))
    return _write_model(args, *to_parameters(result, nominal))


def _print_sensor_notes(record: Mapping) -> None:
    """Note what in the sensors biases the fit: jittered stamps, a noisy gyro in closed loop."""
    irregular = irregular_stamps(record)
    if irregular > IRREGULAR_STAMPS_NOTED:
        print(f"note: {irregular:.1%} of the joint states' stamp intervals are more "
              'than a quarter off the median period; a driver should stamp a sample '
              'with the time it read it, not the time it published it')
    noise = gyro_white_noise(record)
    if noise > GYRO_NOISE_NOTED:
        print(f"note: the gyro's white noise is about {noise:.3g} rad/s; from a run in "
              'closed loop J_theta comes out high (the controllers acted on that noise): '
              'about +3 to +4 % at 0.01 rad/s on the shipped excitation '
              '(docs/identification.md section 7)')


def _inputs(args: argparse.Namespace) -> tuple:
    """Return the record of ``args.run``, the robot's wiring and the nominal parameters."""
    from wip_tools.run_wiring import (load_wiring, parse_remaps, run_params_files,
                                      WiringError)
    nominal = ModelParams()
    if args.scenario:
        from wip_runtime.config import ParamError
        from wip_sim.core.scenario import load_scenario
        try:
            nominal = load_scenario(args.scenario).controller_model.parameters
        except (ParamError, OSError) as err:
            raise IdentifyError(f'--scenario {args.scenario}: {err}') from err
    try:
        files = args.params_files or run_params_files(args.run)
        wiring = load_wiring(files)
        remaps = parse_remaps(args.remaps)
    except WiringError as err:
        raise IdentifyError(str(err)) from err
    return load_record(args.run, wiring, remaps, args.torques), wiring, nominal


def _write_model(args: argparse.Namespace, overrides: dict, notes: list[str]) -> int:
    """Write the identified model to ``--out``, or print it."""
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
