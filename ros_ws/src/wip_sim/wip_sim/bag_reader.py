"""Read rosbag2 MCAP bags without ROS: messages decoded from the schemas embedded in the bag.

Decoding uses ``mcap`` and ``mcap-ros2-support``, which build decoders from the ``ros2msg``
schemas stored in the file, so neither rclpy nor the message packages are needed (a bag
recorded on a robot can be read anywhere). Works on a bag directory (``metadata.yaml`` + one
or more ``.mcap`` files) or on a single ``.mcap`` file, including one whose writer was killed
before finishing it (read up to its last complete record).
"""

import heapq
import pathlib
import struct
from typing import Any, NamedTuple

from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
import yaml

METADATA_FILE_NAME = 'metadata.yaml'

# What a truncated file raises while its last record is read.
_TRUNCATION_ERRORS = (McapError, EOFError, ValueError, IndexError, OSError, MemoryError,
                      struct.error)


class BagReadError(Exception):
    """A bag cannot be found or read."""


class BagMessage(NamedTuple):
    """One decoded message of a bag."""

    topic: str
    type_name: str
    log_time_ns: int  # receive time [ns] (MCAP log time)
    message: Any  # decoded message (attributes named like the .msg fields)


def mcap_files(path):
    """Return the MCAP files of a bag directory (in recording order) or of a single file.

    The order is that of ``relative_file_paths`` in ``metadata.yaml`` when present, else the
    sorted ``*.mcap`` files of the directory.
    """
    path = pathlib.Path(path)
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise BagReadError(f'no bag at {path}')
    metadata_path = path / METADATA_FILE_NAME
    if metadata_path.is_file():
        info = yaml.safe_load(metadata_path.read_text(encoding='utf-8'))
        info = (info or {}).get('rosbag2_bagfile_information', {})
        if info.get('storage_identifier', 'mcap') != 'mcap':
            raise BagReadError(
                f'{path}: storage {info.get("storage_identifier")!r} is not mcap')
        files = [path / name for name in info.get('relative_file_paths', ())]
        if files and all(f.is_file() for f in files):
            return files
    files = sorted(path.glob('*.mcap'))
    if not files:
        raise BagReadError(f'{path}: no .mcap file')
    return files


def scan_mcap_records(path):
    """Yield ``(kind, record)`` for the schemas, channels and messages of an MCAP file.

    Reads the file front to back and stops quietly at a truncated or corrupt tail (a writer
    killed before ``finish()``), so it recovers everything up to the last complete chunk.
    ``kind`` is 'schema', 'channel' or 'message'.
    """
    with open(path, 'rb') as stream:
        records = StreamReader(stream).records
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except _TRUNCATION_ERRORS:
                return
            if isinstance(record, Schema):
                yield 'schema', record
            elif isinstance(record, Channel):
                yield 'channel', record
            elif isinstance(record, Message):
                yield 'message', record


def _has_summary(stream):
    try:
        return SeekingReader(stream).get_summary() is not None
    except _TRUNCATION_ERRORS:
        return False
    finally:
        stream.seek(0)


def _read_file(path, topics):
    factory = DecoderFactory()
    with open(path, 'rb') as stream:
        if _has_summary(stream):
            reader = SeekingReader(stream, decoder_factories=[factory])
            for schema, channel, message, decoded in reader.iter_decoded_messages(
                    topics=topics, log_time_order=True):
                yield BagMessage(channel.topic, schema.name if schema else '',
                                 message.log_time, decoded)
            return
    # Unfinished file: linear scan in file (= receive) order.
    schemas, channels, decoders = {}, {}, {}
    for kind, record in scan_mcap_records(path):
        if kind == 'schema':
            schemas[record.id] = record
        elif kind == 'channel':
            channels[record.id] = record
        else:
            channel = channels.get(record.channel_id)
            if channel is None or (topics is not None and channel.topic not in topics):
                continue
            schema = schemas.get(channel.schema_id)
            decoder = decoders.get(channel.id)
            if decoder is None:
                decoder = factory.decoder_for(channel.message_encoding, schema)
                if decoder is None:
                    raise BagReadError(
                        f'{path}: cannot decode topic {channel.topic} (encoding '
                        f'{channel.message_encoding!r}, schema '
                        f'{schema.encoding if schema else None!r})')
                decoders[channel.id] = decoder
            yield BagMessage(channel.topic, schema.name if schema else '', record.log_time,
                             decoder(record.data))


