"""Reference trajectories: analytic derivatives, the paper's trifolium, config checks."""

import dataclasses
import math

import numpy as np
import pytest

from wip_runtime.config import ParamError, from_mapping
from wip_control.core.reference_curves import Circle, FigureEight, StraightLine, Trifolium
from wip_control.core.reference_state import ReferenceState
from wip_control.core.reference_waypoints import Waypoints
from wip_control.core.references import make_reference, ReferenceParams
from wip_control.core.time_scaling import TimeScaled

SMOOTH = [Trifolium(), Circle(center=(1.0, -2.0), radius=1.5, speed=0.4, direction='cw',
                              start_angle=0.7),
          StraightLine((1.0, 2.0), 0.4, 0.8), FigureEight((0.5, 0.5), 2.0, 40.0)]
IDS = ['trifolium', 'circle', 'line', 'figure_eight']
STEP = 1e-3  # central-difference step [s]


def central(f, t, h=STEP):
    return (f(t + h) - f(t - h)) / (2 * h)


@pytest.mark.parametrize('ref', SMOOTH, ids=IDS)
def test_analytic_derivatives_match_central_differences(ref):
    # Central differences err by h²/6 |f'''|: with h = 1e-3 s and the references'
    # derivatives of order ≤ 1 (rad, m per s^k), that is ≤ 2e-7; rounding adds
    # 1e-16/h ≈ 1e-13. Tolerance 1e-6 absolute.
    for t in np.linspace(0.3, 89.7, 37):
        s = ref.sample(t)
        assert s.v == pytest.approx(math.hypot(central(lambda u: ref.sample(u).x, t),
                                               central(lambda u: ref.sample(u).y, t)),
                                    abs=1e-6)
        assert s.omega == pytest.approx(central(lambda u: ref.sample(u).phi, t), abs=1e-6)
        assert s.omega_dot == pytest.approx(central(lambda u: ref.sample(u).omega, t),
                                            abs=1e-6)
        d = ref.derivatives(t)
        for i, name in enumerate(('x', 'y')):
            assert d[i] == pytest.approx(central(lambda u: getattr(ref.sample(u), name), t),
                                         abs=1e-6)
            assert d[2 + i] == pytest.approx(central(lambda u: ref.derivatives(u)[i], t),
                                             abs=1e-6)
            assert d[4 + i] == pytest.approx(central(lambda u: ref.derivatives(u)[2 + i], t),
                                             abs=1e-6)


@pytest.mark.parametrize('ref', SMOOTH, ids=IDS)
def test_heading_is_the_velocity_direction_and_continuous(ref):
    ts = np.arange(0.0, 90.0, 0.01)
    states = [ref.sample(t) for t in ts]
    phi = np.array([s.phi for s in states])
    d = np.array([ref.derivatives(t)[:2] for t in ts])
    # Same angle mod 2π, to rounding (atan2 of exact derivatives).
    diff = np.angle(np.exp(1j * (phi - np.arctan2(d[:, 1], d[:, 0]))))
    assert np.abs(diff).max() < 1e-9
    # Continuous: each 10 ms step moves ϕ by about ω·0.01 ≤ 0.007 rad, never 2π.
    assert np.abs(np.diff(phi)).max() < 0.01


def test_trifolium_matches_the_papers_formula_speed_range_and_peak_yaw_rate():
    ref = Trifolium()
    ts = np.arange(0.0, 90.0, 0.005)
    states = np.array([ref.sample(t) for t in ts])
    w = math.pi / 45
    # Section V: x_r = κ cos(3Ωt) cos(Ωt), y_r = κ cos(3Ωt) sin(Ωt), κ = 3.
    np.testing.assert_allclose(states[:, 0], 3 * np.cos(3 * w * ts) * np.cos(w * ts),
                               atol=1e-12)
    np.testing.assert_allclose(states[:, 1], 3 * np.cos(3 * w * ts) * np.sin(w * ts),
                               atol=1e-12)
    # υ_r = κΩ√(1 + 8 sin²3Ωt) ∈ [κΩ, 3κΩ] = [0.2094, 0.6283]: docs/paper.md §6's [0.21, 0.63].
    assert states[:, 3].min() == pytest.approx(3 * w, abs=1e-9)
    assert states[:, 3].max() == pytest.approx(9 * w, abs=1e-9)
    assert round(states[:, 3].min(), 2) == 0.21 and round(states[:, 3].max(), 2) == 0.63
    # |ω_r| peaks at the petal tips (sin 3Ωt = 0) at exactly 4Ω + 2·3Ω = 10Ω = 0.698 rad/s,
    # from ϕ_r = 4Ωt + π/2 + atan2(sin 2u, 1 + 2 sin²u); the 5 ms grid hits the tips.
    assert np.abs(states[:, 4]).max() == pytest.approx(10 * w, rel=1e-9)
    assert round(np.abs(states[:, 4]).max(), 2) == 0.70
    # ϕ_r grows by 4π per figure (π/Ω = 45 s).
    assert ref.sample(45.0).phi - ref.sample(0.0).phi == pytest.approx(4 * math.pi,
                                                                        abs=1e-12)


