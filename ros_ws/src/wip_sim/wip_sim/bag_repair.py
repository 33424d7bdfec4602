"""Repair a rosbag2 MCAP bag whose recorder died: ``scripts/bag_repair BAG``.

What a killed recorder (SIGKILL, power loss, full disk) leaves behind: the last MCAP file
without its summary and footer (plain readers fail with "File end magic is invalid"), maybe
a partial chunk at its end, and no ``metadata.yaml`` or one that lists only the files closed
before the crash. MCAP chunks are self-contained (compressed, with a CRC of their content),
so every chunk written completely before the crash can be recovered. This tool:

1. reads every ``*.mcap`` file of the bag directory, in the order of their index
   (``<name>_0.mcap``, ``<name>_1.mcap`` ...);
2. rewrites each unfinished file from its complete chunks (CRC-checked) into a finished
   MCAP file of the same name (summary, indexes, same chunk compression), keeping the
   original as ``<file>.unfinished``; a file without any complete chunk is set aside the
   same way and left out of the bag;
3. rebuilds ``metadata.yaml`` from the files' contents (topics, types, QoS, type hashes,
   message counts, times, per-file entries), keeping ``custom_data`` and ``ros_distro``
   from the old ``metadata.yaml`` or from the ``rosbag2`` metadata record of a file.

Finished files are not touched. Running the tool on a healthy bag only rewrites
``metadata.yaml`` (with the same content). This is ``ros2 bag reindex`` plus the recovery of
unfinished files, which rosbag2 leaves to the MCAP CLI (``mcap recover``).

Usage::

    scripts/bag_repair BAG [--compression zstd|lz4|none] [--dry-run]
"""

import argparse
import os
import pathlib
import re
import struct
import sys
from typing import NamedTuple

from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk, StreamReader
from mcap.writer import Writer
import yaml

from .bag_writer import (_bag_metadata, _COMPRESSION, _library_identifier,
                         BagWriterError, FileStatistics, MCAP_PROFILE, METADATA_FILE_NAME,
                         write_metadata_file)
from .qos_yaml import normalize_offered_qos

UNFINISHED_SUFFIX = '.unfinished'
# What reading a truncated or corrupt tail raises (CRC errors are ValueErrors).
_READ_ERRORS = (McapError, EOFError, ValueError, IndexError, OSError, MemoryError,
                struct.error)
_INDEX_RE = re.compile(r'_(\d+)\.mcap$')


class TopicInfo(NamedTuple):
    """What a bag records of a topic (from an MCAP channel and its schema)."""

    type_name: str
    qos: list
    type_hash: str


class FileReport(NamedTuple):
    """Outcome of the repair of one MCAP file."""

    name: str
    finished: bool  # had its summary (untouched)
    messages: int  # messages in the repaired file
    chunks: int  # complete chunks read (unfinished files) or in the summary
    action: str  # 'kept', 'rewritten' or 'dropped (no complete chunk)'


class RepairResult(NamedTuple):
    """Outcome of :func:`repair_bag`."""

    metadata: dict  # the metadata written (rosbag2_bagfile_information)
    files: list  # FileReport per file, in order


def mcap_files_by_index(directory):
    """The ``*.mcap`` files of a bag directory ordered by their ``_<index>`` suffix."""
    def key(path):
        match = _INDEX_RE.search(path.name)
        return (0, int(match.group(1)), path.name) if match else (1, 0, path.name)
    return sorted(pathlib.Path(directory).glob('*.mcap'), key=key)


def is_finished(path):
    """True if an MCAP file has its summary section (was closed properly)."""
    try:
        with open(path, 'rb') as stream:
            return SeekingReader(stream).get_summary() is not None
    except _READ_ERRORS:
        return False


def _topic_info(channel, schema):
    metadata = channel.metadata or {}
    try:
        qos = normalize_offered_qos(metadata.get('offered_qos_profiles', ''))
    except ValueError:
        qos = []
    return TopicInfo(schema.name if schema is not None else '', qos,
                     str(metadata.get('topic_type_hash', '')))


class FileContents:
    """Topics, counts, times and chunk compression of one MCAP file."""

    def __init__(self, name, finished):
        self.finished = finished
        self.stats = FileStatistics(name)
        self.topics = {}  # topic -> TopicInfo (first channel seen)
        self.counts = {}  # topic -> messages
        self.chunks = 0
        self.compression = None
        self.rosbag2_metadata = None  # parsed 'serialized_metadata' of a rosbag2 record


