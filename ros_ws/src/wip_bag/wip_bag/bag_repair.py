"""Repair a damaged rosbag2 MCAP bag into a new bag: ``scripts/bag_repair BAG [--out NEW]``.

What a killed recorder (SIGKILL, power loss, full disk) leaves behind: the last MCAP file
without its summary and footer (plain readers fail with "File end magic is invalid"), maybe
a partial chunk at its end, and no ``metadata.yaml`` or one that lists only the files closed
before the crash. A disk or a copy can also flip bits anywhere. MCAP chunks are
self-contained (compressed, with a CRC of their content), so every intact chunk can be
recovered, before and after a damaged one. This tool:

1. scans every ``*.mcap`` file of the bag directory, in the order of their index
   (``<name>_0.mcap``, ``<name>_1.mcap`` ...), checking every chunk's CRC
   (:mod:`wip_bag.bag_integrity`);
2. copies each intact, finished file as it is into the new bag, and rewrites each other
   one from its intact chunks (skipping the damaged ones) into a finished MCAP file of the
   same name (summary, indexes, same chunk compression); a file without any intact chunk
   is left out;
3. rebuilds ``metadata.yaml`` from the files' contents (topics, types, QoS, type hashes,
   message counts, times, per-file entries), keeping ``custom_data`` and ``ros_distro``
   from the old ``metadata.yaml`` when they can be read (whatever its encoding) or from
   the ``rosbag2`` metadata record of a file.

The original bag is never touched: the new bag goes to ``--out`` (default
``<BAG>_repaired``), which must not exist; it is built in a temporary directory beside it
and renamed into place when complete. This is ``ros2 bag reindex`` plus the recovery of
damaged files, which rosbag2 leaves to the MCAP CLI (``mcap recover``).

Usage::

    scripts/bag_repair BAG [--out NEW] [--compression zstd|lz4|none] [--dry-run]

Exit codes: 0 the new bag holds every message of the original (nothing was damaged, only
the metadata or the summaries were rebuilt); 1 it was written but messages were lost (the
damaged parts are listed); 2 a usage or input error (nothing written).
"""

import argparse
import errno
import os
import pathlib
import re
import shutil
import sys
import tempfile
from typing import NamedTuple

from mcap.reader import SeekingReader
from mcap.writer import Writer
import yaml

from wip_runtime.cli import (add_exit_codes, check_output_directory, EXIT_DISK_FULL, EXIT_FAILED,
                             EXIT_OK, EXIT_USAGE, exit_with)

from .bag_integrity import iter_chunk_records
from .bag_reader import BagReadError, record_kind, scan
from .bag_writer import (bag_metadata, BagWriterError, COMPRESSION, FileStatistics,
                         library_identifier, MCAP_PROFILE, METADATA_FILE_NAME,
                         write_metadata_file)
from .qos_yaml import normalize_offered_qos

UNFINISHED_SUFFIX = '.unfinished'
_INDEX_RE = re.compile(r'_(\d+)\.mcap$')


class NothingRecoverable(BagWriterError):
    """No file of the bag has an intact chunk: no new bag is written."""


class TopicInfo(NamedTuple):
    """What a bag records of a topic (from an MCAP channel and its schema)."""

    type_name: str
    qos: list
    type_hash: str


class FileReport(NamedTuple):
    """Outcome of the repair of one MCAP file."""

    name: str
    finished: bool  # intact and finished: copied as it is
    messages: int  # messages in the repaired file
    chunks: int  # intact chunks
    action: str  # 'copied', 'rewritten' or 'dropped (no intact chunk)' ('would ...')
    problems: list  # the damaged parts skipped (one line each)


class RepairResult(NamedTuple):
    """Outcome of :func:`repair_bag`."""

    metadata: dict  # the metadata written (rosbag2_bagfile_information)
    files: list  # FileReport per file, in order
    out: pathlib.Path  # the new bag (not written with dry_run)

    @property
    def lost(self) -> bool:
        """True if a damaged part of the original was skipped."""
        return any(f.problems for f in self.files)


