"""The QoS profiles of the graph's topics, and the history of a lockstep run's writers."""

from __future__ import annotations

from rclpy.qos import (QoSDurabilityPolicy, QoSHistoryPolicy, QoSProfile,
                       QoSReliabilityPolicy)

#: Sensors and commands: reliable, keep last 10 (the graph design).
RELIABLE_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=10,
                          reliability=QoSReliabilityPolicy.RELIABLE,
                          durability=QoSDurabilityPolicy.VOLATILE)
#: A real base's sensors in real time: best effort, keep last 10 (REP 2003's sensor data
#: QoS). A best-effort subscription receives from reliable and best-effort publishers alike
#: (IMU drivers often publish best effort, which a reliable subscription would never
#: match), and a reliable publisher can block in publish() while it matches a new reliable
#: reader: measured with rclpy/Fast DDS, the stand-in base's sensor publish() blocked for
#: 0.33 s as the controllers started, which a balancing robot does not survive.
SENSOR_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=10,
                        reliability=QoSReliabilityPolicy.BEST_EFFORT,
                        durability=QoSDurabilityPolicy.VOLATILE)
#: /tf and /tf_static as tf2_ros's broadcasters offer them (reliable; keep last 100,
#: volatile; keep last 1, transient local: a late listener still gets the fixed frames).
TF_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=100,
                    reliability=QoSReliabilityPolicy.RELIABLE,
                    durability=QoSDurabilityPolicy.VOLATILE)
TF_STATIC_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=1,
                           reliability=QoSReliabilityPolicy.RELIABLE,
                           durability=QoSDurabilityPolicy.TRANSIENT_LOCAL)
#: Writer history of the reliable publishers of a lockstep run [messages]. A reliable
#: keep-last writer drops the oldest sample once its history is full, acknowledged by every
#: reader or not: with the graph design's 10, a recorder whose process was descheduled for a
#: few milliseconds on a loaded machine lost ground-truth samples (1998 of 2001 in a 10 s
#: run). A lockstep run waits for the controllers, not for a recorder or a viewer, so its
#: writers keep 50 s of simulated time of every topic: a reader would have to stall that
#: long (seconds of wall time) to lose a sample. The DDS layer allocates history entries as
#: they are used. (The plant waiting for acknowledgements every few ticks instead costs a
#: DDS heartbeat period each time: docs/decisions/lockstep-recording.md.)
LOCKSTEP_WRITER_DEPTH = 10000


def lockstep_writer_qos(qos: QoSProfile) -> QoSProfile:
    """``qos`` with the history of a lockstep writer when it is reliable keep-last."""
    if (not isinstance(qos, QoSProfile) or qos.history != QoSHistoryPolicy.KEEP_LAST
            or qos.reliability != QoSReliabilityPolicy.RELIABLE
            or qos.depth >= LOCKSTEP_WRITER_DEPTH):
        return qos
    return QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=LOCKSTEP_WRITER_DEPTH,
                      reliability=qos.reliability, durability=qos.durability)


#: /clock of a lockstep run (ClockTicker): reliable. Each sample is a tick the graph waits
#: for; a best-effort subscription lost one under load (the reference node missed t = 1.985 s
#: after a recorder's stall while every other node had it) and the run stopped there. The
#: plant's and the replayer's /clock publishers are reliable; depth 10 so that no sample is
#: lost when two arrive between two spins.
CLOCK_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=10,
                       reliability=QoSReliabilityPolicy.RELIABLE,
                       durability=QoSDurabilityPolicy.VOLATILE)
