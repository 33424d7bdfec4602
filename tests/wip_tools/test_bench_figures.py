"""The real-time section's ratios of ``scripts/bench`` from given measurements (closed forms)."""

import pytest

pytest.importorskip('rclpy')

from wip_tools import realtime_bench  # noqa: E402

PLAIN = {'layout': 'composed', 'rt_priority': False, 'pinned': False, 'cpu_latency': None,
         'controller_cpu_fraction': 0.19}


def _rows():
    # The other cases of the section: only the plain composed one counts.
    return [{'layout': 'separate', 'rt_priority': False, 'pinned': False, 'cpu_latency': None,
             'controller_cpu_fraction': 0.9}, PLAIN,
            {**PLAIN, 'rt_priority': True, 'controller_cpu_fraction': 0.15},
            {**PLAIN, 'rt_priority': True, 'pinned': True, 'cpu_latency': 0,
             'controller_cpu_fraction': 0.12}]


def test_the_overhead_figures_are_the_issues_ratios_of_the_plain_composed_case():
    floor = {'messages': {'cpu_fraction': 0.05}, 'serialized': {'cpu_fraction': 0.027},
             'loop': {'cpu_fraction': 0.045}}
    cost = {'median_us': {'back_to_back': 280.0, 'paced': 560.0}}
    per_tick = 103e-6                 # [s] the in-process loop: 2.06 % of a core at 200 Hz
    figures = realtime_bench.overhead_figures(_rows(), floor, cost, per_tick,
                                              realtime_bench.PI_CLASS_CALIBRATION_S / 3.0)
    assert figures['composed_share'] == 0.19
    # (19 - 2.7) / 2.06 and 560 / 103, as the issue computes them.
    assert figures['overhead_ratio'] == pytest.approx((0.19 - 0.027) / (200 * per_tick))
    assert figures['paced_over_in_process'] == pytest.approx(560.0 / 103.0)
    # Against the floor that also sends the command: (19 - 4.5) / 2.06.
    assert figures['overhead_ratio_loop'] == pytest.approx((0.19 - 0.045) / (200 * per_tick))
    # A core three times faster than the Pi-class reference: three times the share there.
    assert figures['pi_class_share'] == pytest.approx(3 * 0.19)


def test_a_figure_whose_measurement_is_missing_is_none_not_an_error():
    figures = realtime_bench.overhead_figures(
        [{'layout': 'composed', 'skipped': 'no graph'}], {'skipped': 'rclpy not available'},
        {'failed': 'x'}, 100e-6, 0.02)
    assert figures['overhead_ratio'] is None and figures['pi_class_share'] is None
    assert figures['overhead_ratio_loop'] is None
    assert figures['paced_over_in_process'] is None


def test_the_calibration_loop_gives_the_least_cpu_time_of_its_runs():
    one, many = realtime_bench.calibration_loop(1), realtime_bench.calibration_loop(3)
    assert one > 0.0 and many > 0.0
    assert many <= one * 1.5 + 0.01     # the least of three runs, not their sum
