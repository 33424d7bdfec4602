"""Open-loop re-run of the controllers on a recorded bag (``scripts/rerun``).

The bag is an in-process run of a short scenario written as the node graph records it
(``tests/record_bag.py``: same topics, types and stamps; sensor samples
drawn again from the true states with the scenario's seed). Re-running the unchanged
controllers on it must reproduce what they computed; changing a gain must change it.
"""

import json

import pytest

pytest.importorskip('wip_msgs.msg', reason='wip_msgs not built (scripts/setup builds it)')

from rosbags.rosbag2 import Reader  # noqa: E402

from wip_sim.core.runner import run_scenario  # noqa: E402
from wip_sim.core.scenario import scenario_from_mapping  # noqa: E402
from wip_bag.bag_reader import read_topics  # noqa: E402
from record_bag import write_record_as_bag  # noqa: E402
from wip_tools.rerun import main, rerun  # noqa: E402

pytestmark = pytest.mark.ros

DURATION = 3.0  # [s]: 600 control ticks, 30 MPC ticks; covers the start-up transient
# Tolerances of "reproduces", per quantity. Only two inputs are not bit-identical to what
# the recorded controllers saw: the IMU angles go through a quaternion and back (about
# 1e-16 rad) and the GPS fix through WGS84 latitude/longitude and back (documented inverse
# to better than 1e-6 m, measured 1.5e-9 m). Everything downstream is Lipschitz in these
# inputs with gains of order 1..10 (generator gains, ARC gain, MPC), so 1e-6 in the units
# of each field (m, rad, m/s, N m ...) is a bound with a margin of 100x over the measured
# 1e-8; the recorded magnitudes are 0.1..10, so this is still a relative 1e-7..1e-5.
REPRODUCE_TOLERANCE = 1e-6


@pytest.fixture(scope='module')
def recorded_bag(tmp_path_factory):
    scenario = scenario_from_mapping({'duration': DURATION})
    result = run_scenario(scenario)
    directory = tmp_path_factory.mktemp('recorded') / 'run'
    counts = write_record_as_bag(result, scenario, directory)
    return directory, counts, result


def _worst(entry):
    return max(field['max_abs_difference'] for field in entry['fields'].values())


def test_rerun_of_unchanged_controllers_reproduces_the_recording(recorded_bag, tmp_path):
    bag, counts, _ = recorded_bag
    out = tmp_path / 'same'
    metrics, comparison = rerun(bag, out, figures=False, quiet=True)
    ticks = counts['/joint_states']
    assert metrics['rerun']['ticks'] == ticks
    assert metrics['rerun']['scenario_source'].endswith('(custom_data)')
    for key, expected in (('estimate', ticks), ('command', ticks), ('arc', ticks),
                          ('mpc', counts['/wip/drive_torque']), ('wheel_torques', ticks)):
        entry = comparison[key]
        assert entry['compared'] == expected, key
        for field, figures in entry['fields'].items():
            assert figures['max_abs_difference'] <= REPRODUCE_TOLERANCE, (key, field)
    # The new bag holds the recording byte for byte plus the recomputed topics; an
    # independent reader opens it.
    topics = read_topics(out / 'bag')
    for topic, count in counts.items():
        assert topics[topic].message_count == count
    assert topics['/rerun/wip/wheel_torques'].message_count == ticks
    assert topics['/rerun/wip/drive_torque'].message_count == counts['/wip/drive_torque']
    with Reader(out / 'bag') as reader:
        assert reader.message_count == sum(t.message_count for t in topics.values())
        original = {}
        with Reader(bag) as source:
            for connection, stamp, data in source.messages():
                original.setdefault(connection.topic, []).append((stamp, bytes(data)))
        copied = {}
        for connection, stamp, data in reader.messages():
            if connection.topic in original:
                copied.setdefault(connection.topic, []).append((stamp, bytes(data)))
        assert copied == original
    for name in ('metrics.json', 'comparison.json', 'timeseries.npz', 'scenario.yaml'):
        assert (out / name).is_file()
    assert json.loads((out / 'comparison.json').read_text()) == comparison


