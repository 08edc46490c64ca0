"""Atomic files: every long job writes through these, so a reader (or a resumed run) sees the old file or the whole
new one, never a part. Temporary files start with ``TMP_PREFIX``; a job may delete leftovers of a killed run."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable

TMP_PREFIX = ".tmp-"


def atomic_write(path: str, write: Callable) -> None:
    """Write ``path`` atomically: ``write(f)`` fills a binary temp file in the same folder, which then replaces
    ``path`` (``os.replace``)."""
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=TMP_PREFIX + os.path.basename(path) + ".")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def write_json(path: str, obj) -> None:
    atomic_write(path, lambda f: f.write(json.dumps(obj, indent=1, sort_keys=True).encode()))


def write_text(path: str, text: str) -> None:
    atomic_write(path, lambda f: f.write(text.encode()))


def check_writable(folder: str) -> None:
    """Create ``folder`` if needed and check that a file can be written there (an OSError naming it otherwise), so a
    job fails before its work, not after."""
    try:
        os.makedirs(folder, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder, prefix=TMP_PREFIX):
            pass
    except OSError as e:
        raise OSError(f"cannot write to {folder!r}: {e.strerror or e}") from e


def write_image(path: str, image) -> None:
    """Write an image (``cv2.imwrite``: BGR or grey, the format from the extension) atomically; an OSError naming the
    path when OpenCV cannot encode it."""
    import cv2

    ok, data = cv2.imencode(os.path.splitext(path)[1] or ".png", image)
    if not ok:
        raise OSError(f"OpenCV could not encode an image for {path!r}")
    atomic_write(path, lambda f: f.write(data.tobytes()))