def _read_finished(path):
    contents = FileContents(path.name, True)
    with open(path, 'rb') as stream:
        reader = SeekingReader(stream)
        summary = reader.get_summary()
        for channel in summary.channels.values():
            contents.topics.setdefault(
                channel.topic, _topic_info(channel, summary.schemas.get(channel.schema_id)))
            contents.counts.setdefault(channel.topic, 0)
        contents.chunks = len(summary.chunk_indexes)
        if summary.chunk_indexes:
            contents.compression = summary.chunk_indexes[0].compression
        statistics = summary.statistics
        if statistics is not None and statistics.message_count > 0:
            for channel_id, count in statistics.channel_message_counts.items():
                contents.counts[summary.channels[channel_id].topic] += count
            contents.stats.count = statistics.message_count
            contents.stats.start_ns = statistics.message_start_time
            contents.stats.end_ns = statistics.message_end_time
        elif statistics is None:  # No statistics record: count the messages.
            stream.seek(0)
            for _, channel, message in SeekingReader(stream).iter_messages(
                    log_time_order=False):
                contents.counts[channel.topic] += 1
                contents.stats.add(message.log_time)
        stream.seek(0)
        for record in SeekingReader(stream).iter_metadata():
            if record.name == 'rosbag2':
                contents.rosbag2_metadata = _parse_serialized(record.metadata)
    return contents


def _parse_serialized(metadata):
    try:
        data = yaml.safe_load(metadata.get('serialized_metadata', ''))
    except yaml.YAMLError:
        return None
    return data if isinstance(data, dict) else None


def _scan_complete_chunks(path):
    """Yield the records of the complete, CRC-valid chunks of a file, in file order.

    Yields ('chunk', compression) before the records of each chunk, then ('schema', r),
    ('channel', r), ('message', r) and ('metadata', r). Stops quietly at the first
    truncated or corrupt record.
    """
    with open(path, 'rb') as stream:
        records = StreamReader(stream, emit_chunks=True, validate_crcs=False).records
        while True:
            try:
                record = next(records)
                if isinstance(record, Chunk):
                    inner = breakup_chunk(record, validate_crc=True)
                else:
                    inner = None
            except StopIteration:
                return
            except _READ_ERRORS:
                return
            if inner is not None:
                yield 'chunk', record.compression
                for item in inner:
                    yield from _classify(item)
            else:
                yield from _classify(record)


def _classify(record):
    if isinstance(record, Schema):
        yield 'schema', record
    elif isinstance(record, Channel):
        yield 'channel', record
    elif isinstance(record, Message):
        yield 'message', record
    elif isinstance(record, Metadata):
        yield 'metadata', record


def _rewrite_unfinished(path, compression, dry_run):
    """Rewrite an unfinished file from its complete chunks; returns its FileContents."""
    contents = FileContents(path.name, False)
    unfinished = path.with_name(path.name + UNFINISHED_SUFFIX)
    if dry_run:
        source, stream, writer = path, None, None
    else:
        if unfinished.exists():
            raise BagWriterError(f'{unfinished} exists: a previous repair was interrupted; '
                                 'move it away first')
        os.replace(path, unfinished)
        source = unfinished
        stream = open(path, 'xb')
        writer = None
    schemas, schema_ids, channel_ids, channel_topics = {}, {}, {}, {}
    try:
        for kind, record in _scan_complete_chunks(source):
            if kind == 'chunk':
                contents.chunks += 1
                if contents.compression is None:
                    contents.compression = record
                continue
            if writer is None and stream is not None:
                chosen = compression or _compression_name(contents.compression)
                writer = Writer(stream, compression=_COMPRESSION[chosen])
                writer.start(profile=MCAP_PROFILE, library=_library_identifier())
            if kind == 'schema' and record.id not in schemas:
                schemas[record.id] = record
                if writer is not None:
                    schema_ids[record.id] = writer.register_schema(
                        record.name, record.encoding, record.data)
            elif kind == 'channel' and record.id not in channel_topics:
                channel_topics[record.id] = record.topic
                contents.topics.setdefault(
                    record.topic, _topic_info(record, schemas.get(record.schema_id)))
                contents.counts.setdefault(record.topic, 0)
                if writer is not None:
                    channel_ids[record.id] = writer.register_channel(
                        record.topic, record.message_encoding,
                        schema_ids.get(record.schema_id, 0), dict(record.metadata))
            elif kind == 'message' and record.channel_id in channel_topics:
                if writer is not None:
                    writer.add_message(channel_ids[record.channel_id], record.log_time,
                                       record.data, record.publish_time, record.sequence)
                contents.counts[channel_topics[record.channel_id]] += 1
                contents.stats.add(record.log_time)
            elif kind == 'metadata' and record.name == 'rosbag2':
                contents.rosbag2_metadata = _parse_serialized(record.metadata)
        if writer is not None and contents.stats.count > 0:
            writer.finish()
    finally:
        if stream is not None:
            stream.close()
    if stream is not None and contents.stats.count == 0:
        path.unlink()  # Nothing recoverable: leave only the .unfinished original.
    return contents


