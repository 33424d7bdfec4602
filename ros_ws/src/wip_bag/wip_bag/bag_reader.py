"""Read rosbag2 MCAP bags without ROS: messages decoded from the schemas embedded in the bag.

Decoding uses ``mcap`` and ``mcap-ros2-support``, which build decoders from the ``ros2msg``
schemas stored in the file, so neither rclpy nor the message packages are needed (a bag
recorded on a robot can be read anywhere). Works on a bag directory (``metadata.yaml`` + one
or more ``.mcap`` files) or on a single ``.mcap`` file.

Every file is checked before it is read (:mod:`wip_bag.bag_integrity`: each chunk's CRC,
the summary's CRC, a proper end). A damaged or unfinished file raises
:class:`BagIntegrityError`, which names the time range and the topics affected, unless the
caller asks for ``allow_partial=True``: then the intact chunks are read and the damaged
ones skipped (the tools say so, and mark their results ``partial``).
"""

import heapq
import shlex
import os
import sys
import pathlib
from typing import Any, NamedTuple

from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Metadata, Schema
from mcap_ros2.decoder import DecoderFactory
import yaml

from .bag_integrity import FileScan, iter_chunk_records, scan_file
from .cdr_fast import CheckedDecoder, layout_of

METADATA_FILE_NAME = 'metadata.yaml'


class BagReadError(Exception):
    """A bag cannot be found or read."""


class BagIntegrityError(BagReadError):
    """A bag is damaged or unfinished; the message says where, when and which topics."""

    def __init__(self, message: str, scans: list) -> None:
        super().__init__(message)
        self.scans = scans


_SCAN_CACHE: dict = {}


def scan(file) -> FileScan:
    """:func:`wip_bag.bag_integrity.scan_file`, cached while the file is unchanged."""
    file = pathlib.Path(file)
    stat = file.stat()
    key = (str(file.resolve()), stat.st_size, stat.st_mtime_ns, stat.st_ino)
    found = _SCAN_CACHE.get(key)
    if found is None:
        if len(_SCAN_CACHE) > 64:
            _SCAN_CACHE.clear()
        try:
            found = _SCAN_CACHE[key] = scan_file(file)
        except OSError as err:
            raise BagReadError(f'{file}: {err.strerror or err}') from err
    return found


def integrity_problems(scans) -> list[str]:
    """One line per damaged part of the scanned files, times from the bag's first message."""
    starts = [c.start_ns for s in scans for c in s.chunks]
    origin = min(starts) if starts else None
    return [line for s in scans for line in s.problems(origin)]


#: What a bag directory without metadata.yaml means, for the readers' warning and
#: bag_info's verdict (one wording).
NO_METADATA = ('no metadata.yaml (an unfinished recording, or a file lost): ros2 bag and '
               "rosbags cannot open it; the wip-ros tools read the .mcap files' contents; "
               'scripts/bag_repair {bag} writes a new bag with one')
_warned_no_metadata: set[str] = set()


def missing_metadata(path) -> str | None:
    """:data:`NO_METADATA` for a bag directory without metadata.yaml, else None."""
    path = pathlib.Path(path)
    if path.is_dir() and not (path / METADATA_FILE_NAME).is_file():
        return NO_METADATA.format(bag=shlex.quote(str(path)))
    return None


