"""The MPC tested in closed loop: the longitudinal/tilt part of the paper plant (1).

A small closed loop (the MPC with perfect state knowledge on the paper plant (1) restricted
to the longitudinal/tilt subsystem, ω = 0, RK4 at 1 ms) for the tests of the MPC and of its
benchmark against DAQP.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from wip_control.core.integration import rk4_step
from wip_control.core.model import nominal_terms
from wip_control.core.mpc import LongitudinalMpc
from wip_control.core.mpc_config import MpcParams
from wip_description.params import ModelParams


class LongitudinalRun(NamedTuple):
    """Closed-loop trajectory at the plant rate and the MPC calls that produced it."""

    t: np.ndarray          #: time [s]
    v: np.ndarray          #: υ [m/s]
    theta: np.ndarray      #: θ [rad]
    theta_dot: np.ndarray  #: θ̇ [rad/s]
    tau_v: np.ndarray      #: applied τυ [N m]
    inputs: list           #: one dict per MPC tick: STEP_KEYS + 'tau_previous'
    results: list          #: the MpcResult of each tick
    fell: bool             #: |θ| reached ``fall_angle``


def _constant(value: float) -> Callable[[float], float]:
    return lambda t: value


def simulate_longitudinal(params: ModelParams, config: MpcParams, duration: float = 10.0,
                          theta_initial: float = 0.05, v_d: float | Callable = 0.5,
                          tau_limit: float | Callable = 30.0,
                          disturbance_v: Callable[[float], float] | None = None,
                          plant_period: float = 1e-3, fall_angle: float = 1.0) -> LongitudinalRun:
    """MPC on the longitudinal/tilt part of the paper plant (1) with perfect knowledge.

    The plant is υ̇ = f2 + g2 τ + d2, θ̈ = f3 + g3 τ (ω = 0), integrated by RK4 with step
    ``plant_period`` [s] and τ held between MPC ticks. The MPC receives the true
    (υ, θ, θ̇) and the true lumped drifts f̂2 = f2 + d2, f̂3 = f3 (what an ideal ESO would
    give). ``v_d``, ``tau_limit`` and ``disturbance_v`` [m/s²] may be functions of t [s].
    The run stops early once |θ| ≥ ``fall_angle`` [rad].
    """
    v_d_of = v_d if callable(v_d) else _constant(float(v_d))
    limit_of = tau_limit if callable(tau_limit) else _constant(float(tau_limit))
    d2_of = disturbance_v if disturbance_v is not None else _constant(0.0)
    decimation = int(round(config.sampling_period / plant_period))
    if decimation < 1 or abs(decimation * plant_period - config.sampling_period) > 1e-9:
        raise ValueError('sampling_period must be an integer multiple of plant_period')
    n_steps = int(round(duration / plant_period))
    mpc = LongitudinalMpc(params, config)
    mpc.reset(0.0)

    def derivative(v, theta, theta_dot, tau, d2):
        terms = nominal_terms(params, theta, 0.0, theta_dot)
        return (terms.f2 + terms.g2 * tau + d2, theta_dot, terms.f3 + terms.g3 * tau)

    v, theta, theta_dot, tau = 0.0, float(theta_initial), 0.0, 0.0
    out = np.empty((n_steps + 1, 5))
    inputs, results = [], []
    fell = False
    k_last = n_steps
    for k in range(n_steps + 1):
        t = k * plant_period
        d2 = d2_of(t)
        out[k] = (t, v, theta, theta_dot, tau)
        if abs(theta) >= fall_angle:
            fell, k_last = True, k
            break
        if k == n_steps:
            break
        if k % decimation == 0:
            terms = nominal_terms(params, theta, 0.0, theta_dot)
            args = dict(v_hat=v, theta_hat=theta, theta_dot_hat=theta_dot,
                        f2_hat=terms.f2 + d2, f3_hat=terms.f3, v_d=v_d_of(t),
                        tau_limit=limit_of(t))
            inputs.append(dict(args, tau_previous=mpc.tau_previous))
            result = mpc.step(**args)
            results.append(result)
            tau = result.tau_v
            out[k, 4] = tau
        # RK4, disturbance held over the step.
        v, theta, theta_dot = rk4_step(
            lambda _, x: derivative(*x, tau, d2), t, (v, theta, theta_dot), plant_period)
    out = out[:k_last + 1]
    return LongitudinalRun(out[:, 0], out[:, 1], out[:, 2], out[:, 3], out[:, 4], inputs,
                           results, fell)
