"""Split bags, repair of unfinished bags and ``bag_info``, without ROS processes.

Every bag is checked with ``rosbags`` (an independent rosbag2 reader) as well as with the
project's reader. Messages are std_msgs/String with distinct, incompressible payloads, so
that exact equality of bytes and counts is the criterion (no tolerance is needed).
"""

import os
import random

import pytest
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import Reader
from std_msgs.msg import String
import yaml

from bagtools_helpers import assert_metadata_matches_content
from wip_bag.bag_info import bag_information, format_bag_information
from wip_bag.bag_info import main as bag_info_main
from wip_bag.bag_reader import iter_raw_messages, read_bag, read_topics
from wip_bag.bag_repair import main as bag_repair_main
from wip_bag.bag_repair import mcap_files_by_index, repair_bag
from wip_bag.bag_writer import BagWriterError, Rosbag2McapWriter

START_NS = 1_700_000_000_000_000_000
PERIOD_NS = 1_000_000  # 1 kHz


def _payloads(n, seed=0):
    rng = random.Random(seed)
    return [bytes(serialize_message(String(data=f'{k}:' + ''.join(
        rng.choice('abcdefghijklmnopqrstuvwxyz0123456789') for _ in range(40 + k % 60)))))
        for k in range(n)]


def _topic(k):
    return '/fast' if k % 4 else '/slow'


def _write(directory, payloads, **options):
    bag = Rosbag2McapWriter(directory, **options)
    bag.add_topic('/fast', 'std_msgs/msg/String')
    bag.add_topic('/slow', 'std_msgs/msg/String')
    for k, data in enumerate(payloads):
        bag.write(_topic(k), data, START_NS + k * PERIOD_NS)
    return bag


