"""The simulation graph's design: who publishes and subscribes what, and what a run must see.

Pure tables and functions over them: what run_graph waits for before the plant may start
(:func:`expected_endpoints`, :func:`unmatched_pairs`) and what a lockstep recording must hold
at its end (:func:`expected_recorded`).
"""

from __future__ import annotations

import pathlib
from typing import Any, Callable

from wip_viewer.viewer_core import LATCHED_TOPICS

from .launcher import in_namespace, INPUT_TOPICS, VIEWER_TOPICS
from .params_files import CONTROLLER_NODES
from .probe import Probe


#: Publishers of each topic in the graph design.
PUBLISHERS = {
    '/joint_states': ('plant',),
    '/imu/data': ('plant',),
    '/gps/fix': ('plant',),
    '/wip/ground_truth': ('plant',),
    '/wip/reference': ('reference',),
    '/wip/state_estimate': ('eso',),
    '/wip/velocity_command': ('trajectory_generator',),
    '/wip/yaw_torque': ('arc',),
    '/wip/drive_torque': ('mpc',),
    '/wip/wheel_torques': ('torque_mixer',),
    '/effort_controller/commands': ('torque_mixer',),
}
#: Subscriptions of each topic in the graph design (without the recorder).
SUBSCRIBERS = {
    '/joint_states': ('eso',),
    '/imu/data': ('eso',),
    '/gps/fix': ('eso',),
    '/wip/ground_truth': (),
    '/wip/reference': ('trajectory_generator',),
    '/wip/state_estimate': ('trajectory_generator', 'arc', 'mpc'),
    '/wip/velocity_command': ('arc', 'mpc'),
    '/wip/yaw_torque': ('mpc', 'torque_mixer'),
    '/wip/drive_torque': ('torque_mixer',),
    '/wip/wheel_torques': ('plant', 'eso'),
    '/effort_controller/commands': (),
}
#: Lockstep: /clock is published by the plant; every controller node's time source
#: subscribes to it, except the reference node's, which its /clock ticker drives
#: (wip_runtime.clock.ClockTicker). Composed, the nodes share the reference node's
#: time source (wip_runtime.composition.share_sim_clock): one subscription.
CLOCK_SUBSCRIPTIONS = {'separate': len(CONTROLLER_NODES), 'composed': 1, 'single': 1}
#: Nodes with a /clock subscription of their own in lockstep, per layout.
CLOCK_NODES = {'separate': CONTROLLER_NODES, 'composed': ('reference',),
               'single': ('reference',)}
#: Topics recorded with --record: the graph's, its inputs (with /clock in lockstep; with the
#: viewer's topics, :data:`VIEWER_TOPICS`, when the viewer runs).
RECORDED_TOPICS = tuple(PUBLISHERS) + ('/diagnostics',) + INPUT_TOPICS

#: /diagnostics key prefixes of a node's DDS match counts of one topic, '<KEY> <topic>':
#: subscriptions matched by its publisher, publishers matched by its subscription (see
#: :func:`unmatched_pairs`, ``wip_runtime.diagnostics``).
MATCHED_KEY = 'matched subscriptions'
MATCHED_PUBLISHERS_KEY = 'matched publishers'


def expected_endpoints(clock_mode: str, recording: bool, layout: str = 'separate',
                       viewer: bool = False) -> dict[str, tuple[int, int]]:
    """Minimum (publishers, subscriptions) of each topic before the plant may start."""
    extra = 1 if recording else 0
    expected = {topic: (len(PUBLISHERS[topic]), len(SUBSCRIBERS[topic]) + extra)
                for topic in PUBLISHERS}
    if viewer:
        # Its outputs must reach the recorder from the first message (the transient-local
        # ones reach a late reader too, and exist only with viewer.robot_model); its own
        # inputs are best effort and may miss the first ticks (nothing waits for it).
        expected.update({topic: (1, extra) for topic in VIEWER_TOPICS
                         if topic not in LATCHED_TOPICS})
    if clock_mode == 'lockstep':
        # The recorder runs on sim time too (its time source) and records /clock.
        expected['/clock'] = (1, CLOCK_SUBSCRIPTIONS[layout] + 2 * extra)
    return expected


