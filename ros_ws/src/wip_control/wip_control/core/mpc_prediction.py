r"""Condensed prediction of the longitudinal/tilt subsystem, eqs. (16)–(18) in [1]_.

The MPC predicts x = (υ, θ, θ̇) with the Euler model (17)

.. math::

    x(k+1) = A x(k) + B \tau_\upsilon(k) + c, \qquad
    B = T_s [g_2(\hat\theta);\ 0;\ g_3(\hat\theta)]

over ``Np`` steps, with the input increments Δτ(k) … Δτ(k+Nc−1) as decision variables
and τ(k+i) = τ(k−1) + Σ_{j ≤ min(i, Nc−1)} Δτ(k+j). Stacking the outputs
ȳ = (x(k+1), …, x(k+Np)) (3·Np values, interleaved υ, θ, θ̇ per step) gives

.. math::

    \bar y = \tilde G\, \Delta\bar\tau + \bar y_{free}

where ȳ_free is the trajectory with τ held at τ(k−1) (the paper's f̃ + g̃).

Two predictions (docs/paper.md §5):

``'gravity_aware'`` (default)
    A = [[1, a01, 0], [0, 1, Ts], [0, a21, 1]] with the linearised gravity terms
    a01 = −Ts mp² l² g / Ω0 and a21 = Ts mv mp g l / Ω0 (Ω0 = Ω(0)), and
    c = Ts [f̂2; 0; f̂3] − (A − A_paper) x̂, so that the first step equals the paper's
    (and the ESO's) one-step model while later steps feel the pendulum's instability.
    G̃ block (i, j) = Σ_{m=j..i} A^{i−m} B for j ≤ min(i, Nc−1), else 0.

``'paper'`` (literal eq. (18), kept for the ablation)
    A = A_paper = [[1, 0, 0], [0, 1, Ts], [0, 0, 1]], c = Ts [f̂2; 0; f̂3], and G̃ as
    printed in [1]_: block (i, j) = g(x(k+i|k−1)) = B for j ≤ i, a single one-step
    gain with no propagation through the dynamics. Its θ rows are zero (B has no θ
    entry), so neither the θ weight nor the θ limit can act: the vehicle falls.
    The free response is the same held-τ trajectory as in the default (the paper's
    f̃ + g̃ evaluated along x(k+i|k−1)).

Because B = g2·b2 + g3·b3 with b2 = Ts e0 and b3 = Ts e2 fixed, G̃ = g2 G2 + g3 G3 with
G2, G3 independent of the state: they are computed once here.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import numpy as np

from wip_description.params import ModelParams

#: Prediction models understood by :class:`CondensedPrediction`.
PREDICTION_MODELS = ('gravity_aware', 'paper')

#: Index of υ, θ, θ̇ inside one predicted step.
V_ROW, THETA_ROW, THETA_DOT_ROW = range(3)
STATE_DIM = 3


def paper_state_matrix(sampling_period: float) -> np.ndarray:
    """A_paper of eq. (17): υ and θ̇ integrate their (held) drifts, θ integrates θ̇."""
    ts = sampling_period
    return np.array([[1.0, 0.0, 0.0],
                     [0.0, 1.0, ts],
                     [0.0, 0.0, 1.0]])


def gravity_aware_state_matrix(params: ModelParams, sampling_period: float) -> np.ndarray:
    """A_paper plus the linearised gravity coupling of f_υ2 and f_θ3 at θ = 0.

    d f_υ2/dθ (0) = −mp² l² g / Ω0 and d f_θ3/dθ (0) = mv mp g l / Ω0 (eq. (1)).
    """
    p = params
    ts = sampling_period
    omega0 = p.omega_denominator(0.0)
    a = paper_state_matrix(ts)
    a[V_ROW, THETA_ROW] = -ts * (p.body_mass * p.com_height) ** 2 * p.gravity / omega0
    a[THETA_DOT_ROW, THETA_ROW] = (ts * p.effective_mass * p.body_mass * p.gravity
                                   * p.com_height / omega0)
    return a


def gravity_coefficients(params: ModelParams, sampling_period: float) -> tuple[float, float]:
    """(a_υθ [m/s² per rad], a_θθ [1/s²]): the gravity terms of A per second, f ≈ a θ.

    The part of the drifts f̂2, f̂3 linear in θ that the gravity-aware prediction models
    itself (:func:`gravity_aware_state_matrix`, divided by Ts).
    """
    a = gravity_aware_state_matrix(params, sampling_period)
    return (float(a[V_ROW, THETA_ROW]) / sampling_period,
            float(a[THETA_DOT_ROW, THETA_ROW]) / sampling_period)


class CondensedPrediction:
    """State-independent parts of the condensed prediction ȳ = G̃ Δτ̄ + ȳ_free.

    Parameters
    ----------
    params : physical parameters (for the gravity terms of A).
    sampling_period : Ts [s].
    prediction_horizon : Np, number of predicted steps.
    control_horizon : Nc ≤ Np, number of input increments.
    model : ``'gravity_aware'`` or ``'paper'`` (see the module docstring).

    Attributes
    ----------
    state_matrix : A (3×3) used for the free response.
    gain_matrix_v, gain_matrix_theta_dot : G2 and G3 (3·Np × Nc): G̃ = g2 G2 + g3 G3.
    free_state_matrix : M (3·Np × 3), free_v_column, free_theta_dot_column : γ2, γ3
        (3·Np): ȳ_free = M x̂ + γ2 (f̂2 + g2 τ(k−1)) + γ3 (f̂3 + g3 τ(k−1)).
    """

    def __init__(self, params: ModelParams, sampling_period: float,
                 prediction_horizon: int, control_horizon: int,
                 model: str = 'gravity_aware') -> None:
        if model not in PREDICTION_MODELS:
            raise ValueError(f'prediction model {model!r} is not one of {list(PREDICTION_MODELS)}')
        if not 1 <= control_horizon <= prediction_horizon:
            raise ValueError(f'need 1 <= control_horizon ({control_horizon}) <= '
                             f'prediction_horizon ({prediction_horizon})')
        if not sampling_period > 0.0:
            raise ValueError(f'sampling_period must be > 0 s, got {sampling_period!r}')
        ts, n_p, n_c = float(sampling_period), int(prediction_horizon), int(control_horizon)
        self.sampling_period = ts
        self.prediction_horizon = n_p
        self.control_horizon = n_c
        self.model = model
        a_paper = paper_state_matrix(ts)
        a = gravity_aware_state_matrix(params, ts) if model == 'gravity_aware' else a_paper
        self.state_matrix = a
        self.paper_state_matrix = a_paper

        # powers[k] = A^k, k = 0..Np; partial[k] = Σ_{p=0..k} A^p, k = 0..Np−1.
        powers = np.empty((n_p + 1, STATE_DIM, STATE_DIM))
        powers[0] = np.eye(STATE_DIM)
        for k in range(1, n_p + 1):
            powers[k] = powers[k - 1] @ a
        partial = np.cumsum(powers[:n_p], axis=0)

        # Free response (τ held at τ(k−1)): x_free(i+1) = A^{i+1} x̂ + Σ_{p≤i} A^p (Bτ + c)
        # with Bτ + c = Ts[f̂2 + g2 τ; 0; f̂3 + g3 τ] − (A − A_paper) x̂.
        drift_correction = a - a_paper
        self.free_state_matrix = (powers[1:] - partial @ drift_correction).reshape(
            STATE_DIM * n_p, STATE_DIM)
        self.free_v_column = ts * partial[:, :, V_ROW].reshape(-1)
        self.free_theta_dot_column = ts * partial[:, :, THETA_DOT_ROW].reshape(-1)

        # Block (i, j) of G̃ for unit b: Σ_{m=j..i} A^{i−m} b = partial[i−j] b (gravity
        # aware), or b itself (paper), for j ≤ i; zero above the block diagonal.
        if model == 'gravity_aware':
            step_v = ts * partial[:, :, V_ROW]                 # (Np, 3): S_k b2
            step_theta_dot = ts * partial[:, :, THETA_DOT_ROW]  # (Np, 3): S_k b3
        else:
            step_v = np.zeros((n_p, STATE_DIM))
            step_v[:, V_ROW] = ts
            step_theta_dot = np.zeros((n_p, STATE_DIM))
            step_theta_dot[:, THETA_DOT_ROW] = ts
        self.gain_matrix_v = self._toeplitz(step_v)
        self.gain_matrix_theta_dot = self._toeplitz(step_theta_dot)

    def decaying_input_columns(self, ratio: float) -> tuple[np.ndarray, np.ndarray]:
        """Free response to a geometrically decaying input: (γ2ρ, γ3ρ), 3·Np each.

        (γ2ρ, γ3ρ) (3·Np each): the free response to an input on the υ̇ (θ̈) row that
        decays geometrically, ρ^p at step p (ρ = 1: the constant-input columns γ2, γ3).

        x(k+1) = Σ_{p≤k} A^{k−p} b ρ^p = D_k b with D_0 = I, D_k = A^k + ρ D_{k−1}.
        """
        n_p, a = self.prediction_horizon, self.state_matrix
        power = np.eye(STATE_DIM)
        total = np.eye(STATE_DIM)
        out = np.empty((n_p, STATE_DIM, STATE_DIM))
        out[0] = total
        for k in range(1, n_p):
            power = power @ a
            total = power + ratio * total
            out[k] = total
        ts = self.sampling_period
        return (ts * out[:, :, V_ROW].reshape(-1), ts * out[:, :, THETA_DOT_ROW].reshape(-1))

    def _toeplitz(self, steps: np.ndarray) -> np.ndarray:
        n_p, n_c = self.prediction_horizon, self.control_horizon
        out = np.zeros((n_p, STATE_DIM, n_c))
        for j in range(n_c):
            out[j:, :, j] = steps[:n_p - j]
        return out.reshape(STATE_DIM * n_p, n_c)

    def input_matrix(self, g2: float, g3: float) -> np.ndarray:
        """G̃ (3·Np × Nc) for input gains g2 [m/s² per N·m], g3 [rad/s² per N·m]."""
        return g2 * self.gain_matrix_v + g3 * self.gain_matrix_theta_dot

    def free_response(self, x_hat: np.ndarray, f2_hat: float, f3_hat: float, g2: float,
                      g3: float, tau_previous: float) -> np.ndarray:
        """ȳ_free (3·Np): the predicted outputs with τ held at ``tau_previous`` [N·m]."""
        return (self.free_state_matrix @ np.asarray(x_hat, dtype=float)
                + self.free_v_column * (f2_hat + g2 * tau_previous)
                + self.free_theta_dot_column * (f3_hat + g3 * tau_previous))
