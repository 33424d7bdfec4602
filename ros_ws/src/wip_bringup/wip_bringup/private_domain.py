"""A private DDS domain per run or test.

Reserved on this host so that two runs (or two test sessions) started side by side never share one.

Simulations and tests run in a random domain of their own with localhost-only discovery.
Picking at random alone collides: with a few sessions running at once, two processes of
different runs met in one domain, and a lockstep plant then took the other run's torques.
A reservation is an advisory lock (flock) on a file per domain id in the temporary
directory, held for as long as the reserving process keeps the returned descriptor open;
the kernel drops it when the process exits, however it exits, so nothing goes stale.
"""

from __future__ import annotations

import fcntl
import os
import pathlib
import random
import tempfile

#: 1..101: the Fast DDS ports of higher domain ids fall into Linux's ephemeral port range.
FIRST_DOMAIN_ID = 1
LAST_DOMAIN_ID = 101
LOCK_DIRECTORY = pathlib.Path(tempfile.gettempdir()) / 'wip-ros-domains'


def reserve_private_domain(rng: random.Random | None = None) -> tuple[int, int]:
    """Reserve a domain id no other process of this host holds.

    Return the id and the descriptor that holds it (close it to release the domain). Fall
    back to a random id, unreserved (descriptor -1), when all are taken or the lock
    directory cannot be used.
    """
    rng = rng or random.Random()
    candidates = list(range(FIRST_DOMAIN_ID, LAST_DOMAIN_ID + 1))
    rng.shuffle(candidates)
    try:
        LOCK_DIRECTORY.mkdir(mode=0o1777, parents=True, exist_ok=True)
    except OSError:
        return candidates[0], -1
    for domain_id in candidates:
        try:
            descriptor = os.open(LOCK_DIRECTORY / f'{domain_id}.lock',
                                 os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except OSError:
            continue
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(descriptor)
            continue
        return domain_id, descriptor
    return candidates[0], -1


def release_private_domain(descriptor: int) -> None:
    """Give a reserved domain back (a no-op for an unreserved one)."""
    if descriptor >= 0:
        os.close(descriptor)


#: Descriptors of :func:`take_private_domain`, released together.
_TAKEN: list[int] = []


def take_private_domain() -> int:
    """Return a reserved domain id held until :func:`release_taken_domains`.

    For a test harness: its fixture releases them after each test.
    """
    domain_id, descriptor = reserve_private_domain()
    _TAKEN.append(descriptor)
    return domain_id


def release_taken_domains() -> None:
    """Release every domain of :func:`take_private_domain`."""
    while _TAKEN:
        release_private_domain(_TAKEN.pop())