def mcap_files_by_index(directory):
    """Return the ``*.mcap`` files of a bag directory ordered by their ``_<index>`` suffix."""
    def key(path):
        match = _INDEX_RE.search(path.name)
        return (0, int(match.group(1)), path.name) if match else (1, 0, path.name)
    return sorted(pathlib.Path(directory).glob('*.mcap'), key=key)


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


def _rewrite(path, target, compression):
    """Write the intact chunks of ``path`` into a finished MCAP file ``target``.

    ``target`` None: only count. Returns the file's FileContents.
    """
    file_scan = scan(path)
    contents = FileContents(path.name, False)
    contents.compression = file_scan.chunks[0].compression if file_scan.chunks else None
    stream = writer = None
    schema_ids, channel_ids, channel_topics = {}, {}, {}
    schemas = dict(file_scan.schemas)
    for record in file_scan.metadata:
        if record.name == 'rosbag2':
            contents.rosbag2_metadata = _parse_serialized(record.metadata)
    try:
        for _, records in iter_chunk_records(path, file_scan):
            contents.chunks += 1
            for item in records:
                kind = record_kind(item)
                if kind is not None:
                    if target is not None and writer is None:
                        stream = open(target, 'xb')  # noqa: SIM115 - closed in the finally
                        chosen = compression or _compression_name(contents.compression)
                        writer = Writer(stream, compression=COMPRESSION[chosen])
                        writer.start(profile=MCAP_PROFILE, library=library_identifier())
                    if kind == 'schema':
                        schemas.setdefault(item.id, item)
                    elif kind == 'channel' and item.id not in channel_topics:
                        channel_topics[item.id] = item.topic
                    elif kind == 'message':
                        _add_message(item, file_scan, schemas, writer, schema_ids,
                                     channel_ids, channel_topics, contents)
                    elif kind == 'metadata' and item.name == 'rosbag2' and \
                            contents.rosbag2_metadata is None:
                        contents.rosbag2_metadata = _parse_serialized(item.metadata)
        if writer is not None and contents.stats.count > 0:
            writer.finish()
    finally:
        if stream is not None:
            stream.close()
    if target is not None and contents.stats.count == 0:
        pathlib.Path(target).unlink(missing_ok=True)
    return contents


def _add_message(message, file_scan, schemas, writer, schema_ids, channel_ids,
                 channel_topics, contents):
    channel = file_scan.channels.get(message.channel_id)
    if channel is None:
        return  # Its channel was only in a damaged chunk: its topic is unknown.
    if channel.id not in channel_ids:
        schema = schemas.get(channel.schema_id)
        contents.topics.setdefault(channel.topic, _topic_info(channel, schema))
        contents.counts.setdefault(channel.topic, 0)
        if writer is not None:
            if schema is not None and schema.id not in schema_ids:
                schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding,
                                                               schema.data)
            channel_ids[channel.id] = writer.register_channel(
                channel.topic, channel.message_encoding,
                schema_ids.get(channel.schema_id, 0), dict(channel.metadata))
        else:
            channel_ids[channel.id] = channel.id
    if writer is not None:
        writer.add_message(channel_ids[channel.id], message.log_time, message.data,
                           message.publish_time, message.sequence)
    contents.counts[channel.topic] += 1
    contents.stats.add(message.log_time)


def read_file_contents(path):
    """Topics, message counts, times and chunk compression of one MCAP file.

    From the summary of an intact, finished file; from its intact chunks otherwise
    (``FileContents.finished`` tells which).
    """
    path = pathlib.Path(path)
    if scan(path).seekable:
        return _read_finished(path)
    return _rewrite(path, None, None)


def _compression_name(chunk_compression):
    return {'zstd': 'zstd', 'lz4': 'lz4', '': 'none'}.get(chunk_compression, 'zstd')


def _old_metadata(directory):
    """``custom_data`` and ``ros_distro`` of an old metadata.yaml, whatever state it is in.

    Undecodable bytes become U+FFFD (a damaged metadata.yaml is what this tool rebuilds),
    and only values of the right type are kept.
    """
    path = pathlib.Path(directory) / METADATA_FILE_NAME
    try:
        text = path.read_bytes().decode('utf-8', errors='replace')
        data = yaml.safe_load(text)
    except (OSError, yaml.YAMLError, ValueError, RecursionError):
        return None
    info = data.get('rosbag2_bagfile_information') if isinstance(data, dict) else None
    return _usable_metadata(info)


