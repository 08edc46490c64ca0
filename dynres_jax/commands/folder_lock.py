"""An output folder's lock: ``run.lock`` in --out, ``flock``-ed by the process that claimed the folder
(``checks.claim``), holding its pid and host: a second run on the same folder is refused while the first runs. The
holder deletes it when it exits (a killed one leaves it behind, stale: the kernel has dropped its ``flock``)."""

from __future__ import annotations

import atexit
import fcntl
import os
import socket

from dynres_jax.errors import InputError

LOCK = "run.lock"  # in --out: flock-ed by the process that claimed it, holding its pid and host
_locks: dict[str, tuple[int, str, int]] = {}  # folder (real path) -> (open lock file, its path, holder's pid)


def hold(out: str) -> bool:
    """Hold ``out``'s lock for the rest of this process (an ``flock``: the kernel drops it when the process dies, so a
    stale lock, its pid no longer alive, is taken over); False when another process holds it."""
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as e:  # a folder the checks let through but the system refuses (/proc, a read-only mount)
        raise InputError(f"--out: cannot write to {out!r} ({e.strerror})") from None
    key, path = os.path.realpath(out), os.path.join(out, LOCK)
    if key in _locks:
        return True
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return False
        except OSError as e:
            os.close(fd)
            raise InputError(f"--out {out!r}: cannot lock {LOCK} ({e.strerror or e}); choose a folder on a file "
                             "system with locks") from None
        if _same_file(fd, path):
            break
        os.close(fd)  # its holder deleted it as we opened it (``release``): lock the file now at the path
    os.ftruncate(fd, 0)
    os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode())
    _locks[key] = (fd, os.path.abspath(path), os.getpid())
    return True


def _same_file(fd: int, path: str) -> bool:
    try:
        here, there = os.fstat(fd), os.stat(path)
    except FileNotFoundError:
        return False
    return (here.st_dev, here.st_ino) == (there.st_dev, there.st_ino)


@atexit.register
def release() -> None:
    """Delete the locks this process holds, then drop them (in that order, so that a run waiting on the same file
    finds it gone and locks a new one); a forked child that exits leaves its parent's locks alone."""
    for key, (fd, path, pid) in list(_locks.items()):
        if pid != os.getpid():
            continue
        try:
            os.unlink(path)
        except OSError:
            pass  # the folder is gone or read-only now: the kernel still drops the lock as the file closes
        os.close(fd)
        del _locks[key]


def holder(out: str) -> str:
    """Who holds ``out``'s lock, as its file says."""
    try:
        with open(os.path.join(out, LOCK)) as f:
            return f.read().strip() or "pid not yet written"
    except OSError as e:
        return f"its {LOCK} unreadable: {e.strerror or e}"
