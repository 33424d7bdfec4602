"""The replayer's timing and QoS: bag time against the wall clock, playback QoS, remaps.

No node here: :class:`PlaybackClock` maps the steady wall clock to bag time (rate,
pauses), :func:`playback_qos` is rosbag2's rule for the QoS a recorded topic is played
with, and :func:`parse_remaps` reads the ``remap`` parameter.
"""

from rclpy.duration import Duration, Infinite
from rclpy.exceptions import InvalidTopicNameException
from rclpy.qos import (QoSDurabilityPolicy, QoSHistoryPolicy, QoSLivelinessPolicy, QoSProfile,
                       QoSReliabilityPolicy)
from rclpy.validate_full_topic_name import validate_full_topic_name

from .qos_yaml import INFINITE_DURATION_NS, normalize_offered_qos

_RELIABILITY = {'system_default': QoSReliabilityPolicy.SYSTEM_DEFAULT,
                'reliable': QoSReliabilityPolicy.RELIABLE,
                'best_effort': QoSReliabilityPolicy.BEST_EFFORT,
                'best_available': QoSReliabilityPolicy.BEST_AVAILABLE}
_DURABILITY = {'system_default': QoSDurabilityPolicy.SYSTEM_DEFAULT,
               'transient_local': QoSDurabilityPolicy.TRANSIENT_LOCAL,
               'volatile': QoSDurabilityPolicy.VOLATILE,
               'best_available': QoSDurabilityPolicy.BEST_AVAILABLE}
_LIVELINESS = {'system_default': QoSLivelinessPolicy.SYSTEM_DEFAULT,
               'automatic': QoSLivelinessPolicy.AUTOMATIC,
               'manual_by_topic': QoSLivelinessPolicy.MANUAL_BY_TOPIC,
               'best_available': QoSLivelinessPolicy.BEST_AVAILABLE}


def _duration(mapping):
    nanoseconds = int(mapping['sec']) * 1_000_000_000 + int(mapping['nsec'])
    if nanoseconds >= INFINITE_DURATION_NS:
        return Infinite
    return Duration(nanoseconds=nanoseconds)


def playback_qos(offered_profiles, depth):
    """QoS to publish a recorded topic with (rosbag2's adapt_offer_to_recorded_offers).

    Parameters
    ----------
    offered_profiles : str or sequence
        The recorded ``offered_qos_profiles`` (YAML string or v9 mappings).
    depth : int
        Keep-last depth of the history.
    """
    profiles = normalize_offered_qos(offered_profiles)
    default = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=depth,
                         reliability=QoSReliabilityPolicy.RELIABLE,
                         durability=QoSDurabilityPolicy.VOLATILE)
    if not profiles:
        return default
    keys = ('reliability', 'durability', 'deadline', 'liveliness', 'liveliness_lease_duration')
    first = profiles[0]
    if any(tuple(p[k] for k in keys) != tuple(first[k] for k in keys) for p in profiles[1:]):
        return default
    try:
        return QoSProfile(
            history=QoSHistoryPolicy.KEEP_LAST, depth=depth,
            reliability=_RELIABILITY[first['reliability']],
            durability=_DURABILITY[first['durability']],
            deadline=_duration(first['deadline']),
            lifespan=_duration(first['lifespan']),
            liveliness=_LIVELINESS[first['liveliness']],
            liveliness_lease_duration=_duration(first['liveliness_lease_duration']),
            avoid_ros_namespace_conventions=bool(first['avoid_ros_namespace_conventions']))
    except KeyError:  # 'unknown' policies: fall back like rosbag2
        return default


def parse_remaps(pairs):
    """{'from': 'to'} from ``['from:=to', ...]``."""
    out = {}
    for pair in pairs:
        source, sep, target = pair.partition(':=')
        if not sep or not source or not target:
            raise ValueError(f'remap {pair!r} is not of the form from:=to')
        for name in (source, target):
            try:
                validate_full_topic_name('/' + name.lstrip('/'))
            except InvalidTopicNameException:
                raise ValueError(f'remap {pair!r}: {name!r} is not a valid ROS topic name '
                                 '(letters, digits and underscores in /-separated tokens, '
                                 'none starting with a digit)') from None
        out[source] = target
    return out


class PlaybackClock:
    """Bag time as a function of the steady wall clock, with a rate and pauses.

    bag_time(now) = anchor_bag + (now - anchor_wall) * rate while playing; frozen while
    paused. Times in integer nanoseconds (bag) and float seconds (wall).
    """

    def __init__(self, rate, start_bag_ns, now):
        self.rate = float(rate)
        self.paused = False
        self.restart(start_bag_ns, now)

    def restart(self, start_bag_ns, now):
        self.anchor_bag_ns = int(start_bag_ns)
        self.anchor_wall = now

    def bag_time_ns(self, now):
        if self.paused:
            return self.anchor_bag_ns
        return self.anchor_bag_ns + int(round((now - self.anchor_wall) * self.rate * 1e9))

    def wall_time(self, bag_ns):
        """Wall time [s] at which bag time ``bag_ns`` is reached (inf while paused)."""
        if self.paused:
            return float('inf')
        return self.anchor_wall + (bag_ns - self.anchor_bag_ns) * 1e-9 / self.rate

    def pause(self, now):
        if not self.paused:
            self.anchor_bag_ns = self.bag_time_ns(now)
            self.paused = True

    def resume(self, now):
        if self.paused:
            self.paused = False
            self.anchor_wall = now
