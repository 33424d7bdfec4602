r"""The simulated WIP: the paper model (1) of [1]_ or a full Lagrange–d'Alembert model.

State layout (:mod:`.model`): ``(x, y, ϕ, x_v, θ, ω, υ, θ̇)``. Both models share the
kinematics

.. math::

    \dot x = \upsilon \cos\phi, \quad \dot y = \upsilon \sin\phi, \quad
    \dot\phi = \omega, \quad \dot x_v = \upsilon, \quad \dot\theta = \dot\theta

and differ in the dynamics of (ω, υ, θ̇). Disturbances enter both models as in eq. (1):
d1 [rad/s²] adds to ω̇, d2 [m/s²] to υ̇, d3 [rad/s²] to θ̈ (τd1..τd3 of [1]_).

Model ``'paper'``
    Eq. (1) of [1]_ exactly, with τυ = τl + τr and τω = τr − τl (REP 103, see
    :mod:`.model`); the tests check it against :func:`.model.nominal_terms`.

Model ``'full'``: derivation
    Same bodies and parameters as the reading of (1) in docs/paper.md §1 (``ModelParams``):

    - body (pendulum): mass m_p, centre of mass at distance l above the axle along
      the body axis, pitch inertia I_c about its centre of mass, tilt θ (positive
      leaning forward, a rotation about the axle axis e_lat = left);
    - chassis: point mass m_c on the axle (it turns with the body; on the axle it adds
      nothing to the pitch inertia);
    - two wheels of mass m_w, spin inertia J_ω, radius r, at ±d/2 along the axle;
    - J_υ: yaw inertia about the vertical of everything that is not modelled above,
      i.e. the body's own yaw inertia about its centre of mass (assumed the same
      about the body's long axis and its forward axis, I_x = I_z, which is what makes
      it independent of θ as in (1)), the chassis and the wheels' diametral inertia.

    Generalised coordinates q = (x, y, ϕ, θ, φ_l, φ_r), φ_i the absolute spin angle of
    wheel i about the axle (positive rolls forward). Unit vectors e_f = (cos ϕ, sin ϕ, 0),
    e_lat = (−sin ϕ, cos ϕ, 0), e_z. Positions: axle centre p = (x, y, r); body centre of
    mass p + l sinθ e_f + l cosθ e_z; wheel centres p ± (d/2) e_lat.

    Lagrangian L = T − V with V = m_p g l cosθ and

    .. math::

        T = \tfrac12 m_p |\dot p_{cm}|^2 + \tfrac12 I_c \dot\theta^2
          + \tfrac12 m_c |\dot p|^2
          + \sum_{i=l,r} \big(\tfrac12 m_w |\dot p_i|^2
                                 + \tfrac12 J_\omega \dot\varphi_i^2\big)
          + \tfrac12 J_\upsilon \dot\phi^2 .

    Nonholonomic constraints (no lateral slip, rolling without slip of each wheel):
    ẋ sinϕ − ẏ cosϕ = 0, r φ̇_l = υ − (d/2) ω, r φ̇_r = υ + (d/2) ω with υ = ẋ cosϕ + ẏ sinϕ.
    Hence q̇ = S(q) ν with quasi-velocities ν = (ω, υ, θ̇).

    Generalised forces: motor i applies τ_i to wheel i about e_lat and, its stator being
    fixed to the body, −τ_i to the body (the reaction torque): virtual work
    δW = Σ τ_i (δφ_i − δθ). Lagrange–d'Alembert, Sᵀ (d/dt ∂L/∂q̇ − ∂L/∂q − Q) = 0, gives
    (derived and checked with sympy; the kinetic energy in ν equals E − V of docs/paper.md §1)

    .. math::

        J(\theta)\dot\omega + m_p l^2 \sin 2\theta\, \omega\dot\theta
            + m_p l \sin\theta\, \upsilon\omega = \frac{d}{2r}\tau_\omega

        m_v \dot\upsilon + m_p l \cos\theta\, \ddot\theta
            - m_p l \sin\theta\,(\dot\theta^2 + \omega^2) = \tau_\upsilon / r

        m_p l \cos\theta\, \dot\upsilon + J_\theta \ddot\theta - m_p g l \sin\theta
            - m_p l^2 \sin\theta\cos\theta\, \omega^2 = -\tau_\upsilon

    with J(θ) = J_ϕ + m_p l² sin²θ, m_v, J_θ, J_ϕ as in ``ModelParams``. Solving the
    2×2 block (determinant Ω) gives g2 = (J_θ + m_p l r cosθ)/(Ω r),
    g3 = −(m_v r + m_p l cosθ)/(Ω r), as docs/paper.md §1 lists.

    Differences from (1), all found by the derivation:

    - reaction torque −τυ on the body pitch (changes g2 and g3, see above);
    - centrifugal term −m_p l ω² sinθ in the forward equation;
    - Coriolis term +m_p l υ ω sinθ on the left of the yaw equation. It is gyroscopic
      with the centrifugal term (their power υ(−m_p l ω² sinθ) + ω(m_p l υ ω sinθ) is
      zero), so E is conserved; the yaw momentum J(θ) ω is **not** conserved in the
      full model: d/dt (J(θ) ω) = −m_p l sinθ υ ω + (d/2r) τω (the ground's lateral
      and longitudinal forces at the wheels act on it);
    - **yaw input gain g1 = d / (2 r J(θ)), half of the paper's d / (r J(θ))**: with d
      the distance between the wheels (as in J_ϕ and in the odometry), the wheel
      forces τ_i / r act at ±d/2, so their yaw moment is (τr − τl) d / (2r). The paper's
      g1 is twice the physical value (it would be right if d were the half-track). This
      follows the derivation; the controllers keep using (1).

    Energy: E = ½ m_v υ² + m_p l cosθ υ θ̇ + ½ J_θ θ̇² + ½ J(θ) ω² + m_p g l cosθ for
    both models (same kinetic energy), conserved with zero inputs and disturbances.

Both models share one right-hand side: the full model's extra terms carry
coefficients that are zero for the paper model, and the yaw gain is d/r or d/(2r).

Implementation: the RK4 steps are compiled with numba (:mod:`.plant_rk4`, ``cache=True``):
the simulator takes 90 000 steps per 90 s run, and the interpreted scalar RK4 step
(about 3 µs, 16 µs per control period of 5 steps) was the largest cost of the
in-process runner; compiled, a control period costs about 1 µs. No ``fastmath``: the
compiled step performs the same IEEE operations in the same order as the Python
expression it replaced (checked bit for bit over 20 000 steps), so results are
unchanged. The first call in a process loads the compiled code from numba's cache
(``__pycache__``), or compiles it (about 1 s) when the cache is missing or stale;
:class:`Plant` does that at construction, not at its first step.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from typing import Callable, Sequence

import numpy as np

from wip_runtime.config import param
from wip_control.core.model import STATE_SIZE, THETA, input_gains
from wip_description.params import ModelParams

#: Plant models integrated here: the paper's eq. (1) and the full Lagrange–d'Alembert model.
EQUATION_MODELS = ('paper', 'full')
#: Plant models of a physics engine, by the module that builds them. The module is imported
#: only when a scenario chooses the model (:func:`scenario_plant`): the controllers a robot
#: installs (wip_control alone) need neither the simulator package nor the engine.
ENGINE_MODELS = {'mujoco': 'wip_sim.mujoco_plant'}
#: Every plant model a scenario may choose.
MODELS = EQUATION_MODELS + tuple(ENGINE_MODELS)

#: Default tilt [rad] past which :meth:`Plant.has_fallen` reports a fall (0.9 · π/2).
DEFAULT_FALL_LIMIT = 0.45 * math.pi

Disturbance = Sequence[float]
DisturbanceFunction = Callable[[float], Sequence[float]]


@dataclasses.dataclass(frozen=True)
class PlantParams:
    """Which dynamics the simulated plant integrates."""

    model: str = param('paper', '1', "plant dynamics: 'paper' = eq. (1), 'full' = "
                       "Lagrange-d'Alembert model, 'mujoco' = its bodies in MuJoCo with wheel "
                       'contacts (plant.contact); docs/decisions/sim-parameters.md',
                       choices=MODELS)
    wheel_friction: float = param(0.0, 'N m s/rad', 'viscous friction of each wheel on its '
                                  'axle: a torque -b (wheel rate - body tilt rate) between '
                                  'wheel and body, acting as the motor torque does',
                                  minimum=0.0, maximum=10.0)
    motor_time_constant: float = param(0.0, 's', 'first-order lag of each wheel torque '
                                       'behind its command (motor current loop); 0 = none',
                                       minimum=0.0, maximum=0.1)


def equation_model(model: str) -> str:
    """Return the equation model whose equations describe ``model``.

    ``model`` itself, or 'full' for an engine model (the same bodies; used for the
    metrics' lumped disturbances and gains).
    """
    return 'full' if model in ENGINE_MODELS else model


def scenario_plant(scenario):
    """Return the true plant of ``scenario`` (a :class:`.scenario.Scenario`).

    Model, parameters and, for an engine model, contact and terrain, stepped at the
    scenario's plant rate. Equation models give a :class:`Plant`; an engine model an
    object with the same ``hold_floats`` (and ``has_fallen``).
    """
    section = scenario.plant
    model = section.model.model
    if model not in ENGINE_MODELS:
        return Plant(section.parameters, model, section.model.wheel_friction)
    try:
        module = importlib.import_module(ENGINE_MODELS[model])
    except ImportError as err:      # the simulator package is not installed
        raise ImportError(f'plant model {model!r} needs {ENGINE_MODELS[model]} (the '
                          f'wip_sim package): {err}') from err
    return module.make_plant(section.parameters, section.contact,
                             scenario.control_period / scenario.rates.substeps,
                             section.terrain, section.model.wheel_friction)


def tilt_pole(params: ModelParams, model: str = 'paper') -> float:
    r"""Unstable pitch pole [rad/s] of the linearisation at rest (θ = 0, all rates 0).

    .. math:: \lambda = \sqrt{m_v m_p g l / \Omega_0}, \quad
              \Omega_0 = m_v J_\theta - m_p^2 l^2

    Identical for both models: their extra terms are quadratic in the velocities
    (ω², υω) or act through the input, so they vanish from the linearisation at rest
    with zero input. About 4.58 rad/s with the default parameters.
    """
    _check_model(equation_model(model))
    p = params
    return math.sqrt(p.effective_mass * p.body_mass * p.gravity * p.com_height
                     / p.omega_denominator(0.0))


def plant_input_gains(params: ModelParams, model: str,
                      theta: float) -> tuple[float, float, float]:
    """(g1, g2, g3) of the plant ``model`` ('paper' or 'full') at tilt θ [rad]."""
    if equation_model(model) == 'full':
        return full_input_gains(params, theta)
    return input_gains(params, theta)


def full_input_gains(params: ModelParams, theta: float) -> tuple[float, float, float]:
    """(g1, g2, g3) of the full model at tilt θ [rad] (units as in eq. (1)).

    g1 = d / (2 r J(θ)), g2 = (J_θ + m_p l r cosθ)/(Ω r), g3 = −(m_v r + m_p l cosθ)/(Ω r).
    """
    p = params
    mp, l, r = p.body_mass, p.com_height, p.wheel_radius  # noqa: E741 - the paper's symbol
    s, c = math.sin(theta), math.cos(theta)
    big_omega = p.omega_denominator(theta)
    g1 = p.track_width / (2.0 * r * (p.yaw_inertia_total + mp * l * l * s * s))
    g2 = (p.pitch_inertia + mp * l * r * c) / (big_omega * r)
    g3 = -(p.effective_mass * r + mp * l * c) / (big_omega * r)
    return g1, g2, g3


def _check_model(model: str) -> None:
    if model not in EQUATION_MODELS:
        raise ValueError(f'unknown plant model {model!r}; expected one of '
                         f'{list(EQUATION_MODELS)} (engine models: scenario_plant)')


def _state_floats(state: Sequence[float]) -> list[float]:
    """Return the 8 state entries as Python floats; ValueError on a wrong size or NaN/inf."""
    if isinstance(state, np.ndarray):
        if state.shape != (STATE_SIZE,):
            raise ValueError(f'plant state must have shape ({STATE_SIZE},), got {state.shape}')
        values = state.tolist()
    else:
        values = [float(v) for v in state]
        if len(values) != STATE_SIZE:
            raise ValueError(f'plant state must have {STATE_SIZE} entries, got {len(values)}')
    if not math.isfinite(math.fsum(values)):
        raise ValueError(f'plant state must be finite, got {values}')
    return values


def _check_inputs(tau_left: float, tau_right: float, disturbance: Disturbance) -> tuple:
    d1, d2, d3 = disturbance
    if not math.isfinite(tau_left + tau_right + d1 + d2 + d3):
        raise ValueError('wheel torques and disturbances must be finite, got '
                         f'tau_left={tau_left!r}, tau_right={tau_right!r}, '
                         f'disturbance={tuple(disturbance)!r}')
    return float(tau_left), float(tau_right), float(d1), float(d2), float(d3)


class Plant:
    """Simulated WIP: right-hand side, RK4 step, energy and yaw momentum.

    Parameters
    ----------
    params : true physical parameters (may differ from the controllers' nominal ones).
    model : ``'paper'`` (eq. (1)) or ``'full'`` (see the module docstring).

    :meth:`hold_floats` integrates, without input checks (the in-process runner);
    :func:`simulate_hold` checks the inputs and the result around it.
    """

    def __init__(self, params: ModelParams, model: str = 'paper',
                 wheel_friction: float = 0.0) -> None:
        _check_model(model)
        if not (math.isfinite(wheel_friction) and wheel_friction >= 0.0):
            raise ValueError(f'wheel_friction must be finite and >= 0, got {wheel_friction!r}')
        self.params = params
        self.model = model
        self.wheel_friction = float(wheel_friction)
        p = params
        mp, l, g, r = p.body_mass, p.com_height, p.gravity, p.wheel_radius  # noqa: E741 - the paper's symbol
        full = model == 'full'
        # Constants of the right-hand side, bound as closure variables of the stepper.
        self._consts = dict(
            mv=p.effective_mass, jt=p.pitch_inertia, jphi=p.yaw_inertia_total,
            mpl=mp * l, mpl2=mp * l * l, mpgl=mp * g * l,
            mvjt=p.effective_mass * p.pitch_inertia, mpl_sq=(mp * l) ** 2, inv_r=1.0 / r,
            # Yaw gain: d/r in (1), d/(2r) from the derivation.
            yaw_gain=p.track_width / (2.0 * r if full else r),
            # Full-model extra terms: coefficients are 0 for the paper model.
            k_centrifugal=1.0 if full else 0.0,     # m_p l sinθ ω² in the forward eq.
            k_coriolis=mp * l if full else 0.0,     # m_p l sinθ υ ω in the yaw eq.
            k_reaction=1.0 if full else 0.0,        # −τυ on the body pitch
            # Axle friction b: the wheels' rates relative to the body are
            # (υ ∓ (d/2) ω)/r − θ̇, so τυ loses 2b (υ/r − θ̇) and τω loses b d ω / r.
            friction_v=2.0 * wheel_friction, friction_w=wheel_friction * p.track_width / r)
        self._accelerations = _make_accelerations(**self._consts)
        self._accelerations_array = _make_accelerations(**self._consts, sin=np.sin,
                                                        cos=np.cos)
        # The same constants, in the order of _rk4_hold's first argument.
        self._k = tuple(float(self._consts[name]) for name in _CONSTANT_NAMES)
        _load_integrator()

    # ------------------------------------------------------------------ dynamics

    def derivative(self, state: Sequence[float], tau_left: float, tau_right: float,
                   disturbance: Disturbance = (0.0, 0.0, 0.0)) -> np.ndarray:
        """State derivative ẋ (8,) at ``state`` for wheel torques [N·m] and (d1, d2, d3)."""
        _, _, phi, _, th, om, v, thd = _state_floats(state)
        tl, tr, d1, d2, d3 = _check_inputs(tau_left, tau_right, disturbance)
        tv, tw = tl + tr, tr - tl
        omd, vd, thdd = self._accelerations(th, om, v, thd, tv, tw)
        return np.array((v * math.cos(phi), v * math.sin(phi), om, v, thd,
                         omd + d1, vd + d2, thdd + d3))

    def accelerations_array(self, theta: np.ndarray, omega: np.ndarray, v: np.ndarray,
                            theta_dot: np.ndarray, tau_left: np.ndarray,
                            tau_right: np.ndarray) -> tuple[np.ndarray, ...]:
        """(ω̇, υ̇, θ̈) at many states at once (arrays of one shape), no disturbance.

        The expressions of :meth:`derivative`, evaluated by numpy (equal to it to
        rounding); for the metrics of a whole run, 18 000 states per 90 s.
        """
        return self._accelerations_array(theta, omega, v, theta_dot, tau_left + tau_right,
                                         tau_right - tau_left)

    def hold_floats(self, state: tuple, tau_left: float, tau_right: float,
                    disturbance: np.ndarray, dt: float) -> tuple:
        """``len(disturbance)`` RK4 steps of ``dt`` [s] on a float 8-tuple, no checks.

        The plant's one integration entry. ``disturbance`` is a C-contiguous float array
        (n, 3) of (d1, d2, d3) per step. The caller checks the result for finiteness;
        :func:`simulate_hold` checks the inputs and the result around it.
        """
        return _rk4_hold(self._k, *state, tau_left, tau_right, disturbance, dt)

    # ------------------------------------------------------------------ invariants

    def energy(self, state: Sequence[float]) -> float:
        """Total mechanical energy [J], the same expression for both models.

        E = ½ m_v υ² + m_p l cosθ υ θ̇ + ½ J_θ θ̇² + ½ (J_ϕ + m_p l² sin²θ) ω² + m_p g l cosθ.
        """
        _, _, _, _, th, om, v, thd = _state_floats(state)
        k = self._consts
        s, c = math.sin(th), math.cos(th)
        return (0.5 * k['mv'] * v * v + k['mpl'] * c * v * thd + 0.5 * k['jt'] * thd * thd
                + 0.5 * (k['jphi'] + k['mpl2'] * s * s) * om * om + k['mpgl'] * c)

    def yaw_momentum(self, state: Sequence[float]) -> float:
        """(J_ϕ + m_p l² sin²θ) ω [kg m²/s].

        Conserved by the paper model with zero input; in the full model its rate is
        −m_p l sinθ υ ω + (d/2r) τω (see the module docstring).
        """
        _, _, _, _, th, om, _, _ = _state_floats(state)
        k = self._consts
        s = math.sin(th)
        return (k['jphi'] + k['mpl2'] * s * s) * om

    @staticmethod
    def has_fallen(state: Sequence[float], limit: float = DEFAULT_FALL_LIMIT) -> bool:
        """Return True if |θ| ≥ ``limit`` [rad]."""
        return abs(float(state[THETA])) >= limit

    def linearize(self, state_eq: Sequence[float], tau_left: float = 0.0,
                  tau_right: float = 0.0, disturbance: Disturbance = (0.0, 0.0, 0.0),
                  step: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
        """Jacobians (A (8×8), B (8×2) w.r.t. (τl, τr)) by central differences.

        ``step`` is the perturbation of each variable (rad, m, m/s or N·m); the
        truncation error is O(step²) and the rounding error O(1e-16 / step).
        """
        x0 = np.array(_state_floats(state_eq))
        a = np.empty((STATE_SIZE, STATE_SIZE))
        for j in range(STATE_SIZE):
            e = np.zeros(STATE_SIZE)
            e[j] = step
            a[:, j] = (self.derivative(x0 + e, tau_left, tau_right, disturbance)
                       - self.derivative(x0 - e, tau_left, tau_right, disturbance)) / (2 * step)
        b = np.empty((STATE_SIZE, 2))
        for j, (dl, dr) in enumerate(((step, 0.0), (0.0, step))):
            plus = self.derivative(x0, tau_left + dl, tau_right + dr, disturbance)
            minus = self.derivative(x0, tau_left - dl, tau_right - dr, disturbance)
            b[:, j] = (plus - minus) / (2 * step)
        return a, b


def simulate_hold(plant, state: Sequence[float], tau_left: float, tau_right: float,
                  disturbance_fn: DisturbanceFunction | None, t0: float, dt: float,
                  n_steps: int) -> np.ndarray:
    """Integrate ``n_steps`` RK4 steps of ``dt`` [s] from ``t0`` [s], torques [N m] held.

    ``plant`` is a :class:`Plant` or any plant with its ``hold_floats`` (the MuJoCo
    plant). The disturbance is sampled at each step's start, ``disturbance_fn(t0 + k dt)``,
    and held over that step (``None``: no disturbance). Returns the final state;
    ValueError on a wrong size, NaN/inf, a non-positive ``dt``, a negative or fractional
    ``n_steps``, or a state that became non-finite.
    """
    values, tl, tr, disturbance = _hold_inputs(state, tau_left, tau_right, disturbance_fn,
                                               t0, dt, n_steps)
    return _checked_state(plant.hold_floats(tuple(values), tl, tr, disturbance, dt))


def _hold_inputs(state: Sequence[float], tau_left: float, tau_right: float,
                 disturbance_fn: DisturbanceFunction | None, t0: float, dt: float,
                 n_steps: int) -> tuple[list[float], float, float, np.ndarray]:
    """Return the checked state floats, τl, τr and disturbance rows (n_steps, 3)."""
    values = _state_floats(state)
    tl, tr, _, _, _ = _check_inputs(tau_left, tau_right, (0.0, 0.0, 0.0))
    _check_dt(dt)
    if n_steps < 0 or int(n_steps) != n_steps:
        raise ValueError(f'n_steps must be a non-negative integer, got {n_steps!r}')
    disturbance = np.zeros((int(n_steps), 3))
    if disturbance_fn is not None:
        for k in range(int(n_steps)):
            disturbance[k] = disturbance_fn(t0 + k * dt)
        if not np.all(np.isfinite(disturbance)):
            raise ValueError('disturbances must be finite, got '
                             f'{disturbance[~np.all(np.isfinite(disturbance), axis=1)][0]}')
    return values, tl, tr, disturbance


def _checked_state(x: Sequence[float]) -> np.ndarray:
    """Return a plant's new state as an array; ValueError if it is not finite."""
    if not math.isfinite(math.fsum(x)):
        raise ValueError(f'plant state became non-finite: {x} (check the disturbances)')
    return np.array(x)


def _check_dt(dt: float) -> None:
    if not (math.isfinite(dt) and dt > 0.0):
        raise ValueError(f'dt must be a positive finite time step [s], got {dt!r}')


def _make_accelerations(mv, jt, jphi, mpl, mpl2, mpgl, mvjt, mpl_sq, inv_r, yaw_gain,
                        k_centrifugal, k_coriolis, k_reaction, friction_v, friction_w,
                        sin=math.sin, cos=math.cos):
    """Return the dynamics (ω̇, υ̇, θ̈), constants bound as closure variables.

    On plain floats with ``math``'s sin and cos (:meth:`Plant.derivative`); on arrays
    with numpy's (:meth:`Plant.accelerations_array`, for the metrics of a whole run).
    The integrator :func:`_rk4_hold` inlines the same expressions.
    """

    def accelerations(th, om, v, thd, tv, tw):
        """(ω̇, υ̇, θ̈) without disturbances, for τυ = tv, τω = tw [N·m]."""
        # The axle friction acts as the motors do (with b = 0 the same bits as without).
        tv = tv - friction_v * (v * inv_r - thd)
        tw = tw - friction_w * om
        s = sin(th)
        c = cos(th)
        inv_omega = 1.0 / (mvjt - mpl_sq * c * c)                       # 1/Ω(θ)
        omd = ((yaw_gain * tw - (2.0 * mpl2 * c * thd + k_coriolis * v) * s * om)
               / (jphi + mpl2 * s * s))
        rv = mpl * s * (thd * thd + k_centrifugal * om * om) + tv * inv_r
        rt = mpgl * s + mpl2 * s * c * om * om - k_reaction * tv
        mplc = mpl * c
        return omd, (jt * rv - mplc * rt) * inv_omega, (mv * rt - mplc * rv) * inv_omega

    return accelerations


#: Order of the constants in the first argument of :func:`_rk4_hold`.
_CONSTANT_NAMES = ('mv', 'jt', 'jphi', 'mpl', 'mpl2', 'mpgl', 'mvjt', 'mpl_sq', 'inv_r',
                   'yaw_gain', 'k_centrifugal', 'k_coriolis', 'k_reaction', 'friction_v',
                   'friction_w')


#: The compiled integrator (:func:`.plant_rk4.rk4_hold`), imported by the first Plant.
_rk4_hold = None


def _load_integrator() -> None:
    """Import and warm up the compiled integrator once per process.

    Numba is imported only by a process that builds a plant: see :mod:`.plant_rk4`.
    """
    global _rk4_hold  # noqa: PLW0603 - one compiled function per process
    if _rk4_hold is None:
        from . import plant_rk4
        plant_rk4.warm_up(len(_CONSTANT_NAMES))
        _rk4_hold = plant_rk4.rk4_hold


if __name__ == '__main__':   # python3 -m wip_sim.core.plant: fill numba's cache
    _load_integrator()
