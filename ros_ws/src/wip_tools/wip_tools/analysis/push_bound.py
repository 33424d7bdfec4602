"""Clairvoyant lower bound of the excursion after a push (pure numpy/scipy, no ROS).

How far must ANY controller let the vehicle run ahead of its reference after a push, given
the physical limits? Model (1) (or the full plant's equations, below) linearised about
upright (the tilt's gravity coupling kept, as
:func:`wip_control.core.mpc_prediction.gravity_aware_state_matrix`), in the frame of a
reference moving at constant speed, with the along-track error e, the speed error u:

    ė = u,   u̇ = a_υ θ + g2 τυ + d(t),   θ̈ = a_θ θ + g3 τυ,

a_υ = −mp² l² g / Ω0, a_θ = mv mp g l / Ω0, g2, g3 at θ = 0, d(t) the push (an
acceleration added to υ̇, as the scenarios' longitudinal disturbance). A controller that
knows the push in advance (from its start: it may react at once, not before; or only
after ``reaction_delay``), starting from rest on the reference, chooses the drive torque
τυ(t) piecewise constant on a fine grid (``step``) under

    |θ| ≤ θmax,   |τυ| ≤ τmax,   |τυ(t) − τυ(t − Ts)| ≤ Δτmax  (Ts the MPC period),

and must end at rest (u = θ = θ̇ = 0, τυ = 0) by ``horizon``; it minimises the peak of e.
That is a linear programme over the torque sequence (scipy's HiGHS). The torque-rate limit
over any window Ts contains both a torque held for Ts that jumps by Δτmax (the MPC's) and
any ramp, and the limits hold at the grid's points only: both are relaxations, so the value
is a lower bound for every controller of that model and those limits (the nonlinear plant's
excursion differs by the linearisation, a few % at θ ≤ 0.1 rad).

Why a peak of e at all: the only force that slows the vehicle for long is gravity on a
tilted body. The combination w = u − (g2/g3) θ̇, which the torque does not drive, obeys
ẇ = k θ + d with k = a_υ − g2 a_θ / g3: the push's Δv is absorbed only by ∫ θ dt = −Δv / k,
at |θ| ≤ θmax in at least Δv / (k θmax), and e grows meanwhile, by Δv² / (2 k θmax), give
or take the lean itself, e = ∫ w dt + (g2/g3) θ. For model (1) (``model='paper'``)
k = g whatever the body (Ω0 = mv J_θ − mp² l²; 0.51 m for 1 m/s at 0.1 rad, the lean
±J_θ θmax / (mp l), 0.087 m). The full plant (``model='full'``, ``wip_sim``'s derivation)
also puts the motors' reaction torque −τυ on the body: g2 = (J_θ + mp l r)/(Ω0 r),
g3 = −(mv r + mp l)/(Ω0 r), and then k = g mp l / (mv r + mp l) < g: holding a lean
takes a torque that also drives the wheels forward, so the same lean slows the vehicle
less and the least excursion is larger. The tests check the LP against these.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from wip_description.params import ModelParams


@dataclasses.dataclass(frozen=True)
class PushBound:
    """Result of :func:`push_excursion_bound` (SI units)."""

    excursion: float          #: least peak of e over the recovery [m] (≥ 0)
    times: np.ndarray         #: grid times [s] of the states
    error: np.ndarray         #: e of the optimal sequence [m]
    tilt: np.ndarray          #: θ of the optimal sequence [rad]
    torque: np.ndarray        #: τυ of the optimal sequence [N m], one per grid step
    status: str               #: the solver's message


#: The plant models whose linearisation :func:`linear_model` knows (engine models such as
#: mujoco are the full model's bodies: :func:`wip_sim.core.plant.equation_model`).
BOUND_MODELS = ('paper', 'full')


def linear_model(params: ModelParams,
                 model: str = 'paper') -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (A, B, E) of ż = A z + B τυ + E d for z = (e, u, θ, θ̇) about upright.

    ``model``: 'paper', model (1); 'full', with the reaction torque −τυ on the body (the
    input gains of ``wip_sim.core.plant.full_input_gains`` at θ = 0; A is the same).
    """
    if model not in BOUND_MODELS:
        raise ValueError(f'model must be one of {BOUND_MODELS}, got {model!r}')
    p = params
    omega0 = p.omega_denominator(0.0)
    mp_l = p.body_mass * p.com_height
    a_v = -mp_l * mp_l * p.gravity / omega0
    a_t = p.effective_mass * mp_l * p.gravity / omega0
    reaction = 1.0 if model == 'full' else 0.0
    g2 = (p.pitch_inertia + reaction * mp_l * p.wheel_radius) / (omega0 * p.wheel_radius)
    g3 = -(mp_l + reaction * p.effective_mass * p.wheel_radius) / (omega0 * p.wheel_radius)
    a = np.array([[0.0, 1.0, 0.0, 0.0],
                  [0.0, 0.0, a_v, 0.0],
                  [0.0, 0.0, 0.0, 1.0],
                  [0.0, 0.0, a_t, 0.0]])
    return a, np.array([0.0, g2, 0.0, g3]), np.array([0.0, 1.0, 0.0, 0.0])