def read_bag(path, topics=None):
    """Iterate over the decoded messages of a bag, in receive-time order per file.

    Parameters
    ----------
    path : str or pathlib.Path
        A bag directory or a single ``.mcap`` file.
    topics : iterable of str, optional
        Only these topics (default: all).

    Yields
    ------
    BagMessage
        ``(topic, type_name, log_time_ns, message)``; unpacks as a 4-tuple.

    Raises
    ------
    BagReadError
        If the bag is missing or a topic's schema cannot be decoded (e.g. 'ros2idl').
    """
    if isinstance(topics, str):
        topics = [topics]
    topics = None if topics is None else set(topics)
    for file in mcap_files(path):
        yield from _read_file(file, topics)


def bag_summary(path):
    """Return the figures of a bag, computed from its MCAP content (not from metadata.yaml).

    Parameters
    ----------
    path : str or pathlib.Path
        A bag directory or a single ``.mcap`` file.

    Returns
    -------
    dict
        ``path``, ``files`` (list of str), ``message_count``, ``start_ns``, ``end_ns``,
        ``duration_ns`` (log times [ns]; ``None``, ``None`` and 0 for an empty bag),
        ``finished`` (every file has its summary section, i.e. was closed properly) and
        ``topics``: topic -> dict(``type``, ``message_count``, ``start_ns``, ``end_ns``).
    """
    files = mcap_files(path)
    topics = {}
    finished = True
    for file in files:
        with open(file, 'rb') as stream:
            file_finished = _has_summary(stream)
        finished = finished and file_finished
        for kind, record in _iter_records(file, file_finished):
            if kind == 'channel':
                schema, channel = record
                topics.setdefault(channel.topic, {
                    'type': schema.name if schema else '', 'message_count': 0,
                    'start_ns': None, 'end_ns': None})
            else:
                channel, message = record
                entry = topics[channel.topic]
                entry['message_count'] += 1
                if entry['start_ns'] is None or message.log_time < entry['start_ns']:
                    entry['start_ns'] = message.log_time
                if entry['end_ns'] is None or message.log_time > entry['end_ns']:
                    entry['end_ns'] = message.log_time
    starts = [t['start_ns'] for t in topics.values() if t['start_ns'] is not None]
    ends = [t['end_ns'] for t in topics.values() if t['end_ns'] is not None]
    start_ns = min(starts) if starts else None
    end_ns = max(ends) if ends else None
    return {
        'path': str(path),
        'files': [str(f) for f in files],
        'message_count': sum(t['message_count'] for t in topics.values()),
        'start_ns': start_ns,
        'end_ns': end_ns,
        'duration_ns': 0 if start_ns is None else end_ns - start_ns,
        'finished': finished,
        'topics': topics,
    }


def _iter_records(file, finished):
    """Yield ('channel', (schema, channel)) and ('message', (channel, message)), undecoded."""
    if finished:
        with open(file, 'rb') as stream:
            summary = SeekingReader(stream).get_summary()
            for channel in summary.channels.values():
                yield 'channel', (summary.schemas.get(channel.schema_id), channel)
            stream.seek(0)
            for _, channel, message in SeekingReader(stream).iter_messages(
                    log_time_order=False):
                yield 'message', (channel, message)
        return
    schemas, channels = {}, {}
    for kind, record in scan_mcap_records(file):
        if kind == 'schema':
            schemas[record.id] = record
        elif kind == 'channel':
            channels[record.id] = record
            yield 'channel', (schemas.get(record.schema_id), record)
        elif record.channel_id in channels:
            yield 'message', (channels[record.channel_id], record)


# -- raw access (the replayer republishes serialized messages as they are) ----------------

class RawMessage(NamedTuple):
    """One serialized message of a bag, as recorded."""

    topic: str
    log_time_ns: int  # receive time [ns] (MCAP log time)
    publish_time_ns: int  # send time [ns] (MCAP publish time)
    data: bytes  # serialized message (CDR for rosbag2 bags)


class TopicMetadata(NamedTuple):
    """What a bag holds of a topic: its type, definition, offered QoS and message count."""

    name: str
    type_name: str
    serialization_format: str  # MCAP message encoding, 'cdr' for rosbag2 bags
    offered_qos_profiles: str  # YAML string of the MCAP channel metadata ('' if absent)
    type_hash: str  # RIHS01 hash ('' if absent)
    definition_encoding: str  # 'ros2msg', 'ros2idl' or ''
    definition: str  # full message definition (rosbag2's schema format)
    message_count: int