def missing_endpoints(probe: Probe, expected: dict[str, tuple[int, int]],
                      nodes: list[str]) -> list[str]:
    """Return what the graph still lacks (empty when complete)."""
    missing = []
    present = probe.node_names()
    absent = [n for n in nodes if n not in present]
    if absent:
        missing.append('nodes ' + ', '.join(absent))
    for topic, (publishers, subscribers) in expected.items():
        have_pub, have_sub = probe.count(topic)
        if have_pub < publishers or have_sub < subscribers:
            missing.append(f'{topic} ({have_pub}/{publishers} publishers, '
                           f'{have_sub}/{subscribers} subscriptions)')
    return missing


def unmatched_pairs(status_values: Callable[[str], dict[str, str] | None], namespace: str,
                    recording: bool, clock: str, layout: str) -> list[str]:
    """Designed pairs whose DDS match is not yet seen by both sides.

    A pair counts as matched only when BOTH sides have seen the match, as the match
    counts in the controllers' /diagnostics report it (``matched subscriptions <topic>``
    of a publisher, ``matched publishers <topic>`` of a subscription; the plant checks
    its own endpoints before it starts). DDS matches each side on its own: a reliable
    volatile reader that has not matched the writer yet loses what it sends, and in
    lockstep one lost message of the first tick stalls the run. In lockstep every
    controller must also have matched the plant's /clock. ``status_values(node)``: the
    latest /diagnostics values of that node, or None.
    """
    extra = 1 if recording else 0
    # The nodes report their topics' full names (under the run's namespace).
    ns = namespace
    checks = []   # (node, key, wanted)
    for topic, publishers in PUBLISHERS.items():
        checks += [(name, f'{MATCHED_KEY} {in_namespace(topic, ns)}',
                    len(SUBSCRIBERS[topic]) + extra) for name in publishers]
    for topic, subscribers in SUBSCRIBERS.items():
        checks += [(name, f'{MATCHED_PUBLISHERS_KEY} {in_namespace(topic, ns)}',
                    len(PUBLISHERS[topic])) for name in subscribers]
    if clock == 'lockstep':
        checks += [(name, f'{MATCHED_PUBLISHERS_KEY} /clock', 1)
                   for name in CLOCK_NODES[layout]]
    missing = []
    for name, key, wanted in checks:
        if name == 'plant':
            continue  # Checked by the plant itself before it starts.
        values = status_values(name)
        value = None if values is None else values.get(key)
        if value is not None and int(value) < wanted:
            missing.append(f'{name}: {key} {value}/{wanted}')
    return missing


def expected_recorded(ticks: int, scenario: Any) -> dict[str, int]:
    """Messages a lockstep run of ``ticks`` control ticks published per topic.

    Every control tick t_0 .. t_{k-1} produces one message of each topic (the MPC one
    every ``drive_decimation`` ticks, GPS every control_rate / gps_rate ticks), and the
    final ground truth at t_k has no tick after it.
    """
    gps_every = max(1, round(scenario.rates.control_rate / scenario.sensors.gps_rate))
    expected = {topic: ticks for topic in PUBLISHERS}
    expected['/clock'] = ticks
    expected['/wip/ground_truth'] = ticks + 1
    expected['/gps/fix'] = -(-ticks // gps_every)
    expected['/wip/drive_torque'] = -(-ticks // scenario.drive_decimation)
    return expected


def plant_parameters(clock: str, layout: str, recording: bool,
                     stats_file: pathlib.Path) -> dict[str, Any]:
    """Return the plant's start handshake, stats file and end of run, for the params file.

    The plant starts on ``/plant/start`` once the subscriptions of this design (with the
    recorder's, when ``recording``) have matched its publishers.
    """
    return {
        'autostart': False,
        'start.expected_sensor_subscribers': 1 + recording,
        'start.expected_ground_truth_subscribers': int(recording),
        'start.expected_clock_subscribers': (
            CLOCK_SUBSCRIPTIONS[layout] + 2 * recording if clock == 'lockstep' else 0),
        'stats_file': str(stats_file),
        # Real time, the plant in its own process: the controllers are stopped at the
        # scenario's end while the plant still feeds them (GraphRunner.watch).
        'hold_at_end': clock == 'realtime' and layout != 'single',
    }