def absorption_rate(params: ModelParams, model: str = 'paper') -> float:
    """Return k [m/s² per rad] of ẇ = k θ + d (module docstring): g for model (1)."""
    a, b, _ = linear_model(params, model)
    return a[1, 2] - b[1] * a[3, 2] / b[3]


def push_excursion_bound(params: ModelParams, delta_v: float, *, push_time: float = 0.1,
                         max_tilt: float = 0.1, max_torque: float = 30.0,
                         max_delta_torque: float = 10.0, delta_period: float = 0.1,
                         step: float = 0.02, horizon: float = 8.0,
                         model: str = 'paper', reaction_delay: float = 0.0) -> PushBound:
    """Return the least peak excursion ahead of the reference after a push.

    ``delta_v`` [m/s]: the push's speed change, a constant acceleration delta_v / push_time
    over ``push_time`` [s] (the paper's 10 m/s² for 0.1 s: 1 m/s); negative pushes back
    (the excursion is then behind, reported positive: the model is symmetric).
    ``max_torque``: |τυ| = |τl + τr| [N m] (two wheels of 15 N m: 30);
    ``max_delta_torque`` [N m] per ``delta_period`` [s]; ``step`` [s]: the grid;
    ``horizon`` [s]: the time by which it must be at rest; ``model``: the plant's
    equations, 'paper' or 'full' (:func:`linear_model`); ``reaction_delay`` [s]: the
    torque stays 0 for this long after the push starts (a controller that must first see
    the push; rounded to the grid). ValueError on bad arguments or when no sequence can
    bring it to rest by then (the push is beyond the limits).
    """
    from scipy.optimize import linprog

    _check_arguments(dict(delta_v=delta_v, push_time=push_time, max_tilt=max_tilt,
                          max_torque=max_torque, max_delta_torque=max_delta_torque,
                          delta_period=delta_period, step=step, horizon=horizon))
    dv = abs(float(delta_v))
    n = int(round(horizon / step))
    times = step * np.arange(n + 1)
    if not (math.isfinite(reaction_delay) and 0.0 <= reaction_delay < horizon):
        raise ValueError(f'push_excursion_bound: reaction_delay must be in [0, horizon), '
                         f'got {reaction_delay!r}')
    if dv == 0.0:
        zeros = np.zeros(n + 1)
        return PushBound(0.0, times, zeros, zeros.copy(), np.zeros(n), 'no push')
    ad, bd, ed = _discretised(params, step, model)
    lag = max(1, int(round(delta_period / step)))
    push = np.where(times[:-1] < push_time - 1e-9, dv / push_time, 0.0)
    # Sparse, not condensed: the tilt's unstable pole (√a_θ ≈ 4.6 /s) makes a condensed
    # prediction over seconds ill-conditioned (e^{4.6 · 8} ≈ 1e16). Variables:
    # z_0 .. z_n (4 each), τ_0 .. τ_{n-1}, P; minimise P.
    nz, nt = 4 * (n + 1), n
    nv = nz + nt + 1
    pi = nz + nt                                     # index of P; z_k[j] at 4k + j
    eq, beq = _dynamics(ad, bd, ed, push, n, nv)
    ub, bub = _peak_and_rate_limits(n, nv, lag, max_delta_torque)
    bounds = _variable_bounds(n, max_tilt, max_torque, int(round(reaction_delay / step)))
    cost = np.zeros(nv)
    cost[pi] = 1.0
    result = linprog(cost, A_ub=ub, b_ub=bub, A_eq=eq, b_eq=beq,
                     bounds=bounds, method='highs')
    if result.status != 0:
        # HiGHS' automatic choice (dual simplex) sometimes stops without a status on
        # these LPs, where its interior-point method solves them.
        result = linprog(cost, A_ub=ub, b_ub=bub, A_eq=eq, b_eq=beq,
                         bounds=bounds, method='highs-ipm')
    if result.status != 0:
        raise ValueError(f'push_excursion_bound: no torque sequence within the limits '
                         f'brings a push of {dv} m/s to rest in {horizon} s '
                         f'({result.message})')
    states = result.x[:nz].reshape(n + 1, 4)
    return PushBound(float(max(result.x[pi], 0.0)), times, states[:, 0], states[:, 2],
                     result.x[nz:nz + nt], result.message)