def _usable_metadata(info):
    if not isinstance(info, dict):
        return None
    out = {}
    custom = info.get('custom_data')
    if isinstance(custom, dict) and all(isinstance(k, str) and isinstance(v, str)
                                        for k, v in custom.items()):
        out['custom_data'] = custom
    if isinstance(info.get('ros_distro'), str):
        out['ros_distro'] = info['ros_distro']
    return out or None


def default_output(directory):
    """Where the repaired copy of ``directory`` goes by default: ``<BAG>_repaired``."""
    directory = pathlib.Path(directory)
    return directory.with_name(directory.name + '_repaired')


def repair_bag(directory, out=None, compression=None, dry_run=False):
    """Copy a damaged bag's intact content into a new, whole bag; see the module docstring.

    Parameters
    ----------
    directory : str or pathlib.Path
        The bag directory (never modified).
    out : str or pathlib.Path, optional
        The new bag directory; must not exist. Default ``<directory>_repaired``.
    compression : str, optional
        Chunk compression of rewritten files ('zstd', 'lz4', 'none'); default: that of the
        file's first chunk.
    dry_run : bool
        Only report what would be done; write nothing.

    Returns
    -------
    RepairResult
        The metadata (written unless ``dry_run``), a report per file, the new bag's path.

    Raises
    ------
    BagWriterError
        If the directory holds no ``.mcap`` file, or ``out`` exists or cannot be written.
    """
    directory = pathlib.Path(directory)
    paths, out = _check_repair_arguments(directory, out, compression)
    work = None
    if not dry_run:
        out.parent.mkdir(parents=True, exist_ok=True)
        work = pathlib.Path(tempfile.mkdtemp(prefix=f'.{out.name}.partial-', dir=out.parent))
        # mkdtemp makes it 0700: the bag gets the mode a mkdir would give it (as rosbag2's).
        os.chmod(work, 0o777 & ~current_umask())
    try:
        reports, kept = _repair_files(paths, work, compression, dry_run)
        if not kept:
            raise NothingRecoverable(
                f'{directory}: no intact chunk in any file, nothing to recover ('
                + '; '.join(line for r in reports for line in r.problems) + ')')
        information = _metadata_of(directory, kept)
        if work is not None:
            write_metadata_file(work / METADATA_FILE_NAME, information)
            os.rename(work, out)  # The new bag appears whole, or not at all.
            work = None
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)  # Ours: created above.
    return RepairResult(information, reports, out)


def _check_repair_arguments(directory, out, compression):
    """Return the bag's MCAP files and the new bag's path; ValueError, BagWriterError."""
    if compression is not None and compression not in COMPRESSION:
        raise ValueError(f'compression {compression!r} not supported; expected one of '
                         f'{sorted(COMPRESSION)}')
    if not directory.is_dir():
        raise BagWriterError(f'{directory} is not a bag directory')
    paths = mcap_files_by_index(directory)
    if not paths:
        raise BagWriterError(f'{directory}: no .mcap file to repair')
    out = pathlib.Path(out) if out is not None else default_output(directory)
    if out.exists() or out.is_symlink():
        raise BagWriterError(f'--out {out} exists: the repaired bag goes to a new directory '
                             '(give another --out)')
    resolved = out.resolve()
    if resolved == directory.resolve() or directory.resolve() in resolved.parents:
        raise BagWriterError(f'--out {out}: inside the original bag, which is never touched')
    try:
        check_output_directory(out, '--out')
    except ValueError as err:
        raise BagWriterError(str(err)) from err
    return paths, out


