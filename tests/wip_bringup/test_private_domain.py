"""Private DDS domains are reserved on the host.

No two holders share one, a released or dead holder's domain is free again, and an exhausted range
still gives a usable id.
"""

import subprocess
import sys

from wip_bringup import private_domain


def test_reservations_are_distinct_until_the_range_is_exhausted(tmp_path, monkeypatch):
    monkeypatch.setattr(private_domain, 'LOCK_DIRECTORY', tmp_path)
    held = [private_domain.reserve_private_domain() for _ in range(101)]
    ids = [domain_id for domain_id, _ in held]
    assert sorted(ids) == list(range(1, 102))
    assert all(descriptor >= 0 for _, descriptor in held)
    # All taken: an id in range, marked unreserved.
    domain_id, descriptor = private_domain.reserve_private_domain()
    assert 1 <= domain_id <= 101 and descriptor == -1
    # A released domain is the only free one, so the next reservation gets it.
    released_id, released = held.pop(17)
    private_domain.release_private_domain(released)
    assert private_domain.reserve_private_domain()[0] == released_id
    for _, held_descriptor in held:
        private_domain.release_private_domain(held_descriptor)


def test_a_domain_held_by_another_process_is_skipped_and_freed_when_it_exits(
        tmp_path, monkeypatch):
    monkeypatch.setattr(private_domain, 'LOCK_DIRECTORY', tmp_path)
    holder = subprocess.Popen(
        [sys.executable, '-c',
         'import sys, pathlib; from wip_bringup import private_domain as p;'
         f' p.LOCK_DIRECTORY = pathlib.Path({str(tmp_path)!r});'
         ' print(p.reserve_private_domain()[0], flush=True); sys.stdin.read()'],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        env={'PYTHONPATH': ':'.join(sys.path)})
    try:
        taken = int(holder.stdout.readline())
        mine = [private_domain.reserve_private_domain() for _ in range(100)]
        assert taken not in {domain_id for domain_id, _ in mine}
    finally:
        holder.communicate('')
    assert private_domain.reserve_private_domain()[0] == taken