def _variable_bounds(n: int, max_tilt: float, max_torque: float, idle: int) -> list:
    """Return the boxes of z_0..z_n, τ_0..τ_{n−1}, P: |θ|, |τ|, at rest at the end.

    The first ``idle`` torques are 0 (the reaction delay).
    """
    nz = 4 * (n + 1)
    bounds = [(None, None)] * nz + [(-max_torque, max_torque)] * n + [(None, None)]
    for i in range(1, n + 1):
        bounds[4 * i + 2] = (-max_tilt, max_tilt)
    for j in (1, 2, 3):                              # at rest at the end, torque off
        bounds[4 * n + j] = (0.0, 0.0)
    for k in list(range(min(idle, n))) + [n - 1]:
        bounds[nz + k] = (0.0, 0.0)
    return bounds


def _check_arguments(values: dict) -> None:
    """Raise ValueError unless the arguments of :func:`push_excursion_bound` are usable."""
    for name, value in values.items():
        if not (isinstance(value, (int, float)) and math.isfinite(value)):
            raise ValueError(f'push_excursion_bound: {name} must be a finite number, '
                             f'got {value!r}')
        if name != 'delta_v' and value <= 0.0:
            raise ValueError(f'push_excursion_bound: {name} must be > 0, got {value!r}')
    step, push_time, delta_period, horizon = (values[name] for name in (
        'step', 'push_time', 'delta_period', 'horizon'))
    if not push_time <= horizon or not step <= min(push_time, delta_period):
        raise ValueError('push_excursion_bound: need step <= push_time, delta_period and '
                         f'push_time <= horizon (got {step}, {push_time}, {delta_period}, '
                         f'{horizon})')


def _discretised(params: ModelParams, step: float, model: str) -> tuple:
    """Return (Ad, Bd, Ed): the exact zero-order-hold discretisation over one step."""
    from scipy.linalg import expm

    a, b, e = linear_model(params, model)
    big = np.zeros((6, 6))
    big[:4, :4], big[:4, 4], big[:4, 5] = a * step, b * step, e * step
    phi = expm(big)
    return phi[:4, :4], phi[:4, 4], phi[:4, 5]


def _dynamics(ad, bd, ed, push: np.ndarray, n: int, nv: int) -> tuple:
    """Return the equalities of the motion: z_{k+1} − Ad z_k − Bd τ_k = Ed d_k.

    And z_0 = 0: at rest on the reference.
    """
    from scipy import sparse

    nz = 4 * (n + 1)
    k = np.arange(n)
    rows, cols, vals = [np.arange(4)], [np.arange(4)], [np.ones(4)]
    for j in range(4):
        row = 4 * (k + 1) + j
        rows.append(row), cols.append(row), vals.append(np.ones(n))
        for i in range(4):
            if ad[j, i] != 0.0:
                rows.append(row), cols.append(4 * k + i), vals.append(np.full(n, -ad[j, i]))
        rows.append(row), cols.append(nz + k), vals.append(np.full(n, -bd[j]))
    eq = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                           shape=(4 * (n + 1), nv))
    beq = np.zeros(4 * (n + 1))
    beq[4:] = (ed[None, :] * push[:, None]).ravel()
    return eq, beq