def _channels_and_counts(file):
    """(schemas, channels, counts per channel id) of one MCAP file."""
    with open(file, 'rb') as stream:
        finished = _has_summary(stream)
        if finished:
            summary = SeekingReader(stream).get_summary()
            counts = dict(summary.statistics.channel_message_counts) if (
                summary.statistics is not None) else None
            if counts is None:
                counts = {cid: 0 for cid in summary.channels}
                stream.seek(0)
                for _, channel, _ in SeekingReader(stream).iter_messages(
                        log_time_order=False):
                    counts[channel.id] += 1
            return dict(summary.schemas), dict(summary.channels), counts
    schemas, channels, counts = {}, {}, {}
    for kind, record in scan_mcap_records(file):
        if kind == 'schema':
            schemas[record.id] = record
        elif kind == 'channel':
            channels[record.id] = record
            counts.setdefault(record.id, 0)
        elif record.channel_id in counts:
            counts[record.channel_id] += 1
    return schemas, channels, counts


def read_topics(path):
    """Return the topics of a bag (directory or single file) from its MCAP content.

    Returns
    -------
    dict
        topic -> :class:`TopicMetadata`, in the order the topics first appear; message
        counts are summed over the files.
    """
    topics = {}
    for file in mcap_files(path):
        schemas, channels, counts = _channels_and_counts(file)
        for channel_id, channel in channels.items():
            schema = schemas.get(channel.schema_id)
            count = counts.get(channel_id, 0)
            known = topics.get(channel.topic)
            if known is not None:
                if known.type_name != (schema.name if schema else ''):
                    raise BagReadError(
                        f'{path}: topic {channel.topic} has two types, {known.type_name} '
                        f'and {schema.name if schema else None}')
                topics[channel.topic] = known._replace(
                    message_count=known.message_count + count)
                continue
            metadata = channel.metadata or {}
            topics[channel.topic] = TopicMetadata(
                name=channel.topic,
                type_name=schema.name if schema else '',
                serialization_format=channel.message_encoding,
                offered_qos_profiles=metadata.get('offered_qos_profiles', ''),
                type_hash=metadata.get('topic_type_hash', ''),
                definition_encoding=schema.encoding if schema else '',
                definition=schema.data.decode('utf-8', 'replace') if schema else '',
                message_count=count)
    return topics


def _iter_raw_file(file, topics, start_ns, end_ns):
    with open(file, 'rb') as stream:
        if _has_summary(stream):
            reader = SeekingReader(stream)
            for _, channel, message in reader.iter_messages(
                    topics=topics, starting_at=start_ns, ending_at=end_ns,
                    log_time_order=True):
                yield RawMessage(channel.topic, message.log_time, message.publish_time,
                                 message.data)
            return
    channels = {}
    for kind, record in scan_mcap_records(file):
        if kind == 'channel':
            channels[record.id] = record.topic
        elif kind == 'message':
            topic = channels.get(record.channel_id)
            if topic is None or (topics is not None and topic not in topics):
                continue
            if start_ns is not None and record.log_time < start_ns:
                continue
            if end_ns is not None and record.log_time > end_ns:
                continue
            yield RawMessage(topic, record.log_time, record.publish_time, record.data)


def iter_raw_messages(path, topics=None, start_ns=None, end_ns=None):
    """Iterate over the serialized messages of a bag in receive-time order.

    Parameters
    ----------
    path : str or pathlib.Path
        A bag directory or a single ``.mcap`` file.
    topics : iterable of str, optional
        Only these topics (default: all).
    start_ns, end_ns : int, optional
        Only messages with ``start_ns <= log time <= end_ns`` [ns].

    Yields
    ------
    RawMessage
        ``(topic, log_time_ns, publish_time_ns, data)``. The files of a split bag are
        merged by log time (stable: equal times keep the file order).
    """
    if isinstance(topics, str):
        topics = [topics]
    topics = None if topics is None else sorted(set(topics))
    iterators = [_iter_raw_file(f, topics, start_ns, end_ns) for f in mcap_files(path)]
    if len(iterators) == 1:
        yield from iterators[0]
    else:
        yield from heapq.merge(*iterators, key=lambda m: m.log_time_ns)
