"""One process per run folder: an advisory lock on ``<run_dir>/.jaxhead.lock``.  [host]

A cohort's subjects may run in other processes (Dask workers): each holds its subject's own lock,
``<run_dir>/.jaxhead-<subject>.lock``, while it works in ``<run_dir>/<subject>/``, so that a task
left running by a killed driver and the task of the next run never write one folder together.

The lock is a kernel lock (``flock``) on the file, so it is released when its holder exits in any
way, ``kill -9`` included: a lock left by a dead process is never "held". The file also records
who holds it (pid, host, start time, command) for the message a second process prints; a record
left behind by a process that died is reported when the next run takes the lock over.
"""

import contextlib
import datetime
import errno
import fcntl
import json
import logging
import os
import socket
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

log = logging.getLogger("jaxhead")

LOCK_NAME = ".jaxhead.lock"


class RunLockedError(ValueError):
    """Another process holds the run folder's lock."""


def _holder(fh) -> dict:
    try:
        fh.seek(0)
        return json.loads(fh.read() or "{}")
    except (OSError, ValueError):
        return {}


def _describe(h: dict) -> str:
    if not h:
        return "another jaxhead process"
    return (f"jaxhead pid {h.get('pid')} on {h.get('host')} (started {h.get('started')}: "
            f"{h.get('command', '?')})")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextlib.contextmanager
def run_lock(run_dir: str | os.PathLike, *, wait: bool = False,
             say: Callable[[str], None] = log.info, subject: str | None = None) -> Iterator[Path]:
    """Hold the lock of a run folder (or of one subject in it) for the duration of the block.

    Arguments:
        run_dir: the run folder (must exist).
        wait: if another process holds the lock, wait for it (saying so) instead of raising.
        say: where the waiting and stale-lock messages go.
        subject: lock only this subject's folder (``.jaxhead-<subject>.lock``), as a worker does.

    Raises:
        RunLockedError: the folder is locked by another process and `wait` is False.
    """
    path = Path(run_dir) / (LOCK_NAME if subject is None else f".jaxhead-{subject}.lock")
    what = f"run folder {run_dir}" + (f" (subject {subject})" if subject is not None else "")
    fh = open(path, "a+")
    try:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise
            who = _describe(_holder(fh))
            if not wait:
                raise RunLockedError(
                    f"{what} is in use by {who}; wait for it to finish "
                    "(`jaxhead run --wait`), or write to another folder (`--out`).") from None
            say(f"{what} is in use by {who}; waiting for it to finish ...")
            t0 = time.monotonic()
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
            say(f"{what} is free after {time.monotonic() - t0:.0f} s; continuing")
        old = _holder(fh)
        if old.get("pid") and old.get("host") == socket.gethostname() \
                and not _alive(int(old["pid"])):
            say(f"taking over the stale lock of {_describe(old)}: that process is no longer "
                "running (it was killed or crashed); its unfinished stage folders are discarded")
        elif old.get("pid"):
            say(f"taking over the lock record of {_describe(old)}, which no longer holds it")
        fh.seek(0)
        fh.truncate()
        fh.write(json.dumps({
            "pid": os.getpid(), "host": socket.gethostname(),
            "started": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "command": " ".join(sys.argv[:4])}))
        fh.flush()
        yield path
        fh.seek(0)
        fh.truncate()  # a clean exit leaves no holder record
        fh.flush()
    finally:
        fh.close()  # releases the flock