def _peak_and_rate_limits(n: int, nv: int, lag: int, max_delta_torque: float) -> tuple:
    """Return the inequalities e_k − P ≤ 0; ±(τ_k − τ_{k−lag}) ≤ Δτ (τ = 0 before the push)."""
    from scipy import sparse

    nz, nt = 4 * (n + 1), n
    pi = nz + nt
    k = np.arange(n)
    late = k[k >= lag]
    rows = [k, k, n + k, n + late, 2 * n + k, 2 * n + late]
    cols = [4 * (k + 1), np.full(n, pi), nz + k, nz + late - lag, nz + k, nz + late - lag]
    vals = [np.ones(n), -np.ones(n), np.ones(n), -np.ones(len(late)), -np.ones(n),
            np.ones(len(late))]
    ub = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                           shape=(3 * n, nv))
    return ub, np.concatenate([np.zeros(n), np.full(2 * n, max_delta_torque)])


#: Seconds after the start at which the benchmark's push comes: the start from rest on the
#: reference has settled by then (the paper scenario converges within 5.3 s).
PUSH_AT = 10.0


def push_scenario_mapping(reference: str, plant: str = 'paper', *, mismatch: bool = False,
                          noise: bool = False, delta_v: float = 1.0, push_width: float = 0.1,
                          speed: float = 0.5, duration: float = 20.0) -> dict:
    """Return the scenario mapping of one push-recovery case (``reference``: line or circle).

    Starts on the reference at rest; the push, delta_v / push_width for push_width [s], at
    :data:`PUSH_AT`. ``mismatch``: body 20 % heavier, centre of mass 10 % higher (the plant's
    parameters; the controllers keep the nominal model); ``noise``: a consumer IMU's
    (pitch 0.002 rad, gyro 0.01 rad/s), as the robustness suite's.
    """
    if reference == 'line':
        ref = {'kind': 'line', 'line_speed': speed}
    elif reference == 'circle':
        ref = {'kind': 'circle', 'circle_speed': speed}
    else:
        raise ValueError(f"reference must be 'line' or 'circle', got {reference!r}")
    plant_section: dict = {'model': plant}
    if mismatch:
        base = ModelParams()
        plant_section['parameters'] = {'body_mass': 1.2 * base.body_mass,
                                       'com_height': 1.1 * base.com_height}
    mapping = {
        'name': f'push_{reference}_{plant}' + ('_mismatch' if mismatch else '')
                + ('_noise' if noise else ''),
        'duration': duration,
        'initial_state': {'pose_relative_to_reference': True, 'pose': [0.0, 0.0, 0.0],
                          'x_v': 0.0, 'theta': 0.0},
        'reference': ref,
        'plant': plant_section,
        'disturbances': {'yaw': [], 'tilt': [], 'longitudinal': [
            {'kind': 'pulse', 'amplitude': delta_v / push_width, 'start_time': PUSH_AT,
             'width': push_width}]},
    }
    if noise:
        mapping['sensors'] = {'imu_pitch_noise_std': 0.002, 'gyro_noise_std': 0.01}
    return mapping


def measured_excursion(record, push_at: float = PUSH_AT) -> float:
    """Peak along-track error [m] ahead of the reference after ``push_at``, less the one before.

    The along-track error of the axle centre in the reference's frame, (p − p_r) · (cos ϕr,
    sin ϕr), from the record's truth and reference (sampled at the control ticks); the
    value at the push is subtracted (the tracking error the push found).
    """
    truth, ref = record['truth'], record['reference']
    t = np.asarray(ref['t'])
    x = np.interp(t, truth['t'], truth['x'])
    y = np.interp(t, truth['t'], truth['y'])
    along = ((x - ref['x']) * np.cos(ref['phi']) + (y - ref['y']) * np.sin(ref['phi']))
    after = t >= push_at
    if not after.any():
        raise ValueError(f'the record ends at {t[-1]:.2f} s, before the push at {push_at} s')
    at_push = float(np.interp(push_at, t, along))
    return float(np.max(along[after]) - at_push)


#: [m/s], [rad]: the largest speed error and tilt at the push of a run "at rest on its
#: reference", the state the bound starts from. A noisy run meets the push up to 0.1 m/s
#: and 0.04 rad off it (docs/benchmarks.md): its ratio is then only indicative.
AT_REST_SPEED, AT_REST_TILT = 0.02, 0.01


def state_at_push(record, push_at: float = PUSH_AT) -> tuple[float, float]:
    """Return (υ − υr [m/s], θ [rad]) of the true plant at ``push_at``.

    The bound starts at rest on the reference (υ = υr, θ = 0); a run that meets the push
    elsewhere is compared with a bound that is not its own.
    """
    truth, ref = record['truth'], record['reference']
    speed = float(np.interp(push_at, truth['t'], truth['v']))
    return (speed - float(np.interp(push_at, ref['t'], ref['v'])),
            float(np.interp(push_at, truth['t'], truth['theta'])))


