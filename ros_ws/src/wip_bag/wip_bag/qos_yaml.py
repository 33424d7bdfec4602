"""QoS profiles in the form rosbag2 stores them (bag metadata version 9).

rosbag2 (Jazzy) records, for every topic, the QoS profiles *offered* by its publishers:

- in ``metadata.yaml`` (version 9) under ``topic_metadata.offered_qos_profiles`` as a YAML
  sequence of mappings;
- in the MCAP channel metadata under the key ``offered_qos_profiles`` as that same sequence
  dumped to a YAML *string* (``rosbag2_storage::serialize_rclcpp_qos_vector``).

Version 9 writes the policies by name (``keep_last``, ``reliable``, ``volatile``,
``automatic``, ``unknown`` ...: ``rmw_qos_*_policy_to_str``) and durations as ``{sec, nsec}``;
an infinite duration (``RMW_DURATION_INFINITE``, 2^63 - 1 ns) is ``{sec: 9223372036,
nsec: 854775807}``. See ``rosbag2_storage/src/rosbag2_storage/qos.cpp`` in ros2/rosbag2.

This module has no rclpy import: :func:`qos_profile_to_dict` reads an ``rclpy.qos.QoSProfile``
by duck typing, so the bag writer stays usable (and testable) without ROS.
"""

import yaml

# Policy names of rmw's ``rmw_qos_*_policy_to_str`` indexed by the rmw enum value (the value
# of rclpy's ``QoS*Policy`` enums is the rmw value).
HISTORY_NAMES = ('system_default', 'keep_last', 'keep_all', 'unknown')
RELIABILITY_NAMES = ('system_default', 'reliable', 'best_effort', 'unknown', 'best_available')
DURABILITY_NAMES = ('system_default', 'transient_local', 'volatile', 'unknown', 'best_available')
LIVELINESS_NAMES = (
    'system_default', 'automatic', 'manual_by_node', 'manual_by_topic', 'unknown',
    'best_available')

INFINITE_DURATION_NS = 2**63 - 1  # RMW_DURATION_INFINITE [ns]
NANOSECONDS_PER_SECOND = 1_000_000_000

_KEYS = (
    'history', 'depth', 'reliability', 'durability', 'deadline', 'lifespan', 'liveliness',
    'liveliness_lease_duration', 'avoid_ros_namespace_conventions')


def _policy_name(value, names, what):
    """Return the rosbag2 v9 name of a QoS policy given as enum, int or name."""
    if isinstance(value, str):
        name = value.lower()
        if name not in names:
            raise ValueError(f'unknown {what} policy {value!r}; expected one of {names}')
        return name
    index = int(getattr(value, 'value', value))
    if not 0 <= index < len(names):
        raise ValueError(f'unknown {what} policy value {index}')
    return names[index]


def duration_to_dict(duration):
    """Convert a duration to rosbag2's ``{sec, nsec}`` mapping.

    Parameters
    ----------
    duration : rclpy.duration.Duration, int or dict
        A duration object with ``nanoseconds``, a count of nanoseconds [ns], or a mapping
        with ``sec`` and ``nsec`` (returned as is, after a check).

    Returns
    -------
    dict
        ``{'sec': int, 'nsec': int}`` with ``0 <= nsec < 1e9``.
    """
    if isinstance(duration, dict):
        return {'sec': int(duration['sec']), 'nsec': int(duration['nsec'])}
    nanoseconds = int(getattr(duration, 'nanoseconds', duration))
    if nanoseconds < 0:
        raise ValueError(f'negative QoS duration {nanoseconds} ns')
    return {'sec': nanoseconds // NANOSECONDS_PER_SECOND,
            'nsec': nanoseconds % NANOSECONDS_PER_SECOND}


def qos_profile_to_dict(profile):
    """Convert a QoS profile to one entry of rosbag2's ``offered_qos_profiles`` (v9).

    Parameters
    ----------
    profile : rclpy.qos.QoSProfile or dict
        An rclpy profile (read by attribute) or a mapping with the same keys (missing keys
        take rmw's defaults: system_default policies, zero durations).

    Returns
    -------
    dict
        Mapping with the keys, in rosbag2's order: history, depth, reliability, durability,
        deadline, lifespan, liveliness, liveliness_lease_duration,
        avoid_ros_namespace_conventions.
    """
    if isinstance(profile, dict):
        unknown = set(profile) - set(_KEYS)
        if unknown:
            raise ValueError(f'unknown QoS keys {sorted(unknown)}')

        def get(key, default):
            return profile.get(key, default)
    else:
        def get(key, default):
            return getattr(profile, key, default)
    return {
        'history': _policy_name(get('history', 0), HISTORY_NAMES, 'history'),
        'depth': int(get('depth', 0)),
        'reliability': _policy_name(get('reliability', 0), RELIABILITY_NAMES, 'reliability'),
        'durability': _policy_name(get('durability', 0), DURABILITY_NAMES, 'durability'),
        'deadline': duration_to_dict(get('deadline', 0)),
        'lifespan': duration_to_dict(get('lifespan', 0)),
        'liveliness': _policy_name(get('liveliness', 0), LIVELINESS_NAMES, 'liveliness'),
        'liveliness_lease_duration': duration_to_dict(get('liveliness_lease_duration', 0)),
        'avoid_ros_namespace_conventions': bool(get('avoid_ros_namespace_conventions', False)),
    }


def normalize_offered_qos(profiles):
    """Return offered QoS profiles as a list of rosbag2 v9 mappings.

    Parameters
    ----------
    profiles : None, str or sequence
        None or '' (no profile known), a YAML string as found in MCAP channel metadata or in
        a version <= 8 metadata.yaml, or a sequence of rclpy profiles / mappings.

    Returns
    -------
    list of dict
    """
    if profiles is None or profiles == '':
        return []
    if isinstance(profiles, str):
        try:
            profiles = yaml.safe_load(profiles)
        except yaml.YAMLError as err:
            raise ValueError(f'offered QoS profiles are not valid YAML: {err}') from err
        if profiles is None:
            return []
        if not isinstance(profiles, list):
            raise ValueError('offered QoS profiles YAML must be a sequence of mappings')
    return [qos_profile_to_dict(p) for p in profiles]


def dump_offered_qos(profiles):
    """Dump offered QoS profiles to the YAML string of the MCAP channel metadata.

    Parameters
    ----------
    profiles : None, str or sequence
        Anything :func:`normalize_offered_qos` accepts.

    Returns
    -------
    str
        Block-style YAML sequence without a trailing newline ('[]' for no profile), as
        yaml-cpp's ``YAML::Dump`` writes it in rosbag2.
    """
    dicts = normalize_offered_qos(profiles)
    if not dicts:
        return '[]'
    return yaml.safe_dump(dicts, default_flow_style=False, sort_keys=False).rstrip('\n')