def test_circle_line_and_figure_eight_closed_forms():
    c = Circle(center=(1.0, 2.0), radius=2.0, speed=0.5, direction='ccw', start_angle=0.0)
    s = c.sample(0.0)
    assert (s.x, s.y, s.phi, s.v, s.omega, s.omega_dot) == pytest.approx(
        (3.0, 2.0, math.pi / 2, 0.5, 0.25, 0.0))
    cw = Circle(radius=2.0, speed=0.5, direction='cw').sample(0.0)
    assert (cw.phi, cw.omega) == pytest.approx((-math.pi / 2, -0.25))
    line = StraightLine((1.0, 1.0), math.pi / 4, 1.0).sample(2.0)
    assert (line.x, line.y) == pytest.approx((1 + math.sqrt(2), 1 + math.sqrt(2)))
    f8 = FigureEight((0.0, 0.0), 3.0, 60.0)
    assert f8.sample(0.0).phi == pytest.approx(math.pi / 4)  # leaves the centre at 45°
    assert (f8.sample(30.0).x, f8.sample(30.0).y) == pytest.approx((0.0, 0.0), abs=1e-12)
    speeds = [f8.sample(t).v for t in np.linspace(0, 60, 6001)]
    w = 2 * math.pi / 60
    # Speed a w √(4c⁴ − 3c² + 1): min √(7/16) at c² = 3/8, max √2 at c = ±1.
    assert min(speeds) == pytest.approx(3 * w * math.sqrt(7 / 16), rel=1e-4)
    assert max(speeds) == pytest.approx(3 * w * math.sqrt(2), rel=1e-9)


# --- Waypoints ----------------------------------------------------------------------

SQUARE = [(0.0, 0.0), (4.0, 0.0), (4.0, 4.0), (0.0, 4.0)]


def test_waypoints_profile_respects_speed_acceleration_and_yaw_rate_limits():
    ref = Waypoints(SQUARE, speed=0.5, acceleration=0.2, corner_radius=1.0,
                    max_yaw_rate=0.25)
    dt = 0.002
    ts = np.arange(-1.0, ref.duration + 1.0, dt)
    states = np.array([ref.sample(t) for t in ts])
    v, omega = states[:, 3], states[:, 4]
    assert v.max() == pytest.approx(0.5) and v.min() == 0.0
    # On the fillets υ ≤ max_yaw_rate·R = 0.25, so |ω| = υ/R ≤ 0.25.
    assert np.abs(omega).max() <= 0.25 + 1e-12
    # |υ̇| ≤ a: finite differences of a piecewise-linear speed are exact up to rounding.
    assert np.abs(np.diff(v) / dt).max() <= 0.2 + 1e-9
    # Position continuous (no jumps at piece boundaries): |Δp| ≤ υ_max dt.
    step = np.hypot(np.diff(states[:, 0]), np.diff(states[:, 1]))
    assert step.max() <= 0.5 * dt + 1e-12
    # Starts at the first waypoint at rest, ends at the last at rest, heading continuous.
    assert (states[0, 0], states[0, 1], states[0, 3]) == (0.0, 0.0, 0.0)
    assert states[-1, :2] == pytest.approx((0.0, 4.0), abs=1e-12)
    assert states[-1, 3] == 0.0
    assert np.abs(np.diff(states[:, 2])).max() <= 0.25 * dt + 1e-12
    assert states[-1, 2] == pytest.approx(math.pi)  # two left turns of 90°