#: The benchmark's cases: (reference, plant model, mismatch, noise).
PUSH_CASES = tuple((reference, plant, mismatch, noise)
                   for reference in ('line', 'circle')
                   for plant, mismatch in (('paper', False), ('full', True))
                   for noise in (False, True))


def scenario_bound(scenario, delta_v: float, push_time: float) -> PushBound:
    """Return the bound for the true plant of ``scenario`` and its MPC limits (``mpc.*``).

    The true plant's parameters and equations: the full model's for 'full' and the engine
    models, which have the motors' reaction torque on the body.
    """
    from wip_sim.core.plant import equation_model

    mpc = scenario.mpc
    return push_excursion_bound(scenario.plant.parameters, delta_v, push_time=push_time,
                                max_tilt=mpc.max_tilt, max_torque=mpc.max_drive_torque,
                                max_delta_torque=mpc.max_delta_torque,
                                delta_period=mpc.sampling_period,
                                model=equation_model(scenario.plant.model.model))


#: Sensor-noise seeds of each noisy case: the noise moves the state the push finds, and
#: one seed's excursion says little (docs/benchmarks.md), so the median counts.
NOISE_SEEDS = (0, 1, 2, 3, 4)


def push_recovery_rows(cases=PUSH_CASES, delta_v: float = 1.0, push_width: float = 0.1,
                       overrides: dict | None = None, seeds=NOISE_SEEDS) -> list[dict]:
    """Run each case in-process; its measured excursion, the bound and their ratio.

    ``overrides``: scenario keys merged into every case (e.g. a controller setting). A
    case with noise runs once per seed of ``seeds``: its excursion is the median, with
    the least and largest ratio (a clean case runs once: it does not depend on the seed).
    """
    from wip_sim.core.scenario import scenario_from_mapping

    bounds: dict = {}
    rows = []
    for reference, plant, mismatch, noise in cases:
        mapping = push_scenario_mapping(reference, plant, mismatch=mismatch, noise=noise,
                                        delta_v=delta_v, push_width=push_width)
        for key, value in (overrides or {}).items():
            mapping[key] = ({**mapping[key], **value} if isinstance(value, dict)
                            and isinstance(mapping.get(key), dict) else value)
        scenario = scenario_from_mapping(mapping)
        key = (scenario.plant.parameters, scenario.plant.model.model, scenario.mpc.max_tilt,
               scenario.mpc.max_drive_torque, scenario.mpc.max_delta_torque,
               scenario.mpc.sampling_period)
        if key not in bounds:
            bounds[key] = scenario_bound(scenario, delta_v, push_width).excursion
        results = [_excursion(scenario_from_mapping({**mapping, 'seed': seed}))
                   for seed in (seeds if noise else (mapping.get('seed', 0),))]
        runs = [excursion for excursion, _ in results]
        off_speed = max(abs(state[0]) for _, state in results)
        off_tilt = max(abs(state[1]) for _, state in results)
        fell = any(math.isinf(run) for run in runs)
        measured = math.inf if fell else float(np.median(runs))
        rows.append({'reference': reference, 'plant': plant, 'mismatch': mismatch,
                     'noise': noise, 'fell': fell, 'measured_m': measured,
                     'bound_m': bounds[key], 'ratio': measured / bounds[key],
                     'runs': len(runs), 'ratio_min': min(runs) / bounds[key],
                     'ratio_max': max(runs) / bounds[key],
                     # The worst of the runs: how far from rest on the reference the push
                     # found the vehicle (the bound's start), and whether all were at rest.
                     'speed_error_at_push': off_speed, 'tilt_at_push': off_tilt,
                     'at_rest': off_speed <= AT_REST_SPEED and off_tilt <= AT_REST_TILT})
    return rows


def _excursion(scenario) -> tuple[float, tuple[float, float]]:
    """Return the measured excursion of one run of ``scenario`` [m] (inf: it fell).

    Also :func:`state_at_push` of the run.
    """
    from wip_sim.core.runner import run_scenario

    result = run_scenario(scenario)
    state = state_at_push(result.record)
    return (math.inf if result.fell else measured_excursion(result.record)), state
