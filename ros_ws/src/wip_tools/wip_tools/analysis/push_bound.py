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
after ``reaction_delay``), starting from rest on the reference (or from a given speed
error, tilt and tilt rate, with the torques of the last Ts before the push), chooses the
drive torque τυ(t) piecewise constant on a fine grid (``step``) under

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
    speed: np.ndarray | None = None      #: u = υ − υr of the optimal sequence [m/s]
    tilt_rate: np.ndarray | None = None  #: θ̇ of the optimal sequence [rad/s]


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
                         model: str = 'paper', reaction_delay: float = 0.0,
                         initial_state=(0.0, 0.0, 0.0), earlier_torques=()) -> PushBound:
    """Return the least peak excursion ahead of the reference after a push.

    ``delta_v`` [m/s]: the push's speed change, a constant acceleration delta_v / push_time
    over ``push_time`` [s] (the paper's 10 m/s² for 0.1 s: 1 m/s); negative pushes back
    (the excursion is then behind, reported positive: the model is symmetric).
    ``max_torque``: |τυ| = |τl + τr| [N m] (two wheels of 15 N m: 30);
    ``max_delta_torque`` [N m] per ``delta_period`` [s]; ``step`` [s]: the grid;
    ``horizon`` [s]: the time by which it must be at rest; ``model``: the plant's
    equations, 'paper' or 'full' (:func:`linear_model`); ``reaction_delay`` [s]: the
    torque stays as it was (0, or the last of ``earlier_torques``) for this long after
    the push starts (a controller that must first see the push; rounded to the grid).
    ``initial_state``: (u [m/s], θ [rad], θ̇ [rad/s]) when the push starts (e = 0 there:
    the excursion is counted from it); ``earlier_torques`` [N m]: τυ on the grid over the
    last ``delta_period`` before the push, oldest first (missing ones: 0), which the
    rate limit's first windows reach back to. ValueError on bad arguments or when no
    sequence can bring it to rest by then (the push is beyond the limits).
    """
    _check_arguments(dict(delta_v=delta_v, push_time=push_time, max_tilt=max_tilt,
                          max_torque=max_torque, max_delta_torque=max_delta_torque,
                          delta_period=delta_period, step=step, horizon=horizon))
    n = int(round(horizon / step))
    times = step * np.arange(n + 1)
    if not (math.isfinite(reaction_delay) and 0.0 <= reaction_delay < horizon):
        raise ValueError(f'push_excursion_bound: reaction_delay must be in [0, horizon), '
                         f'got {reaction_delay!r}')
    lag = max(1, int(round(delta_period / step)))
    # The model is odd in (push, state, torque): a push back is the mirror of one ahead.
    sign = -1.0 if delta_v < 0.0 else 1.0
    start = sign * _initial_state(initial_state)
    earlier = sign * _earlier_torques(earlier_torques, lag)
    dv = abs(float(delta_v))
    if dv == 0.0 and not (np.any(start) or np.any(earlier)):
        zeros = np.zeros(n + 1)
        return PushBound(0.0, times, zeros, zeros.copy(), np.zeros(n), 'no push',
                         zeros.copy(), zeros.copy())
    push = np.where(times[:-1] < push_time - 1e-9, dv / push_time, 0.0)
    result, nz = _solve(params, model, step, push, start, earlier,
                        (max_tilt, max_torque, max_delta_torque),
                        int(round(reaction_delay / step)))
    if result.status != 0:
        raise ValueError(f'push_excursion_bound: no torque sequence within the limits '
                         f'brings a push of {dv} m/s to rest in {horizon} s '
                         f'({result.message})')
    states = sign * result.x[:nz].reshape(n + 1, 4)
    return PushBound(float(max(result.x[-1], 0.0)), times, states[:, 0], states[:, 2],
                     sign * result.x[nz:nz + n], result.message, states[:, 1], states[:, 3])


