"""Worker processes that end with the process whose work they do.

A ``kill -9`` (the out-of-memory killer, a scheduler's hard limit) gives a process no chance to stop its
workers: without help they live on, idle, holding memory and the locks of the directory they write
(``don_gym.io.DirectoryLock``), so that the next command is refused. :func:`end_with_parent`, called first
thing in a worker (a pool's initializer, a data loader's ``worker_init_fn``), ties the worker's life to
its owner's.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import select
import signal
import sys
import threading
import time

__all__ = ["PARENT_POLL_S", "end_with_parent", "process_alive"]

#: Seconds between two looks at the owner where the kernel cannot notify its end (no pidfd).
PARENT_POLL_S = 0.5
_PR_SET_PDEATHSIG = 1


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` of this machine is running (a zombie, dead but not yet reaped, is not)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, someone else's
        return True
    with contextlib.suppress(OSError, IndexError):
        # "pid (name) S ...": the state follows the last parenthesis (a name may hold one).
        with open(f"/proc/{pid}/stat", "rb") as stat:
            return stat.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    return True


def end_with_parent(owner_pid: int, parent_death_signal: bool = True) -> None:
    """End this process (SIGKILL) as soon as process ``owner_pid`` ends, however it ends.

    Two guards: Linux's parent-death signal (``prctl(PR_SET_PDEATHSIG)``) for the direct parent, and a
    daemon thread that waits for ``owner_pid`` itself, because a worker's direct parent need not be its
    owner (a fork server starts the workers of a data loader and outlives the trainer by a moment). The
    wait is a pidfd where the kernel has them (Linux 5.3+), else a look every :data:`PARENT_POLL_S` s.
    An owner that is already gone ends the worker at once. SIGKILL, not an exception: a worker killed so
    leaves only its temporary files, which the next run removes, and cannot hang on a queue nobody reads.
    ``parent_death_signal=False`` keeps to the watch: the signal follows the parent *thread* that started the
    process, and a launcher (torchrun) may start its processes from a thread that ends before they do.
    """
    if parent_death_signal and sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if not process_alive(owner_pid):
        os.kill(os.getpid(), signal.SIGKILL)
    threading.Thread(target=_wait_for_end, args=(owner_pid,), name="end-with-parent", daemon=True).start()


def _wait_for_end(owner_pid: int) -> None:
    try:
        pidfd: int | None = os.pidfd_open(owner_pid)
    except (AttributeError, OSError):  # no pidfds here, or the owner is gone already
        pidfd = None
    if pidfd is not None:
        with contextlib.suppress(OSError):
            select.select([pidfd], [], [])  # readable once the process has ended
    while process_alive(owner_pid):  # without a pidfd, or should the wait have failed
        time.sleep(PARENT_POLL_S)
    os.kill(os.getpid(), signal.SIGKILL)