def check_bag(path, allow_partial=False):
    """Scan every file of a bag; raise :class:`BagIntegrityError` if one is damaged.

    Returns the list of :class:`~wip_bag.bag_integrity.FileScan` (in file order). With
    ``allow_partial`` a damaged bag is returned too (its ``problems`` tell what is lost).
    A bag directory without metadata.yaml is read from its files, with a warning on
    stderr (once per bag and process), as bag_info reports it NOT OK.
    """
    missing = missing_metadata(path)
    if missing and str(path) not in _warned_no_metadata:
        _warned_no_metadata.add(str(path))
        print(f'warning: {path}: {missing}', file=sys.stderr)
    scans = [scan(f) for f in mcap_files(path)]
    problems = integrity_problems(scans)
    if problems and not allow_partial:
        raise BagIntegrityError(
            f'{path}: damaged or unfinished bag: ' + '; '.join(problems)
            + ' (scripts/bag_repair recovers the intact chunks into a new bag)', scans)
    return scans


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
        info = read_metadata_file(metadata_path)
        if info.get('storage_identifier', 'mcap') != 'mcap':
            raise BagReadError(
                f'{path}: storage {info.get("storage_identifier")!r} is not mcap')
        names = info.get('relative_file_paths') or ()
        if not isinstance(names, (list, tuple)) or not all(
                isinstance(n, str) and n and os.sep not in n and n not in ('.', '..')
                for n in names):
            raise BagReadError(f'{metadata_path}: relative_file_paths is not a list of file '
                               'names (scripts/bag_repair rebuilds metadata.yaml)')
        files = [path / name for name in names]
        if files and all(f.is_file() for f in files):
            return files
    files = sorted(path.glob('*.mcap'))
    if not files:
        raise BagReadError(f'{path}: no .mcap file')
    return files


def read_metadata_file(metadata_path):
    """Return the ``rosbag2_bagfile_information`` mapping of a metadata.yaml, or BagReadError."""
    metadata_path = pathlib.Path(metadata_path)
    hint = ' (scripts/bag_repair rebuilds metadata.yaml from the files)'
    try:
        text = metadata_path.read_bytes().decode('utf-8')
    except UnicodeDecodeError:
        raise BagReadError(f'{metadata_path}: not UTF-8 text{hint}') from None
    except OSError as err:
        raise BagReadError(f'{metadata_path}: {err.strerror or err}') from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        where = getattr(err, 'problem_mark', None)
        line = f' at line {where.line + 1}' if where is not None else ''
        raise BagReadError(f'{metadata_path}: not valid YAML{line}{hint}') from None
    except (ValueError, RecursionError):
        raise BagReadError(f'{metadata_path}: a value cannot be read{hint}') from None
    info = data.get('rosbag2_bagfile_information') if isinstance(data, dict) else None
    if data is None:
        return {}
    if not isinstance(info, dict):
        raise BagReadError(f'{metadata_path}: not a rosbag2 metadata file (expected a '
                           f'mapping with rosbag2_bagfile_information){hint}')
    return info


#: The MCAP records the bag tools read, by the name they go by.
_RECORD_KINDS = ((Schema, 'schema'), (Channel, 'channel'), (Message, 'message'),
                 (Metadata, 'metadata'))


def record_kind(record) -> str | None:
    """Return the kind of an MCAP record: 'schema', 'channel', 'message', 'metadata' or None."""
    for cls, kind in _RECORD_KINDS:
        if isinstance(record, cls):
            return kind
    return None


class _Decoders:
    """Each channel's decoder: mcap_ros2's, behind the checked fast path of :mod:`.cdr_fast`."""

    def __init__(self, path) -> None:
        self.path = path
        self.factory = DecoderFactory()
        self.by_channel: dict = {}

    def decode(self, channel, schema, message):
        decoder = self.by_channel.get(channel.id)
        if decoder is None:
            slow = self.factory.decoder_for(channel.message_encoding, schema)
            if slow is None:
                raise BagReadError(
                    f'{self.path}: cannot decode topic {channel.topic} (encoding '
                    f'{channel.message_encoding!r}, schema '
                    f'{schema.encoding if schema else None!r})')
            layout = None
            if schema is not None and schema.encoding == 'ros2msg' and \
                    channel.message_encoding == 'cdr':
                layout = layout_of(schema.name, schema.data.decode('utf-8', 'replace'))
            decoder = self.by_channel[channel.id] = CheckedDecoder(layout, slow)
        return decoder(message.data)


def _read_file(path, topics, file_scan):
    decoders = _Decoders(path)
    if file_scan.seekable and file_scan.loose:
        # Messages outside chunks: mcap's reader, which reads such a file linearly.
        messages = _mcap_ordered(path, topics)
    elif file_scan.seekable:
        messages = _log_time_ordered(path, file_scan, topics)
    else:   # damaged (partial read asked for) or without summary: the intact chunks
        messages = _intact_messages(path, file_scan, topics)
    for channel, schema, message in messages:
        yield BagMessage(channel.topic, schema.name if schema else '', message.log_time,
                         decoders.decode(channel, schema, message))


