"""The paper's Section V end to end, in-process: what the paper claims and docs/paper.md adopts.

One 90 s run (about 3 s of wall time) is shared by the tests of this module.

Requirements (issue "Foundation", spec section 6):
- the vehicle never falls;
- |θ| ≤ 0.1 rad except within 3 s after the collision pulse, and never above 0.2 rad;
- |τl|, |τr| ≤ 15 N·m; |Δτυ| ≤ 10 N·m per MPC step; no QP failure;
- the desired velocities stay within their limits (paper Fig. 7);
- the ESO estimates match the true states (paper Figs. 8-9);
- α̂ stays bounded (paper Fig. 10).
"""

import math

import numpy as np
import pytest

from wip_tools.analysis.metrics import compute_metrics
from wip_control.core.mpc_config import PAPER_MPC_SETTINGS
from wip_sim.core.runner import run_scenario
from wip_sim.core.scenario import paper_scenario, Scenario, scenario_from_mapping

# Numerical slack on hard limits: the QP is solved to eps_abs = 1e-6 and the mixer clips
# in floating point, so a limit may be met to ~1e-9 but never exceeded by more.
HARD_LIMIT_TOL = 1e-6


#: The MPC as the paper formulates it (PAPER_MPC_SETTINGS); the default MPC is the robust
#: one (per-step soft limits, offset-free target, re-tuned weights), checked below too.
PAPER_MAPPING = {'mpc': dict(PAPER_MPC_SETTINGS)}

#: The paper scenario's metrics on main ced33b1, before the robust MPC (the paper design): the
#: paper settings must keep reproducing them within 5 %.
METRICS_BEFORE_ISSUE_9 = {'convergence_time_s': 14.36, 'rms_position_error_m': 0.5894,
                          'max_position_error_m': 1.6929, 'rms_heading_error_rad': 0.3641,
                          'max_abs_theta_rad': 0.0910,
                          'max_abs_theta_outside_pulse_windows_rad': 0.0841,
                          'max_abs_wheel_torque_nm': 5.6692}


@pytest.fixture(scope='module')
def paper_run():
    # The paper's design (its ESOs, adaptation law, heading gains, untimed reference and,
    # with PAPER_MAPPING, its MPC); the default design is the robust one
    # (docs/estimation.md, docs/mpc.md).
    scenario = paper_scenario(PAPER_MAPPING)
    result = run_scenario(scenario)
    metrics = compute_metrics(result.record, scenario, fell=result.fell,
                              duration_s=result.simulated_time_s)
    return scenario, result, metrics


@pytest.mark.slow
def test_paper_scenario_stays_up_for_the_whole_run(paper_run):
    scenario, result, metrics = paper_run
    assert not metrics['fell']
    assert result.simulated_time_s == pytest.approx(scenario.duration)


@pytest.mark.slow
def test_tilt_within_limit_outside_the_pulse_and_never_above_twice_it(paper_run):
    _, _, metrics = paper_run
    assert metrics['max_abs_theta_outside_pulse_windows_rad'] <= 0.1
    assert metrics['max_abs_theta_rad'] <= 0.2


@pytest.mark.slow
def test_torque_and_torque_rate_limits_hold(paper_run):
    scenario, _, metrics = paper_run
    assert metrics['max_abs_wheel_torque_nm'] <= scenario.mixer.max_wheel_torque + HARD_LIMIT_TOL
    assert metrics['max_abs_delta_tau_v_nm'] <= scenario.mpc.max_delta_torque + HARD_LIMIT_TOL
    assert metrics['max_abs_tau_omega_nm'] <= scenario.arc.max_yaw_torque + HARD_LIMIT_TOL


@pytest.mark.slow
def test_no_qp_failure_in_900_ticks(paper_run):
    _, _, metrics = paper_run
    assert metrics['mpc_ticks'] == 900  # t = 0, 0.1, ..., 89.9
    assert metrics['qp_failures'] == 0


@pytest.mark.slow
def test_desired_velocities_within_their_limits(paper_run):
    scenario, _, metrics = paper_run
    generator = scenario.trajectory_generator
    assert metrics['max_abs_v_d_mps'] <= generator.max_speed + 1e-12
    assert metrics['max_abs_omega_d_radps'] <= generator.max_yaw_rate + 1e-12


