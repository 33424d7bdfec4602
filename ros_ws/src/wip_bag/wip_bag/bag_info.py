"""Print what ``ros2 bag info`` prints for a rosbag2 MCAP bag: ``scripts/bag_info BAG``.

rosbag2's CLI is not on PyPI; this prints the same block as ``ros2 bag info`` (Jazzy,
``rosbag2_py`` ``format_bag_meta_data``): files, bag size, storage id, ROS distro, duration,
start, end, message count and one line per topic with its type, message count and
serialization format. Two lines are added after it:

- ``Compression``: the MCAP chunk compression found in the files (rosbag2's own file or
  message compression, ``compression_format``/``compression_mode`` of metadata.yaml, is
  shown when set);
- ``Check``: whether every chunk's CRC matches, every file was finished and
  ``metadata.yaml`` matches the files' contents; otherwise what is wrong (the time range
  and topics of a damaged part) and that ``scripts/bag_repair`` recovers the rest.

The verdict is also the exit code: 0 OK, 1 NOT OK, 2 no bag there (or bad options).

Like ``ros2 bag info``, the figures come from ``metadata.yaml`` when the bag directory has
one; a single ``.mcap`` file, a directory without ``metadata.yaml`` or ``--from-content``
use the files' contents (their summaries; a scan of unfinished files).

Usage::

    scripts/bag_info BAG [--from-content] [--json FILE]
"""

import argparse
import json
import pathlib
import sys
import time

from wip_runtime.cli import add_exit_codes, EXIT_FAILED, EXIT_OK, EXIT_USAGE, exit_with

from .bag_reader import (BagReadError, integrity_problems, missing_metadata,
                         read_metadata_file, scan)
from .bag_repair import mcap_files_by_index, read_file_contents
from .bag_writer import METADATA_FILE_NAME

INDENT = 19  # width of the field names of ros2 bag info ('Topic information: ')
_UNITS = ('B', 'KiB', 'MiB', 'GiB', 'TiB')


def format_file_size(size):
    """Bytes as rosbag2 prints them: '512 B', '1.5 KiB', '3.2 MiB' (one decimal)."""
    size = float(size)
    index = 0
    while size >= 1024.0 and index < len(_UNITS) - 1:
        size /= 1024.0
        index += 1
    return f'{size:.0f} {_UNITS[index]}' if index == 0 else f'{size:.1f} {_UNITS[index]}'


def format_seconds(nanoseconds):
    """'12.345678901' from integer nanoseconds (nanosecond precision, as Jazzy prints)."""
    nanoseconds = int(nanoseconds)
    sign = '-' if nanoseconds < 0 else ''
    seconds, fraction = divmod(abs(nanoseconds), 1_000_000_000)
    return f'{sign}{seconds}.{fraction:09d}'


def format_time_point(nanoseconds):
    """'Jan  1 2024 12:00:00.123456789 (1704110400.123456789)' in local time."""
    seconds, fraction = divmod(int(nanoseconds), 1_000_000_000)
    try:
        local = time.localtime(seconds)
    except (OverflowError, OSError, ValueError):
        return f'({format_seconds(nanoseconds)})'

    date = time.strftime('%b %e %Y', local)
    return f'{date} {time.strftime("%H:%M:%S", local)}.{fraction:09d} ' \
           f'({format_seconds(nanoseconds)})'


def _files_of(path):
    path = pathlib.Path(path)
    if path.is_file():
        return path.parent, [path]
    if not path.is_dir():
        raise BagReadError(f'no bag at {path}')
    files = mcap_files_by_index(path)
    if not files:
        raise BagReadError(f'{path}: no .mcap file')
    return path, files


def _from_content(contents):
    topics, counts = {}, {}
    for c in contents:
        for topic, info in c.topics.items():
            topics.setdefault(topic, info.type_name)
            counts[topic] = counts.get(topic, 0) + c.counts.get(topic, 0)
    starts = [c.stats.start_ns for c in contents if c.stats.start_ns is not None]
    ends = [c.stats.end_ns for c in contents if c.stats.end_ns is not None]
    start = min(starts) if starts else 0
    return {
        'files': [c.stats.path for c in contents],
        'message_count': sum(c.stats.count for c in contents),
        'start_ns': start,
        'duration_ns': (max(ends) - start) if ends else 0,
        'topics': [{'name': t, 'type': topics[t], 'count': counts[t],
                    'serialization_format': 'cdr'} for t in topics],
    }