def _mcap_ordered(path, topics):
    with open(path, 'rb') as stream:
        reader = SeekingReader(stream, validate_crcs=True)
        for schema, channel, message in reader.iter_messages(topics=topics,
                                                             log_time_order=True):
            yield channel, schema, message


def _log_time_ordered(path, file_scan, topics=None):
    """(channel, schema, message) of a file's chunks in mcap's log-time order.

    The order of mcap's ``SeekingReader.iter_messages(log_time_order=True)``: by log
    time, then chunk offset, then place in the chunk; chunks opened by (start time,
    offset), so that only the messages of the chunks that may hold the next one are held.
    Tuples in a heap, where mcap compares Python objects (a fifth of a bag's read).
    """
    channels, schemas = file_scan.channels, file_scan.schemas
    order = sorted(file_scan.chunks, key=lambda c: (c.start_ns, c.offset))
    pending: list = []
    for good, records in iter_chunk_records(path, file_scan, order):
        opened = (good.start_ns, good.offset, -1)
        while pending and pending[0][:3] < opened:
            yield heapq.heappop(pending)[3]
        for index, record in enumerate(records):
            if record_kind(record) != 'message':
                continue
            channel = channels.get(record.channel_id)
            if channel is None or (topics is not None and channel.topic not in topics):
                continue
            heapq.heappush(pending, (record.log_time, good.offset, index,
                                     (channel, schemas.get(channel.schema_id), record)))
    while pending:
        yield heapq.heappop(pending)[3]


def _intact_messages(path, file_scan, topics=None, start_ns=None, end_ns=None):
    """(channel, schema, message) of the intact chunks of a file, by log time per chunk."""
    channels, schemas = dict(file_scan.channels), dict(file_scan.schemas)
    for good, records in iter_chunk_records(path, file_scan):
        if start_ns is not None and good.end_ns < start_ns:
            continue
        if end_ns is not None and good.start_ns > end_ns:
            continue
        batch = []
        for record in records:
            kind = record_kind(record)
            if kind == 'schema':
                schemas.setdefault(record.id, record)
            elif kind == 'channel':
                channels.setdefault(record.id, record)
            elif kind == 'message':
                channel = channels.get(record.channel_id)
                if channel is None or (topics is not None and channel.topic not in topics):
                    continue
                if start_ns is not None and record.log_time < start_ns:
                    continue
                if end_ns is not None and record.log_time > end_ns:
                    continue
                batch.append((channel, schemas.get(channel.schema_id), record))
        batch.sort(key=lambda item: item[2].log_time)  # stable: equal times keep order
        yield from batch