def read_file_contents(path):
    """Topics, message counts, times and chunk compression of one MCAP file.

    From the summary of a finished file; from a scan of the complete chunks of an unfinished
    one (``FileContents.finished`` tells which).
    """
    path = pathlib.Path(path)
    if is_finished(path):
        return _read_finished(path)
    return _rewrite_unfinished(path, None, dry_run=True)


def _compression_name(chunk_compression):
    return {'zstd': 'zstd', 'lz4': 'lz4', '': 'none'}.get(chunk_compression, 'zstd')


def _old_metadata(directory):
    path = pathlib.Path(directory) / METADATA_FILE_NAME
    try:
        data = yaml.safe_load(path.read_text(encoding='utf-8'))
    except (OSError, yaml.YAMLError):
        return None
    info = (data or {}).get('rosbag2_bagfile_information') if isinstance(data, dict) else None
    return info if isinstance(info, dict) else None


def repair_bag(directory, compression=None, dry_run=False):
    """Make a bag whole again after its recorder died; see the module docstring.

    Parameters
    ----------
    directory : str or pathlib.Path
        The bag directory.
    compression : str, optional
        Chunk compression of rewritten files ('zstd', 'lz4', 'none'); default: that of the
        file's first chunk.
    dry_run : bool
        Only report what would be done; write nothing.

    Returns
    -------
    RepairResult
        The metadata (written unless ``dry_run``) and a report per file.

    Raises
    ------
    BagWriterError
        If the directory holds no ``.mcap`` file.
    """
    directory = pathlib.Path(directory)
    if compression is not None and compression not in _COMPRESSION:
        raise ValueError(f'compression {compression!r} not supported; expected one of '
                         f'{sorted(_COMPRESSION)}')
    if not directory.is_dir():
        raise BagWriterError(f'{directory} is not a bag directory')
    paths = mcap_files_by_index(directory)
    if not paths:
        raise BagWriterError(f'{directory}: no .mcap file to repair')
    reports, kept = [], []
    for path in paths:
        if is_finished(path):
            contents = _read_finished(path)
            reports.append(FileReport(path.name, True, contents.stats.count, contents.chunks,
                                      'kept'))
        else:
            contents = _rewrite_unfinished(path, compression, dry_run)
            action = ('rewritten' if contents.stats.count > 0
                      else 'dropped (no complete chunk)')
            reports.append(FileReport(path.name, False, contents.stats.count,
                                      contents.chunks, action))
            if contents.stats.count == 0:
                continue
        kept.append(contents)

    topics, counts = {}, {}
    for contents in kept:
        for topic, info in contents.topics.items():
            topics.setdefault(topic, info)
            counts[topic] = counts.get(topic, 0) + contents.counts.get(topic, 0)
    old = _old_metadata(directory)
    if old is None:
        old = next((c.rosbag2_metadata for c in kept if c.rosbag2_metadata), None) or {}
    information = _bag_metadata(
        files=[c.stats for c in kept],
        topics=[(topic, info.type_name, info.qos, info.type_hash, counts[topic])
                for topic, info in topics.items()],
        custom_data=old.get('custom_data') or {},
        ros_distro=old.get('ros_distro') or os.environ.get('ROS_DISTRO') or 'jazzy')
    if not dry_run:
        write_metadata_file(directory / METADATA_FILE_NAME, information)
    return RepairResult(information, reports)


def main(argv=None):
    """``scripts/bag_repair BAG``: see the module docstring."""
    parser = argparse.ArgumentParser(
        prog='bag_repair', description='Recover the complete chunks of unfinished MCAP '
        'files of a rosbag2 bag and rebuild its metadata.yaml from the files\' contents.')
    parser.add_argument('bag', help='bag directory')
    parser.add_argument('--compression', choices=sorted(_COMPRESSION),
                        help='chunk compression of rewritten files (default: as found)')
    parser.add_argument('--dry-run', action='store_true',
                        help='report what would be done, write nothing')
    args = parser.parse_args(argv)
    try:
        result = repair_bag(args.bag, compression=args.compression, dry_run=args.dry_run)
    except (BagWriterError, ValueError, OSError) as err:
        print(f'bag_repair: error: {err}', file=sys.stderr)
        return 1
    for report in result.files:
        note = ''
        if not report.finished and not args.dry_run:
            note = f' (original kept as {report.name}{UNFINISHED_SUFFIX})'
        print(f'{report.name}: {report.action}, {report.messages} messages in '
              f'{report.chunks} chunk(s){note}')
    info = result.metadata
    print(f'{"would write" if args.dry_run else "wrote"} {METADATA_FILE_NAME}: '
          f'{info["message_count"]} messages on {len(info["topics_with_message_count"])} '
          f'topic(s) in {len(info["relative_file_paths"])} file(s)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