def test_waypoints_positions_follow_the_speed_and_heading():
    # x_r, y_r are the integral of υ_r (cos ϕ_r, sin ϕ_r): central differences of the
    # position match it away from the speed-profile kinks (errors O(h² |ϋ|) = 0 on
    # piecewise-linear speed, O(h² υ ω²) ≈ 1e-9 on the fillets).
    ref = Waypoints(SQUARE + [(2.0, 6.0)], speed=0.6, acceleration=0.3,
                    corner_radius=0.8, max_yaw_rate=0.3)
    for t in np.linspace(0.1, ref.duration - 0.1, 400):
        s = ref.sample(t)
        vx = central(lambda u: ref.sample(u).x, t)
        vy = central(lambda u: ref.sample(u).y, t)
        # Near a kink of the profile (within h) the difference can be off by a·h.
        assert vx == pytest.approx(s.v * math.cos(s.phi), abs=0.3 * STEP + 1e-8)
        assert vy == pytest.approx(s.v * math.sin(s.phi), abs=0.3 * STEP + 1e-8)


def test_waypoints_short_legs_shrink_the_fillet_and_stay_on_the_corner_bisector():
    # Legs of 1 m with a 5 m radius: R is reduced so each tangent point is mid-leg.
    ref = Waypoints([(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)], corner_radius=5.0)
    curvatures = [p.curvature for p in ref._pieces if p.curvature != 0.0]
    # Middle leg of 1 m shared by two corners: tangent 0.5 = R tan(45°) → R = 0.5.
    assert curvatures == pytest.approx([2.0, 2.0])


@pytest.mark.parametrize('points, message', [
    ([(0.0, 0.0)], 'at least 2'),
    ([(0.0, 0.0), (0.0, 0.0), (1.0, 0.0)], 'coincide'),
    ([(0.0, 0.0), (1.0, 0.0), (0.0, 0.0001)], 'more than 179 deg'),
])
def test_bad_waypoint_lists_are_rejected(points, message):
    with pytest.raises(ValueError, match=message):
        Waypoints(points)


@pytest.mark.parametrize('ref', SMOOTH + [Waypoints([(0.0, 0.0), (4.0, 0.0), (4.0, 4.0)])],
                         ids=IDS + ['waypoints'])
def test_speed_and_yaw_rate_are_the_samples_to_the_bit(ref):
    # TimeScaled takes its lead speeds and its σ0 table from speed_and_yaw_rate: it must
    # give the very floats of sample(t).v and .omega, or the re-timed reference (and every
    # run) would change in its last bits.
    for t in np.linspace(-1.0, 50.0, 1001):
        s = ref.sample(t)
        assert ref.speed_and_yaw_rate(t) == (s.v, s.omega)


# --- Config ----------------------------------------------------------------------------

def test_make_reference_defaults_to_the_papers_trifolium():
    # Default: the trifolium's path, time-scaled (path following, TimeScaled).
    timed = make_reference()
    assert isinstance(timed, TimeScaled)
    ref = timed.base
    assert isinstance(ref, Trifolium)
    assert ref.size == 3.0 and ref.angular_frequency == pytest.approx(math.pi / 45)
    assert isinstance(ref.sample(1.0), ReferenceState)


@pytest.mark.parametrize('kind, cls', [('circle', Circle), ('line', StraightLine),
                                       ('figure_eight', FigureEight),
                                       ('waypoints', Waypoints), ('trifolium', Trifolium)])
def test_make_reference_builds_each_kind_from_yaml_data(kind, cls):
    config = from_mapping(ReferenceParams, {'kind': kind, 'circle_radius': 3.0,
                                            'waypoints_x': [0, 2, 2],
                                            'waypoints_y': [0, 0, 2]}, 'reference')
    timed = make_reference(config)
    assert isinstance(timed, TimeScaled) and isinstance(timed.base, cls)
    untimed = make_reference(dataclasses.replace(config, time_scaling=False))
    assert isinstance(untimed, cls)


def test_unknown_keys_and_bad_values_are_rejected_naming_the_key():
    with pytest.raises(ParamError, match=r'^reference\.radius: unknown key'):
        from_mapping(ReferenceParams, {'radius': 2.0}, 'reference')
    with pytest.raises(ParamError, match=r'^reference\.kind: .*not one of'):
        from_mapping(ReferenceParams, {'kind': 'spiral'}, 'reference')
    with pytest.raises(ParamError, match=r'^reference\.circle_radius: must be > 0'):
        from_mapping(ReferenceParams, {'circle_radius': 0.0}, 'reference')
    with pytest.raises(ParamError, match=r'^reference\.waypoints_y: has 2 values'):
        from_mapping(ReferenceParams, {'waypoints_x': [0, 1, 2], 'waypoints_y': [0, 1]},
                     'reference')
    with pytest.raises(ParamError, match=r'^reference\.waypoints_x: .*coincide'):
        from_mapping(ReferenceParams, {'kind': 'waypoints', 'waypoints_x': [0, 0, 1],
                                       'waypoints_y': [0, 0, 1]}, 'reference')