def test_changing_an_eso_gain_changes_estimates_and_torques(recorded_bag, tmp_path):
    bag, _, result = recorded_bag
    scenario_file = tmp_path / 'slower_eso.yaml'
    scenario_file.write_text('duration: 3.0\neso:\n  tilt_rate_bandwidth: 20.0\n'
                             '  yaw_rate_bandwidth: 10.0\n')
    out = tmp_path / 'slower'
    assert main([str(bag), '--scenario', str(scenario_file), '--out', str(out),
                 '--no-figures', '--quiet']) == 0
    comparison = json.loads((out / 'comparison.json').read_text())
    # Halving the rate observers' bandwidths (the default gyro estimator; with the
    # paper's ESOs, doubling epsilon does the same): the disturbance estimates lag
    # visibly during the start-up transient. "Visibly" = more
    # than 5 % of the recorded range, i.e. 1e5 times the reproduction tolerance.
    estimate = comparison['estimate']['fields']
    for field in ('f1', 'f3'):
        assert estimate[field]['max_abs_difference'] > 0.05 * estimate[field][
            'max_abs_recorded'], field
    # ... and so do the torques computed from them (ARC from f1, MPC from f2, f3).
    assert comparison['arc']['fields']['tau_omega']['max_abs_difference'] > 0.01
    assert comparison['mpc']['fields']['tau_v']['max_abs_difference'] > 0.01
    assert _worst(comparison['wheel_torques']) > 0.01
    # Open loop: the recorded states (ground truth) are reported unchanged.
    metrics = json.loads((out / 'metrics.json').read_text())
    assert metrics['max_abs_theta_rad'] == pytest.approx(
        float(abs(result.record['truth']['theta']).max()), abs=0.0)
    assert metrics['rerun']['open_loop'] is True


def test_rerun_refuses_a_bag_without_sensor_topics(tmp_path, capsys):
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String
    from wip_bag.bag_writer import Rosbag2McapWriter
    with Rosbag2McapWriter(tmp_path / 'chatter') as bag:
        bag.add_topic('/chatter', 'std_msgs/msg/String')
        bag.write('/chatter', serialize_message(String(data='hi')), 1)
    assert main([str(tmp_path / 'chatter'), '--out', str(tmp_path / 'out'), '--quiet']) == 2
    assert 'no control tick' in capsys.readouterr().err
    # The failed re-run left no OUT/bag behind that would block the next one.
    assert not (tmp_path / 'out' / 'bag').exists()


def test_timing_rules_for_a_bag_without_clock(recorded_bag, tmp_path):
    # The same run recorded without /clock, as in real time: 'auto' picks the receive
    # order. Here every message of a tick has the same log time, so the newest command
    # received before a tick is the one stamped t_(k-1), exactly as with stamps: the three
    # ESO channels reproduce to the same tolerance. A GPS fix received with (not before)
    # the tick's samples is used at the next tick, as by the real-time ESO node, so the
    # planar position (and the commands, yaw and drive torques built on it) may differ
    # (the yaw ARC did reproduce with the paper's design only because ω_d sat on its
    # limit at the start); with --timing stamps everything reproduces again.
    _, _, result = recorded_bag
    scenario = scenario_from_mapping({'duration': DURATION})
    bag = tmp_path / 'no_clock'
    write_record_as_bag(result, scenario, bag, clock=False)
    metrics, comparison = rerun(bag, tmp_path / 'auto', figures=False, quiet=True)
    assert metrics['rerun']['timing'] == 'receive'
    for field in ('phi', 'omega', 'f1', 'x_v', 'v', 'f2', 'theta', 'theta_dot', 'f3'):
        assert comparison['estimate']['fields'][field]['max_abs_difference'] <= (
            REPRODUCE_TOLERANCE), field
    metrics, comparison = rerun(bag, tmp_path / 'stamps', figures=False, quiet=True,
                                timing='stamps')
    assert metrics['rerun']['timing'] == 'stamps'
    for key, entry in comparison.items():
        assert _worst(entry) <= REPRODUCE_TOLERANCE, key