def current_umask() -> int:
    """Return this process's umask (read by setting it and setting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _repair_files(paths, work, compression, dry_run):
    reports, kept = [], []
    scans = [scan(p) for p in paths]
    starts = [c.start_ns for s in scans for c in s.chunks]
    origin = min(starts) if starts else None
    for path, file_scan in zip(paths, scans):
        lost = file_scan.problems(origin)
        if file_scan.seekable:
            contents = _read_finished(path)
            if work is not None:
                shutil.copy2(path, work / path.name)
            action = 'would copy' if dry_run else 'copied'
            reports.append(FileReport(path.name, True, contents.stats.count,
                                      contents.chunks, action, []))
        else:
            target = None if work is None else work / path.name
            contents = _rewrite(path, target, compression)
            if contents.stats.count > 0:
                action = 'would rewrite' if dry_run else 'rewritten'
            else:
                action = ('would drop' if dry_run else 'dropped') + ' (no intact chunk)'
            reports.append(FileReport(path.name, False, contents.stats.count,
                                      contents.chunks, action, lost))
            if contents.stats.count == 0:
                continue
        kept.append(contents)
    return reports, kept


def _metadata_of(directory, kept):
    topics, counts = {}, {}
    for contents in kept:
        for topic, info in contents.topics.items():
            topics.setdefault(topic, info)
            counts[topic] = counts.get(topic, 0) + contents.counts.get(topic, 0)
    old = _old_metadata(directory)
    if old is None:
        old = next((_usable_metadata(c.rosbag2_metadata) for c in kept
                    if _usable_metadata(c.rosbag2_metadata)), None) or {}
    return bag_metadata(
        files=[c.stats for c in kept],
        topics=[(topic, info.type_name, info.qos, info.type_hash, counts[topic])
                for topic, info in topics.items()],
        custom_data=old.get('custom_data') or {},
        ros_distro=old.get('ros_distro') or os.environ.get('ROS_DISTRO') or 'jazzy')


def main(argv=None):
    """``scripts/bag_repair BAG``: see the module docstring."""
    parser = argparse.ArgumentParser(
        prog='scripts/bag_repair', formatter_class=argparse.RawDescriptionHelpFormatter,
        description="""\
Copy the intact chunks of a damaged or unfinished rosbag2 MCAP bag into a new bag with a
rebuilt metadata.yaml; the original is never touched.

Examples
--------
    scripts/bag_repair --dry-run out/run/bag         # what would be kept and lost
    scripts/bag_repair out/run/bag                   # writes out/run/bag_repaired
    scripts/bag_repair out/run/bag --out fixed_bag --compression zstd""")
    parser.add_argument('bag', help='bag directory')
    parser.add_argument('--out', help='the new bag directory (must not exist; default '
                        '<BAG>_repaired)')
    parser.add_argument('--compression', choices=sorted(COMPRESSION),
                        help='chunk compression of rewritten files (default: as found)')
    parser.add_argument('--dry-run', action='store_true',
                        help='report what would be done, write nothing')
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    try:
        result = repair_bag(args.bag, out=args.out, compression=args.compression,
                            dry_run=args.dry_run)
    except NothingRecoverable as err:
        print(f'bag_repair: {err}; nothing written', file=sys.stderr)
        return EXIT_FAILED
    except OSError as err:
        if err.errno not in (errno.ENOSPC, errno.EDQUOT):
            print(f'bag_repair: error: {err}', file=sys.stderr)
            return EXIT_USAGE
        target = args.out or f'{str(args.bag).rstrip("/")}_repaired'
        print(f'bag_repair: error: disk full while writing the repaired bag {target} '
              f'({err.strerror}); nothing was kept there: free space or give --out on '
              f'another disk; {args.bag} was left untouched', file=sys.stderr)
        return EXIT_DISK_FULL
    except (BagWriterError, BagReadError, ValueError) as err:
        print(f'bag_repair: error: {err}', file=sys.stderr)
        return EXIT_USAGE
    for report in result.files:
        print(f'{report.name}: {report.action}, {report.messages} messages in '
              f'{report.chunks} intact chunk(s)')
        for line in report.problems:
            print(f'  skipped: {line}')
    info = result.metadata
    print(f'{"would write" if args.dry_run else "wrote"} {result.out}/{METADATA_FILE_NAME}: '
          f'{info["message_count"]} messages on {len(info["topics_with_message_count"])} '
          f'topic(s) in {len(info["relative_file_paths"])} file(s); '
          f'{args.bag} {"is" if args.dry_run else "was"} left untouched')
    if result.lost:
        print('bag_repair: the damaged parts listed above are lost', file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


if __name__ == '__main__':
    exit_with(main, 'bag_repair')
