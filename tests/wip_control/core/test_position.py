"""Planar position estimator: odometry dead reckoning and GPS correction."""

import math

import numpy as np
import pytest

from wip_runtime.config import ParamError, from_mapping
from wip_control.core.position import PlanarPositionEstimator, PositionParams


def test_odometry_is_exact_on_a_circular_arc():
    # Constant curvature between samples: the chord (length ds·sinc(Δϕ/2), direction
    # ϕ + Δϕ/2) is the exact displacement, even for coarse 0.5 rad heading steps.
    radius, phi0 = 2.0, 0.3
    est = PlanarPositionEstimator()
    cx, cy = -radius * math.sin(phi0), radius * math.cos(phi0)  # centre, left of heading
    est.reset(0.0, 0.0, 0.0, phi0)
    for k in range(1, 40):
        dphi = 0.5 * k
        x, y = est.update_odometry(radius * dphi, phi0 + dphi)
        expected = (cx + radius * math.sin(phi0 + dphi), cy - radius * math.cos(phi0 + dphi))
        # 39 steps of ~1e-16 rounding on metre-scale values.
        assert (x, y) == pytest.approx(expected, abs=1e-12)


def test_odometry_accepts_wrapped_heading():
    a, b = PlanarPositionEstimator(), PlanarPositionEstimator()
    a.reset(1.0, 2.0, 0.0, 3.0)
    b.reset(1.0, 2.0, 0.0, 3.0)
    for k in range(1, 50):
        phi = 3.0 + 0.02 * k  # crosses π
        pa = a.update_odometry(0.01 * k, phi)
        pb = b.update_odometry(0.01 * k, math.remainder(phi, 2 * math.pi))
    # The same increments up to the 2π shift: agreement to rounding.
    assert pa == pytest.approx(pb, abs=1e-12)


def test_gps_fix_resets_the_estimate_with_unit_gain_and_blends_with_smaller_gain():
    est = PlanarPositionEstimator()
    est.reset(0.0, 0.0, 0.0, 0.0)
    est.update_odometry(1.0, 0.0)
    assert est.update_gps(1.2, -0.1) == (1.2, -0.1)
    half = PlanarPositionEstimator(PositionParams(gps_blend_gain=0.25, max_gps_innovation=10.0))
    half.reset(0.0, 0.0, 0.0, 0.0)
    assert half.update_gps(4.0, -8.0) == pytest.approx((1.0, -2.0), abs=1e-15)


def test_blend_gain_reduces_fix_noise_as_predicted():
    # e+ = (1 − k) e + k n: stationary std σ √(k/(2 − k)) (position.py docstring).
    k, sigma, n = 0.2, 0.5, 20000
    rng = np.random.default_rng(3)
    est = PlanarPositionEstimator(PositionParams(gps_blend_gain=k, max_gps_innovation=100.0))
    est.reset(0.0, 0.0, 0.0, 0.0)
    xs = [est.update_gps(*rng.normal(0.0, sigma, 2))[0] for _ in range(n)]
    predicted = sigma * math.sqrt(k / (2 - k))
    # AR(1) with ρ = 1 − k: n k/(2 − k) ≈ 2200 effectively independent samples, so the
    # sample std is within ≈ 1/√(2·2200) = 1.5 % of the truth; 5 % is over 3σ.
    assert np.std(xs[100:]) == pytest.approx(predicted, rel=0.05)


@pytest.mark.parametrize('fix', [(math.nan, 0.0), (0.0, math.inf), (-math.inf, math.nan)])
def test_non_finite_fixes_are_rejected(fix):
    est = PlanarPositionEstimator()
    est.reset(1.0, 2.0, 0.0, 0.0)
    assert est.update_gps(*fix) == (1.0, 2.0)
    assert est.rejected_fixes == 1 and est.accepted_fixes == 0


def test_outlier_fixes_beyond_the_gate_are_rejected():
    est = PlanarPositionEstimator(PositionParams(max_gps_innovation=2.0))
    est.reset(0.0, 0.0, 0.0, 0.0)
    assert est.update_gps(3.0, 0.0) == (0.0, 0.0)
    assert est.update_gps(1.0, 1.0) == (1.0, 1.0)
    assert (est.rejected_fixes, est.accepted_fixes) == (1, 1)


def test_the_gate_widens_with_the_distance_rolled_since_the_last_accepted_fix():
    # r = r0 + d s: after rolling 20 m without a fix, 3 + 0.1 * 20 = 5 m.
    est = PlanarPositionEstimator(PositionParams(max_gps_innovation=3.0, odometry_drift=0.1))
    est.reset(0.0, 0.0, 0.0, 0.0)
    assert est.gate() == 3.0
    est.update_odometry(20.0, 0.0)
    assert est.gate() == pytest.approx(5.0, abs=1e-12)
    assert est.update_gps(20.0, 4.9) == (20.0, 4.9)    # inside: accepted, the gate shrinks
    assert est.gate() == 3.0
    assert est.update_gps(20.0, 8.0) == (20.0, 4.9)    # 3.1 m off: rejected


def test_a_jump_is_rejected_and_a_persistent_one_becomes_a_fault_after_the_time():
    # 10 Hz fixes of a vehicle at rest; from t = 1 s the receiver reports 50 m east.
    config = PositionParams(max_rejection_time=1.0)
    est = PlanarPositionEstimator(config)
    est.reset(0.0, 0.0, 0.0, 0.0)
    for k in range(10):
        est.update_gps(0.0, 0.0, 0.1 * k)
    # A brief jump (0.5 s): rejected, no fault, the estimate untouched.
    for k in range(10, 15):
        assert est.update_gps(50.0, 0.0, 0.1 * k) == (0.0, 0.0)
    assert est.fault == '' and est.rejected_fixes == 5
    est.update_gps(0.01, 0.0, 1.5)                     # back: accepted, the run ends
    assert est.fault == '' and est.position == (0.01, 0.0)
    # A persistent jump: a fault once rejected for max_rejection_time, not before.
    times = [1.6 + 0.1 * k for k in range(12)]
    faults = []
    for t in times:
        est.update_gps(50.0, 0.0, t)
        faults.append(bool(est.fault))
    first = times[faults.index(True)]
    assert first - times[0] == pytest.approx(1.0, abs=1e-9)
    assert '49.99 m from the odometry' in est.fault and est.position == (0.01, 0.0)
    # A good fix again clears it (the source recovered).
    est.update_gps(0.0, 0.0, 3.0)
    assert est.fault == ''


def test_non_finite_odometry_raises_and_keeps_the_state():
    est = PlanarPositionEstimator()
    est.reset(1.0, 2.0, 0.0, 0.0)
    with pytest.raises(ValueError, match='x_v=nan'):
        est.update_odometry(math.nan, 0.0)
    assert est.position == (1.0, 2.0)


def test_config_rejects_gain_outside_unit_interval():
    with pytest.raises(ParamError, match='position.gps_blend_gain'):
        from_mapping(PositionParams, {'gps_blend_gain': 0.0}, 'position')
    with pytest.raises(ParamError, match='position.gps_blend_gain'):
        from_mapping(PositionParams, {'gps_blend_gain': 1.5}, 'position')
