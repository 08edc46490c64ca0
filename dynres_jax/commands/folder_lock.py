"""An output folder's lock: ``run.lock`` in --out, ``flock``-ed by the process that claimed the folder
(``checks.claim``), holding its pid and host: a second run on the same folder is refused while the first runs."""

from __future__ import annotations

import fcntl
import os
import socket

from dynres_jax.errors import InputError

LOCK = "run.lock"  # in --out: flock-ed by the process that claimed it, holding its pid and host; never deleted
_locks: dict[str, int] = {}  # folder (real path) -> the open lock file this process holds


def hold(out: str) -> bool:
    """Hold ``out``'s lock for the rest of this process (an ``flock``: the kernel drops it when the process dies, so a
    stale lock, its pid no longer alive, is taken over); False when another process holds it."""
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as e:  # a folder the checks let through but the system refuses (/proc, a read-only mount)
        raise InputError(f"--out: cannot write to {out!r} ({e.strerror})") from None
    key = os.path.realpath(out)
    if key in _locks:
        return True
    fd = os.open(os.path.join(out, LOCK), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return False
    except OSError as e:
        os.close(fd)
        raise InputError(f"--out {out!r}: cannot lock {LOCK} ({e.strerror or e}); choose a folder on a file system "
                         "with locks") from None
    os.ftruncate(fd, 0)
    os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode())
    _locks[key] = fd
    return True


def holder(out: str) -> str:
    """Who holds ``out``'s lock, as its file says."""
    try:
        with open(os.path.join(out, LOCK)) as f:
            return f.read().strip() or "pid not yet written"
    except OSError as e:
        return f"its {LOCK} unreadable: {e.strerror or e}"
