"""Atomic files: every long job writes through these, so a reader (or a resumed run) sees the old file or the whole
new one, never a part. Temporary files start with ``tmp_prefix(path)``; a job may delete leftovers of a killed run.

A command's claimed ``--out`` folder (``own``) lists every path written in it (``OWN``, before the write), so a later
``--fresh`` deletes what the run made and nothing else (``remove_owned``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import stat
import tempfile
from collections.abc import Callable

from dynres_jax.errors import InputError

TMP_PREFIX = ".tmp-"
OWN = "run.files"  # in a claimed folder: the paths its runs wrote, relative to it, one JSON string a line
_owned: dict[str, set[str]] = {}  # this process's claimed folder (absolute) -> the paths its list holds


def kind(path: str) -> str:
    """What stands at ``path`` (symbolic links followed), never opening it: "file", "folder" or "missing", else a
    phrase for a sentence: "a FIFO (named pipe)", "a character device", "a block device", "a socket", "a broken
    symbolic link", "unreadable (REASON)". Reading a FIFO or a device as a file blocks or reads nothing, so input
    paths are checked with this first (``check_input``)."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "a broken symbolic link" if os.path.islink(path) else "missing"
    except OSError as e:
        return f"unreadable ({e.strerror or e})"
    if stat.S_ISREG(mode):
        return "file"
    if stat.S_ISDIR(mode):
        return "folder"
    for test, what in ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return what
    return "not a regular file"


class MissingInput(InputError, FileNotFoundError):
    """An input path where nothing stands."""


def check_input(path: str, what: str, expect: tuple[str, ...] = ("file",)) -> str:
    """``path``'s kind (``kind``) when it is one of ``expect`` ("file", "folder"); else InputError naming ``what`` (a
    flag, or a phrase such as "depth file") and what stands there instead, in one line (``MissingInput``, also a
    FileNotFoundError, when nothing does)."""
    found = kind(path)
    if found in expect:
        return found
    wanted = " or ".join(f"a {e}" for e in expect)
    if found == "missing":
        raise MissingInput(f"{what} {path!r} does not exist")
    named = {"file": "a file", "folder": "a folder"}.get(found, found)
    raise InputError(f"{what} {path!r} is {named}, not {wanted}")


def tmp_prefix(path: str) -> str:
    """How the temporary files of ``path`` begin (in its folder): short whatever the name's length (a 255-byte name
    fits), the same for every write of ``path``, so a job can find a killed write's leftovers."""
    return TMP_PREFIX + hashlib.sha256(os.fsencode(os.path.basename(path))).hexdigest()[:12] + "."


def atomic_write(path: str, write: Callable) -> None:
    """Write ``path`` atomically: ``write(f)`` fills a binary temp file in the same folder, which then replaces
    ``path`` (``os.replace``)."""
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    record(path)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=tmp_prefix(path))
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


def read_json(path: str):
    """The JSON in ``path``, or None when it is missing or unreadable."""
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


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


def own(folder: str) -> None:
    """From now on, list every path this process writes under ``folder`` (its claimed ``--out``) in ``folder/OWN``;
    nothing when ``folder`` has no list (a run begun before lists: ``--fresh`` refuses it, ``remove_owned``)."""
    _owned.clear()
    if os.path.isfile(os.path.join(folder, OWN)):
        _owned[os.path.abspath(folder)] = set(owned(folder))


def owned(folder: str) -> list[str]:
    """The paths ``folder/OWN`` lists (relative to it; a folder recorded whole ends in "/"). InputError naming the
    list when it is unreadable or names a path outside the folder."""
    listing = os.path.join(folder, OWN)
    try:
        with open(listing, encoding="utf-8") as f:
            paths = [json.loads(line) for line in f if line.strip()]
    except (OSError, ValueError) as e:
        raise InputError(f"{listing!r} is unreadable or damaged ({type(e).__name__})") from None
    for rel in paths:
        if not isinstance(rel, str) or os.path.isabs(rel) or os.path.normpath(rel).split(os.sep)[0] in ("..", "."):
            raise InputError(f"{listing!r} names {rel!r}, not a path inside the folder; the list was edited")
    return paths


def record(path: str, whole: bool = False) -> None:
    """List ``path`` (``whole``: a folder, everything in it) as the claimed folder's own, before it is written, so a
    killed write leaves a listed name, never an unlisted file; nothing for a path outside the claimed folder."""
    path = os.path.abspath(path)
    for folder, paths in _owned.items():
        rel = os.path.relpath(path, folder) + (os.sep if whole else "")
        if rel.startswith(os.pardir + os.sep) or rel in paths or rel == OWN:
            continue
        with open(os.path.join(folder, OWN), "a", encoding="utf-8") as f:
            f.write(json.dumps(rel) + "\n")
        paths.add(rel)


def remove_owned(folder: str, keep: tuple[str, ...] = ()) -> None:
    """Delete what ``folder``'s list names but ``keep`` (files with their temporary leftovers, folders recorded
    whole), then the folders this leaves empty, and empty the list: a file the runs did not write stays."""
    parents, paths = set(), []
    for rel in owned(folder):
        if rel in keep:
            continue
        path = os.path.join(folder, rel.rstrip(os.sep))
        if rel.endswith(os.sep) and os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path)
        elif os.path.lexists(path) and not os.path.isdir(path):
            os.unlink(path)
        parents.add(os.path.dirname(path))
        paths.append(path)
    for leftover in leftovers(paths):
        os.unlink(leftover)
    for parent in sorted(parents, key=len, reverse=True):  # deepest first
        while os.path.normpath(parent) != os.path.normpath(folder) and os.path.isdir(parent) and not os.listdir(parent):
            os.rmdir(parent)
            parent = os.path.dirname(parent)
    write_text(os.path.join(folder, OWN), "")


def leftovers(paths) -> list[str]:
    """The temporary files that killed writes of ``paths`` left."""
    starts: dict[str, set[str]] = {}
    for path in paths:
        starts.setdefault(os.path.dirname(os.path.abspath(path)), set()).add(tmp_prefix(path))
    size = len(tmp_prefix(""))
    return [os.path.join(folder, name) for folder, prefixes in starts.items() if os.path.isdir(folder)
            for name in os.listdir(folder) if name[:size] in prefixes]
