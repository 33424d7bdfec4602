"""A bag directory without metadata.yaml.

bag_info says NOT OK and why, and the readers (report, replay, rerun: every one goes through
``bag_reader.check_bag``) read it with a warning on stderr that says the same and names
scripts/bag_repair. bag_repair's new bag gets the mode a mkdir gives (the umask's), as rosbag2's
bags do.
"""

import contextlib
import io
import os
import stat

import pytest

pytest.importorskip('mcap')

from wip_bag import bag_reader  # noqa: E402
from wip_bag.bag_info import main as bag_info_main  # noqa: E402
from wip_bag.bag_reader import iter_raw_messages, read_topics  # noqa: E402
from wip_bag.bag_repair import main as bag_repair_main  # noqa: E402
from wip_bag.bag_writer import Rosbag2McapWriter  # noqa: E402


def _cdr_string(text):
    data = text.encode('utf-8') + b'\x00'
    return b'\x00\x01\x00\x00' + len(data).to_bytes(4, 'little') + data


@pytest.fixture
def bag_without_metadata(tmp_path):
    directory = tmp_path / 'my bag'
    with Rosbag2McapWriter(directory) as bag:
        bag.add_topic('/a', 'std_msgs/msg/String')
        for k in range(10):
            bag.write('/a', _cdr_string(str(k)), 1_000_000_000 + k * 1_000_000)
    (directory / 'metadata.yaml').unlink()
    return directory


def _run(function, *args):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = function(*args)
    return code, out.getvalue(), err.getvalue()


def test_bag_info_and_the_readers_say_the_same(bag_without_metadata, monkeypatch):
    code, out, _ = _run(bag_info_main, [str(bag_without_metadata)])
    assert code == 1
    (check,) = [line for line in out.splitlines() if line.startswith('Check:')]
    said = bag_reader.missing_metadata(bag_without_metadata)
    assert check == 'Check:             NOT OK: ' + said
    assert "scripts/bag_repair '" in said and 'ros2 bag and rosbags cannot open it' in said
    monkeypatch.setattr(bag_reader, '_warned_no_metadata', set())
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert len(list(iter_raw_messages(bag_without_metadata))) == 10   # replay, rerun
        assert list(read_topics(bag_without_metadata)) == ['/a']
    assert err.getvalue() == f'warning: {bag_without_metadata}: {said}\n'   # once


def test_a_repaired_bag_gets_the_umask_mode(bag_without_metadata, tmp_path):
    old = os.umask(0o027)
    try:
        code, _, err = _run(bag_repair_main, [str(bag_without_metadata), '--out',
                                              str(tmp_path / 'repaired')])
    finally:
        os.umask(old)
    assert code == 0, err
    assert stat.S_IMODE((tmp_path / 'repaired').stat().st_mode) == 0o750
    assert (tmp_path / 'repaired' / 'metadata.yaml').is_file()


def test_replay_refuses_a_remap_to_an_invalid_name_before_it_starts(capsys):
    from wip_bag.replayer_node import parse_command_line
    with pytest.raises(SystemExit) as refused:
        parse_command_line(['BAG', '--remap', '/a:=/my b'])
    assert refused.value.code == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and "'/my b' is not a valid ROS topic name" in err