@pytest.mark.slow
def test_eso_estimates_match_the_truth(paper_run):
    # Bounds: the observer bandwidth 1/ε = 100 rad/s against signals of a few rad/s
    # gives velocity errors of order ε·|f| ≈ 1e-2 and disturbance errors of order
    # |ḟ|·ε; the collision pulse (10 m/s² for 0.1 s) and the 20 % error in ĝ1
    # (|0.2 g1 τω| ≤ 0.2·2.58·0.8 ≈ 0.41 rad/s²) dominate f2 and f1 respectively.
    _, _, metrics = paper_run
    eso = metrics['eso_rms_error']
    assert eso['omega'] < 0.01
    assert eso['v'] < 0.02
    assert eso['theta_dot'] < 0.02
    assert eso['f1'] < 0.3
    assert eso['f2'] < 1.0
    assert eso['f3'] < 1.0


@pytest.mark.slow
def test_adaptive_estimate_stays_bounded_and_positive(paper_run):
    _, result, _ = paper_run
    alpha = result.record['arc']['alpha_hat']
    assert np.all(np.isfinite(alpha))
    assert alpha.min() > 0.0
    # Fig. 10: α̂ stays bounded but need not converge to 1/g1 ≈ 0.39-0.45.
    assert alpha.max() < 2.0


@pytest.mark.slow
def test_path_tracking_converges_and_stays_bounded(paper_run):
    # The paper claims the initial errors are rejected within 8 s. With ωd limited to
    # 0.3 rad/s while the trifolium needs up to 0.70 rad/s at its petal tips, an independent
    # prototype of this design first reached 0.1 m at 14.4 s with an RMS error of 0.58 m after
    # 10 s; the bounds below hold this implementation to that floor, not to the paper's claim
    # (see the comparison with the paper in docs/paper.md).
    _, _, metrics = paper_run
    assert metrics['convergence_time_s'] is not None
    assert metrics['convergence_time_s'] <= 20.0
    assert metrics['rms_position_error_m'] <= 0.7
    assert metrics['max_position_error_m'] <= 2.0
    assert metrics['rms_heading_error_rad'] <= 0.5


@pytest.mark.slow
def test_paper_settings_reproduce_the_metrics_from_before_the_robust_mpc(paper_run):
    _, _, metrics = paper_run
    for name, before in METRICS_BEFORE_ISSUE_9.items():
        assert metrics[name] == pytest.approx(before, rel=0.05), name


@pytest.mark.slow
def test_default_robust_mpc_keeps_the_paper_scenario_up_and_within_limits():
    # Measured (robust MPC, paper estimator and generator): no fall, |θ| ≤ 0.083 rad
    # outside the pulse, 5.6 N m per wheel, convergence 15.9 s, RMS error 0.60 m (paper
    # settings: 14.4 s, 0.59 m). The whole default design (docs/estimation.md) does
    # better on the path (path following); these bounds hold for both.
    scenario = Scenario()
    result = run_scenario(scenario)
    metrics = compute_metrics(result.record, scenario, fell=result.fell,
                              duration_s=result.simulated_time_s)
    assert not metrics['fell']
    assert metrics['max_abs_theta_outside_pulse_windows_rad'] <= 0.1
    assert metrics['max_abs_theta_rad'] <= 0.2
    assert metrics['max_abs_wheel_torque_nm'] <= scenario.mixer.max_wheel_torque + HARD_LIMIT_TOL
    assert metrics['max_abs_delta_tau_v_nm'] <= scenario.mpc.max_delta_torque + HARD_LIMIT_TOL
    assert metrics['qp_failures'] == 0
    assert metrics['convergence_time_s'] is not None
    assert metrics['convergence_time_s'] <= 20.0
    assert metrics['rms_position_error_m'] <= 0.7


@pytest.mark.slow
def test_full_plant_is_a_robustness_test_the_controllers_pass():
    # The full Lagrange-d'Alembert plant adds the motor reaction torque, centrifugal
    # and Coriolis terms that the controllers' model (1) ignores.
    scenario = scenario_from_mapping({'plant': {'model': 'full'}, 'duration': 40.0})
    result = run_scenario(scenario)
    metrics = compute_metrics(result.record, scenario, fell=result.fell,
                              duration_s=result.simulated_time_s)
    assert not metrics['fell']
    assert metrics['max_abs_theta_rad'] <= 0.2
    assert metrics['qp_failures'] == 0
    assert metrics['max_abs_wheel_torque_nm'] <= 15.0 + HARD_LIMIT_TOL


@pytest.mark.slow
def test_paper_literal_prediction_falls_in_the_closed_loop():
    # Spec section 5: the paper's G̃ has no propagation, the θ rows ignore the input,
    # and the vehicle falls within about 1.5 s even with perfect state knowledge.
    scenario = scenario_from_mapping({'design': 'paper', 'mpc': {'prediction': 'paper'},
                                      'duration': 10.0})
    result = run_scenario(scenario)
    assert result.fell
    assert result.fall_time < 5.0
    assert math.isfinite(result.fall_time)