def _initial_state(values) -> np.ndarray:
    """Return z_0 = (0, u, θ, θ̇) from (u, θ, θ̇), or raise ValueError."""
    state = np.asarray(values, dtype=float)
    if state.shape != (3,) or not np.all(np.isfinite(state)):
        raise ValueError('push_excursion_bound: initial_state must be three finite numbers '
                         f'(u, theta, theta_dot), got {values!r}')
    return np.concatenate([[0.0], state])


def _earlier_torques(values, lag: int) -> np.ndarray:
    """Return the ``lag`` torques before the push, oldest first (0 where not given)."""
    torques = np.asarray(values, dtype=float).ravel()
    if torques.size > lag or not np.all(np.isfinite(torques)):
        raise ValueError(f'push_excursion_bound: earlier_torques must be at most {lag} '
                         f'finite numbers (delta_period / step), got {values!r}')
    return np.concatenate([np.zeros(lag - torques.size), torques])


def _solve(params, model, step, push, start, earlier, limits, idle) -> tuple:
    """Return (scipy's result, the number of state variables) of the LP (module docstring).

    ``limits``: (θmax, τmax, Δτmax); the first ``idle`` torques hold the last earlier one.
    """
    from scipy.optimize import linprog

    max_tilt, max_torque, max_delta_torque = limits
    n = push.size
    ad, bd, ed = _discretised(params, step, model)
    # Sparse, not condensed: the tilt's unstable pole (√a_θ ≈ 4.6 /s) makes a condensed
    # prediction over seconds ill-conditioned (e^{4.6 · 8} ≈ 1e16). Variables:
    # z_0 .. z_n (4 each), τ_0 .. τ_{n-1}, P; minimise P.
    nz, nt = 4 * (n + 1), n
    nv = nz + nt + 1
    eq, beq = _dynamics(ad, bd, ed, push, n, nv)
    beq[:4] = start
    ub, bub = _peak_and_rate_limits(n, nv, earlier.size, max_delta_torque)
    # The first windows reach back before the push: ±(τ_k − τ_{k−lag}) ≤ Δτ with the
    # earlier torque on the right.
    first = np.arange(min(earlier.size, n))
    bub[n + first] += earlier[first]
    bub[2 * n + first] -= earlier[first]
    bounds = _variable_bounds(n, max_tilt, max_torque, idle, earlier[-1])
    cost = np.zeros(nv)
    cost[-1] = 1.0
    # HiGHS sometimes stops on these LPs without a status (numerical trouble, 'model
    # status Unknown') where the same LP solves without its presolve or with a tighter
    # tolerance (a noisy push case's state: its automatic choice, dual simplex and interior
    # point all stop; without presolve or at 1e-9 it solves, the answers within 1e-8 m).
    for method, options in _LP_METHODS:
        result = linprog(cost, A_ub=ub, b_ub=bub, A_eq=eq, b_eq=beq, bounds=bounds,
                         method=method, options=options)
        if result.status == 0:
            break
    return result, nz


#: (method, options) of scipy's linprog tried in turn by :func:`_solve`.
_LP_METHODS = (('highs', {}), ('highs-ipm', {}), ('highs', {'presolve': False}),
               ('highs-ds', {'dual_feasibility_tolerance': 1e-9}),
               ('highs-ipm', {'primal_feasibility_tolerance': 1e-9}))


def _variable_bounds(n: int, max_tilt: float, max_torque: float, idle: int,
                     held: float = 0.0) -> list:
    """Return the boxes of z_0..z_n, τ_0..τ_{n−1}, P: |θ|, |τ|, at rest at the end.

    The first ``idle`` torques are ``held`` (the reaction delay).
    """
    nz = 4 * (n + 1)
    bounds = [(None, None)] * nz + [(-max_torque, max_torque)] * n + [(None, None)]
    for i in range(1, n + 1):
        bounds[4 * i + 2] = (-max_tilt, max_tilt)
    for j in (1, 2, 3):                              # at rest at the end, torque off
        bounds[4 * n + j] = (0.0, 0.0)
    for k in range(min(idle, n)):
        bounds[nz + k] = (held, held)
    bounds[nz + n - 1] = (0.0, 0.0)
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

    And z_0 = 0: at rest on the reference (the caller may set another start in beq[:4]).
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