def bag_information(path, from_content=False):
    """Gather what :func:`format_bag_information` prints.

    Parameters
    ----------
    path : str or pathlib.Path
        A bag directory or a single ``.mcap`` file.
    from_content : bool
        Ignore ``metadata.yaml`` and use the files' contents.

    Returns
    -------
    dict
        ``files``, ``bag_size`` [bytes], ``storage_identifier``, ``ros_distro``,
        ``duration_ns``, ``start_ns``, ``message_count``, ``topics`` (list of dicts
        ``name``, ``type``, ``count``, ``serialization_format``), ``source``
        ('metadata.yaml' or 'content'), ``chunk_compression`` (dict compression -> number of
        chunks, '' = uncompressed), ``rosbag2_compression`` ('' if none),
        ``unfinished_files`` and ``problems`` (list of str; empty when metadata.yaml matches
        the contents and every file is finished).
    """
    directory, files = _files_of(path)
    scans = [scan(f) for f in files]
    contents = [read_file_contents(f) for f in files]
    content = _from_content(contents)
    metadata = None
    problems = integrity_problems(scans) + [n for s in scans for n in s.notes]
    metadata_path = directory / METADATA_FILE_NAME
    if pathlib.Path(path).is_dir() and metadata_path.is_file():
        try:
            metadata = read_metadata_file(metadata_path)
        except BagReadError as err:
            problems.append(str(err))
    unfinished = [s.path.name for s in scans if s.unfinished]
    info = dict(content)
    info['storage_identifier'] = 'mcap'
    info['ros_distro'] = ''
    info['rosbag2_compression'] = ''
    info['source'] = 'content'
    if metadata is not None:
        try:
            _compare_metadata(metadata, content, info, problems, from_content)
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as err:
            problems.append(f'metadata.yaml is incomplete or malformed ({type(err).__name__}: '
                            f"{err}); figures from the files' contents")
            info.update(content)
            info['source'] = 'content'
    elif pathlib.Path(path).is_dir() and not metadata_path.is_file():
        problems.append(missing_metadata(path))
    info['bag_size'] = sum(f.stat().st_size for f in files)
    chunks = {}
    for c in contents:
        if c.chunks:
            key = c.compression or ''
            chunks[key] = chunks.get(key, 0) + c.chunks
    info['chunk_compression'] = chunks
    info['unfinished_files'] = unfinished
    info['problems'] = problems
    return info


def _compare_metadata(metadata, content, info, problems, from_content):
    """Compare metadata.yaml with the content; take its figures unless from_content."""
    listed = [str(name) for name in metadata.get('relative_file_paths') or []]
    if listed != content['files']:
        problems.append(f'metadata.yaml lists {listed}, the directory holds '
                        f'{content["files"]}')
    if int(metadata.get('message_count', -1)) != content['message_count']:
        problems.append(f'metadata.yaml counts {metadata.get("message_count")} messages, '
                        f'the files hold {content["message_count"]}')
    info['ros_distro'] = str(metadata.get('ros_distro') or '')
    info['storage_identifier'] = str(metadata.get('storage_identifier', 'mcap'))
    if metadata.get('compression_format'):
        info['rosbag2_compression'] = (f'{metadata["compression_format"]} '
                                       f'({metadata.get("compression_mode", "")})')
    if not from_content:
        info['source'] = METADATA_FILE_NAME
        info['files'] = listed
        info['message_count'] = int(metadata.get('message_count', 0))
        info['start_ns'] = int(metadata['starting_time']['nanoseconds_since_epoch'])
        info['duration_ns'] = int(metadata['duration']['nanoseconds'])
        if not (0 <= info['start_ns'] < 2 ** 63 and 0 <= info['duration_ns'] < 2 ** 63):
            raise ValueError('times out of range')
        info['topics'] = [
            {'name': t['topic_metadata']['name'], 'type': t['topic_metadata']['type'],
             'count': int(t['message_count']),
             'serialization_format': t['topic_metadata'].get('serialization_format',
                                                             'cdr')}
            for t in metadata.get('topics_with_message_count') or []]