def _metadata(directory):
    return yaml.safe_load((directory / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']


def _rosbags_messages(directory):
    with Reader(directory) as reader:
        return [(c.topic, t, bytes(d)) for c, t, d in reader.messages()]


def _snapshot(directory):
    """Name -> bytes of every file under ``directory`` (to show it was not touched)."""
    return {p.relative_to(directory): p.read_bytes() for p in sorted(directory.rglob('*'))
            if p.is_file()}


def _expected(payloads, n=None):
    n = len(payloads) if n is None else n
    return [(_topic(k), START_NS + k * PERIOD_NS, payloads[k]) for k in range(n)]


@pytest.mark.parametrize('compression', ['zstd', 'none'])
def test_split_by_size_gives_several_listed_files_read_back_completely(tmp_path, compression):
    payloads = _payloads(3000)
    max_size = 40_000  # [bytes]: about 4..8 files of this data
    directory = tmp_path / 'by_size'
    _write(directory, payloads, compression=compression, chunk_size=8192,
           max_bag_size=max_size).close()
    files = mcap_files_by_index(directory)
    assert [f.name for f in files] == [f'by_size_{i}.mcap' for i in range(len(files))]
    assert len(files) >= 3
    # Each file's data section stays within max_bag_size; its summary comes on top: the
    # schema and channels again, the bag metadata record (~2 KiB here) and one chunk index
    # per chunk (< 100 B each with two channels).
    for f in files:
        summary_allowance = 4096 + 100 * (max_size // 8192 + 8)
        assert os.path.getsize(f) <= max_size + summary_allowance
    # All but the last file are nearly full: the writer splits only when < 1/16 is left
    # (the per-file summary is counted in the allowance above, so use the data bound).
    for f in files[:-1]:
        assert os.path.getsize(f) >= max_size * 15 // 16 - 4096
    assert_metadata_matches_content(directory)
    assert _rosbags_messages(directory) == _expected(payloads)
    assert [(m.topic, m.log_time_ns, m.data) for m in iter_raw_messages(directory)] == \
        _expected(payloads)
    slow = [m.message.data.split(':')[0] for m in read_bag(directory, topics=['/slow'])]
    assert slow == [str(k) for k in range(0, 3000, 4)]
    decoded = [m.message.data for m in read_bag(directory)]
    assert [d.split(':')[0] for d in decoded] == [str(k) for k in range(3000)]

    # bag_info lists every file and the right counts, from metadata.yaml and from content.
    for from_content in (False, True):
        info = bag_information(directory, from_content=from_content)
        assert info['files'] == [f.name for f in files]
        assert info['message_count'] == 3000
        assert {t['name']: t['count'] for t in info['topics']} == {'/fast': 2250, '/slow': 750}
        assert info['problems'] == []
    text = format_bag_information(bag_information(directory))
    assert 'Topic: /fast | Type: std_msgs/msg/String | Count: 2250 | Serialization ' \
           'Format: cdr' in text
    assert 'Messages:          3000\n' in text
    assert 'Duration:          2.999000000s\n' in text
    assert 'Files:             by_size_0.mcap\n                   by_size_1.mcap\n' in text
    assert ('zstd' if compression == 'zstd' else 'none') in text.split('Compression:')[1]


def test_split_by_duration_keeps_each_file_shorter_than_the_limit(tmp_path):
    payloads = _payloads(2500)
    directory = tmp_path / 'by_time'
    _write(directory, payloads, max_bag_duration=0.5).close()
    info = _metadata(directory)
    # 2.5 s of messages, 0.5 s per file -> 5 files of 500 messages (the message at +0.5 s
    # opens the next file).
    assert len(info['files']) == 5
    for i, entry in enumerate(info['files']):
        assert entry['message_count'] == 500
        assert entry['starting_time']['nanoseconds_since_epoch'] == START_NS + i * 500 * PERIOD_NS
        assert entry['duration']['nanoseconds'] < 0.5e9
    assert_metadata_matches_content(directory)
    assert _rosbags_messages(directory) == _expected(payloads)


def test_repair_recovers_every_complete_chunk_of_a_killed_split_bag(tmp_path):
    payloads = _payloads(2000)
    directory = tmp_path / 'killed'
    bag = _write(directory, payloads[:1500], max_bag_duration=0.6, chunk_size=1 << 20)
    bag.flush()  # A chunk boundary: messages 0..1499 are complete on disk.
    for k in range(1500, 1600):  # In the chunk in progress: lost.
        bag.write(_topic(k), payloads[k], START_NS + k * PERIOD_NS)
    bag._stream.close()  # SIGKILL: no summary, no final metadata.yaml.
    # metadata.yaml was written at the splits and lists only the files closed then.
    assert len(_metadata(directory)['relative_file_paths']) == 2
    before = bag_information(directory)
    assert before['problems'] and before['unfinished_files'] == ['killed_2.mcap']
    with Reader(directory) as reader:  # rosbags sees the stale metadata.yaml only ...
        assert reader.message_count == 1200

    original = _snapshot(directory)
    result = repair_bag(directory)
    assert result.out == tmp_path / 'killed_repaired'
    assert [f.action for f in result.files] == ['copied', 'copied', 'rewritten']
    assert result.files[2].messages == 1500 - 1200
    assert _snapshot(directory) == original  # The original is never touched ...
    repaired = result.out
    assert_metadata_matches_content(repaired)  # ... and all of the repaired bag.
    assert _rosbags_messages(repaired) == _expected(payloads, 1500)
    assert bag_information(repaired)['problems'] == []
    # Idempotent: repairing the repaired bag copies every file and gives the same metadata.
    again = repair_bag(repaired, out=tmp_path / 'again')
    assert [f.action for f in again.files] == ['copied'] * 3
    assert _metadata(tmp_path / 'again') == _metadata(repaired)
    with pytest.raises(BagWriterError, match='exists'):  # Never into an existing directory.
        repair_bag(directory, out=tmp_path / 'again')


def test_repair_drops_a_partial_chunk_and_keeps_custom_data(tmp_path):
    payloads = _payloads(400)
    directory = tmp_path / 'torn'
    bag = _write(directory, payloads[:300], chunk_size=1 << 20,
                 custom_data={'scenario': 'test'})
    bag.flush()
    first_chunk_end = os.path.getsize(directory / 'torn_0.mcap')
    for k in range(300, 400):
        bag.write(_topic(k), payloads[k], START_NS + k * PERIOD_NS)
    bag.flush()
    second_chunk_end = os.path.getsize(directory / 'torn_0.mcap')
    bag._stream.close()
    # A power loss tears the second chunk: half of its bytes reached the disk.
    with open(directory / 'torn_0.mcap', 'rb+') as stream:
        stream.truncate((first_chunk_end + second_chunk_end) // 2)
    # Only the bag metadata written at close carries custom_data; without it, the repair
    # falls back to defaults. Give it the metadata.yaml a split would have written.
    (directory / 'metadata.yaml').write_text(yaml.safe_dump({'rosbag2_bagfile_information': {
        'custom_data': {'scenario': 'test'}, 'ros_distro': 'jazzy'}}))
    result = repair_bag(directory, compression='lz4')
    assert result.files[0].messages == 300
    assert _rosbags_messages(result.out) == _expected(payloads, 300)
    assert _metadata(result.out)['custom_data'] == {'scenario': 'test'}
    assert_metadata_matches_content(result.out)


def test_a_file_without_complete_chunk_is_set_aside(tmp_path):
    payloads = _payloads(100)
    directory = tmp_path / 'empty_tail'
    bag = _write(directory, payloads, max_bag_duration=0.05)
    bag.split()  # The recorder dies right after opening a new file.
    bag._stream.close()
    result = repair_bag(directory)
    assert result.files[-1].action == 'dropped (no intact chunk)'
    assert (directory / result.files[-1].name).exists()  # the original: untouched
    assert not (result.out / result.files[-1].name).exists()
    assert_metadata_matches_content(result.out)
    assert _rosbags_messages(result.out) == _expected(payloads)


def test_command_line_tools(tmp_path, capsys):
    payloads = _payloads(50)
    directory = tmp_path / 'cli'
    bag = _write(directory, payloads, chunk_size=256)
    bag._stream.close()
    assert bag_info_main([str(directory)]) == 1  # the verdict is the exit code
    assert 'NOT OK' in capsys.readouterr().out
    # Unfinished: the tail in the chunk in progress is lost, so the exit code is 1.
    assert bag_repair_main([str(directory), '--dry-run']) == 1
    out = capsys.readouterr().out
    assert 'cli_0.mcap: would rewrite' in out and 'rewritten' not in out
    assert f'would write {tmp_path / "cli_repaired"}/metadata.yaml: ' in out
    assert not (directory / 'metadata.yaml').exists()
    assert not (tmp_path / 'cli_repaired').exists()
    assert bag_repair_main([str(directory)]) == 1
    out = capsys.readouterr().out
    assert 'cli_0.mcap: rewritten' in out and 'skipped: cli_0.mcap: unfinished' in out
    repaired = tmp_path / 'cli_repaired'
    assert bag_info_main([str(repaired / 'cli_0.mcap')]) == 0  # a single file
    out = capsys.readouterr().out
    assert 'Check:             OK' in out
    assert 'Messages:          ' in out
    assert bag_info_main([str(tmp_path / 'nothing')]) == 2
    assert read_topics(repaired)['/fast'].type_name == 'std_msgs/msg/String'


@pytest.mark.parametrize('old, new', [('wip_msgs/msg/ArcState', 'YawTorque'),
                                      ('wip_msgs/msg/MpcOutput', 'DriveTorque')])
def test_a_bag_of_a_renamed_message_type_is_played_as_the_type_of_today(old, new):
    pytest.importorskip('wip_msgs')
    from wip_bag.message_types import message_class
    import wip_msgs.msg
    # The fields did not change with the names: an old bag's CDR is today's type's CDR.
    assert message_class(old) is getattr(wip_msgs.msg, new)
    with pytest.raises(LookupError, match='cannot import message type'):
        message_class('wip_msgs/msg/NoSuchType')