def read_bag(path, topics=None, allow_partial=False):
    """Iterate over the decoded messages of a bag, in receive-time order per file.

    Parameters
    ----------
    path : str or pathlib.Path
        A bag directory or a single ``.mcap`` file.
    topics : iterable of str, optional
        Only these topics (default: all).
    allow_partial : bool
        Read the intact chunks of a damaged or unfinished bag instead of raising.

    Yields
    ------
    BagMessage
        ``(topic, type_name, log_time_ns, message)``; unpacks as a 4-tuple.

    Raises
    ------
    BagReadError
        If the bag is missing or a topic's schema cannot be decoded (e.g. 'ros2idl').
    BagIntegrityError
        If a file is damaged or unfinished (before anything is yielded), unless
        ``allow_partial``.
    """
    if isinstance(topics, str):
        topics = [topics]
    topics = None if topics is None else set(topics)
    scans = check_bag(path, allow_partial)
    for file_scan in scans:
        yield from _read_file(file_scan.path, topics, file_scan)


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
        ``finished`` (every file has its summary section, i.e. was closed properly),
        ``problems`` (damaged parts, see :func:`check_bag`; their messages are not counted)
        and ``topics``: topic -> dict(``type``, ``message_count``, ``start_ns``, ``end_ns``).
    """
    scans = check_bag(path, allow_partial=True)
    topics = {}
    finished = all(not s.unfinished for s in scans)
    for file_scan in scans:
        for channel in file_scan.channels.values():
            schema = file_scan.schemas.get(channel.schema_id)
            topics.setdefault(channel.topic, {
                'type': schema.name if schema else '', 'message_count': 0,
                'start_ns': None, 'end_ns': None})
        for channel_id, (count, first, last) in file_scan.message_stats.items():
            channel = file_scan.channels.get(channel_id)
            if channel is None:
                continue
            entry = topics[channel.topic]
            entry['message_count'] += count
            if entry['start_ns'] is None or first < entry['start_ns']:
                entry['start_ns'] = first
            if entry['end_ns'] is None or last > entry['end_ns']:
                entry['end_ns'] = last
    starts = [t['start_ns'] for t in topics.values() if t['start_ns'] is not None]
    ends = [t['end_ns'] for t in topics.values() if t['end_ns'] is not None]
    start_ns = min(starts) if starts else None
    end_ns = max(ends) if ends else None
    return {
        'path': str(path),
        'files': [str(s.path) for s in scans],
        'message_count': sum(t['message_count'] for t in topics.values()),
        'start_ns': start_ns,
        'end_ns': end_ns,
        'duration_ns': 0 if start_ns is None else end_ns - start_ns,
        'finished': finished,
        'problems': integrity_problems(scans),
        'topics': topics,
    }


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


def _channels_and_counts(file_scan):
    """(schemas, channels, counts per channel id) of one scanned MCAP file."""
    counts = {cid: file_scan.message_stats.get(cid, (0,))[0] for cid in file_scan.channels}
    return dict(file_scan.schemas), dict(file_scan.channels), counts


def read_topics(path, allow_partial=False):
    """Return the topics of a bag (directory or single file) from its MCAP content.

    Raises :class:`BagIntegrityError` for a damaged bag unless ``allow_partial``.

    Returns
    -------
    dict
        topic -> :class:`TopicMetadata`, in the order the topics first appear; message
        counts are summed over the files.
    """
    topics = {}
    for file_scan in check_bag(path, allow_partial):
        schemas, channels, counts = _channels_and_counts(file_scan)
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


def _iter_raw_file(file_scan, topics, start_ns, end_ns):
    if file_scan.seekable:
        with open(file_scan.path, 'rb') as stream:
            reader = SeekingReader(stream, validate_crcs=True)
            for _, channel, message in reader.iter_messages(
                    topics=topics, starting_at=start_ns, ending_at=end_ns,
                    log_time_order=True):
                yield RawMessage(channel.topic, message.log_time, message.publish_time,
                                 message.data)
        return
    wanted = None if topics is None else set(topics)
    for channel, _, record in _intact_messages(file_scan.path, file_scan, wanted, start_ns,
                                               end_ns):
        yield RawMessage(channel.topic, record.log_time, record.publish_time, record.data)


def iter_raw_messages(path, topics=None, start_ns=None, end_ns=None, allow_partial=False):
    """Iterate over the serialized messages of a bag in receive-time order.

    Parameters
    ----------
    path : str or pathlib.Path
        A bag directory or a single ``.mcap`` file.
    topics : iterable of str, optional
        Only these topics (default: all).
    start_ns, end_ns : int, optional
        Only messages with ``start_ns <= log time <= end_ns`` [ns].
    allow_partial : bool
        Read the intact chunks of a damaged or unfinished bag instead of raising
        :class:`BagIntegrityError`.

    Yields
    ------
    RawMessage
        ``(topic, log_time_ns, publish_time_ns, data)``. The files of a split bag are
        merged by log time (stable: equal times keep the file order).
    """
    if isinstance(topics, str):
        topics = [topics]
    topics = None if topics is None else sorted(set(topics))
    iterators = [_iter_raw_file(s, topics, start_ns, end_ns)
                 for s in check_bag(path, allow_partial)]
    if len(iterators) == 1:
        yield from iterators[0]
    else:
        yield from heapq.merge(*iterators, key=lambda m: m.log_time_ns)