def _indented(lines):
    if not lines:
        return '\n'
    return lines[0] + '\n' + ''.join(' ' * INDENT + line + '\n' for line in lines[1:])


def format_bag_information(info):
    """Return the text of ``ros2 bag info`` (plus Compression and Check lines) for ``info``."""
    end_ns = info['start_ns'] + info['duration_ns']
    topics = [f'Topic: {t["name"]} | Type: {t["type"]} | Count: {t["count"]} | '
              f'Serialization Format: {t["serialization_format"]}' for t in info['topics']]
    if info['chunk_compression']:
        compression = ', '.join(
            f'{name or "none"} ({count} MCAP chunk{"s" if count != 1 else ""})'
            for name, count in sorted(info['chunk_compression'].items()))
    else:
        compression = 'none (no chunk)'
    if info['rosbag2_compression']:
        compression += f'; rosbag2 {info["rosbag2_compression"]}'
    if info['problems']:
        check = 'NOT OK: ' + '; '.join(info['problems']) + (
            '' if info['problems'][-1].endswith('writes a new bag with one')
            else ' -> run scripts/bag_repair')
    else:
        check = 'OK (every chunk CRC-checked, every file finished, metadata.yaml matches ' \
                'the files)' if info['source'] == METADATA_FILE_NAME else \
                'OK (every chunk CRC-checked, every file finished)'
    return (
        '\n'
        + 'Files:             ' + _indented(info['files'])
        + f'Bag size:          {format_file_size(info["bag_size"])}\n'
        + f'Storage id:        {info["storage_identifier"]}\n'
        + f'ROS Distro:        {info["ros_distro"] or "unknown"}\n'
        + f'Duration:          {format_seconds(info["duration_ns"])}s\n'
        + f'Start:             {format_time_point(info["start_ns"])}\n'
        + f'End:               {format_time_point(end_ns)}\n'
        + f'Messages:          {info["message_count"]}\n'
        + 'Topic information: ' + _indented(topics)
        + 'Service:           0\n'
        + 'Service information: \n'
        + f'Compression:       {compression}\n'
        + f'Check:             {check}\n')


def main(argv=None):
    """``scripts/bag_info BAG``; exit code 0 (OK), 1 (NOT OK) or 2 (no bag there)."""
    parser = argparse.ArgumentParser(
        prog='scripts/bag_info', formatter_class=argparse.RawDescriptionHelpFormatter,
        description="""\
Print what `ros2 bag info` prints for a rosbag2 MCAP bag (directory or single .mcap
file), plus its chunk compression and a check of every chunk's CRC and of metadata.yaml
against the files (OK: exit 0, NOT OK: exit 1).

Examples
--------
    scripts/bag_info out/demo/bag                    # a bag directory
    scripts/bag_info out/demo/bag/bag_0.mcap         # one file
    scripts/bag_info --from-content out/demo/bag     # counts from the data itself
    scripts/bag_info out/demo/bag --json info.json   # also as JSON, to a file
    scripts/bag_info out/demo/bag --json -           # JSON instead of the text""")
    parser.add_argument('bag', help='bag directory or .mcap file')
    parser.add_argument('--from-content', action='store_true',
                        help="figures from the files' contents, not from metadata.yaml")
    parser.add_argument('--json', metavar='FILE',
                        help="also write the information as JSON to FILE ('-': print it "
                        'instead of the text), as --json of bench and check_base')
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    try:
        info = bag_information(args.bag, from_content=args.from_content)
    except (BagReadError, OSError) as err:
        print(f'bag_info: error: {err}', file=sys.stderr)
        return EXIT_USAGE
    if args.json == '-':
        print(json.dumps(info, indent=2))
    else:
        sys.stdout.write(format_bag_information(info))
    if args.json not in (None, '-'):
        try:
            pathlib.Path(args.json).write_text(json.dumps(info, indent=2) + '\n',
                                               encoding='utf-8')
        except OSError as err:
            print(f'bag_info: error: {args.json}: {err.strerror}', file=sys.stderr)
            return EXIT_USAGE
    return EXIT_FAILED if info['problems'] else EXIT_OK


if __name__ == '__main__':
    exit_with(main, 'bag_info')
