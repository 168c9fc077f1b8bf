"""One writer per output folder: an OS-level lock on ``OUT/.lock`` that records its holder.

The lock is an advisory ``flock`` (``msvcrt.locking`` on Windows) held for as long as the process
lives, so a run killed by any signal, ``kill -9`` included, releases it with its last breath: a stale
lock file is simply taken over by the next run. The file names the holder (pid, host, command, start
time) so a refused second run can say who holds the folder.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..errors import InputError

LOCK_FILE = ".lock"

if sys.platform == "win32":  # pragma: no cover
    import msvcrt

    def _try_lock(fd: int) -> bool:
        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
            return True
        except OSError:
            return False
else:
    import fcntl

    def _try_lock(fd: int) -> bool:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except OSError:
            return False


def _holder(path: Path) -> str:
    try:
        info = json.loads(path.read_text())
        started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(float(info["started"])))
        return f"pid {info['pid']} on {info['host']} ('{info['command']}', started {started})"
    except (OSError, ValueError, KeyError, TypeError):
        return "another process"


@contextmanager
def output_lock(out: str | Path) -> Iterator[None]:
    """Hold the lock of output folder ``out`` (created if missing) for the body; refuse if another
    live process holds it."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        if not _try_lock(fd):
            raise InputError(out, f"output folder is in use by {_holder(path)}",
                             "wait for that run to finish, or give another --out")
        record = {"pid": os.getpid(), "host": socket.gethostname(), "command": " ".join(sys.argv[:3]),
                  "started": time.time()}
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, json.dumps(record).encode())
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock
