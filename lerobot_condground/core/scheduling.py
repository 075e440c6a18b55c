"""The package's threads stay at normal scheduling priority.

SVT-AV1 (the AV1 encoder in PyAV's wheel, LeRobot's default video codec) moves the thread that runs an encoder
to SCHED_FIFO at priority 99 whenever the process may, that is as root, and leaves it there: the thread that
recorded, every thread it starts and every process it launches then run at real-time priority, and on a
2-core machine they starve everything beside them (tests, trainings, timings). Every place the package
encodes restores the thread's policy after the encoder; every command starts from SCHED_OTHER, so a child a
command launches never inherits a real-time policy. (Linux; elsewhere there is nothing to restore.)
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

_HAS_SCHED = hasattr(os, "sched_getscheduler")


def normal_priority() -> None:
    """Puts the calling thread back on SCHED_OTHER if something raised it to a real-time policy."""
    if _HAS_SCHED and os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


@contextmanager
def kept_priority() -> Iterator[None]:
    """The calling thread's scheduling policy and priority as they were before the block (an encoder inside)."""
    if not _HAS_SCHED:
        yield
        return
    policy, priority = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
    try:
        yield
    finally:
        if (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) != (policy, priority):
            os.sched_setscheduler(0, policy, os.sched_param(priority))
