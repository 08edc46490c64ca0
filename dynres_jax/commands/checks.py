"""One path for checking a command's input before its work: argparse types that say what they accept, the parser
whose mistakes are one line (``guard.guarded`` ends a command's errors the same way), and the output folder's record.

Every command's ``--out`` folder holds ``run.json``: the command and the settings that made it. A rerun with the same
settings resumes (or rewrites the same results); other settings are refused with what differs, unless ``--fresh``
asks to delete what the earlier runs wrote (``run.files`` lists it; a user's own file stays); a folder of another
command, a non-empty folder this package did not make, or one another run holds (``run.lock``) is refused.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import tempfile

from dynres_jax import distributed
from dynres_jax.commands import docstring, guard
from dynres_jax.commands.flags import OneLineParser, prog  # noqa: F401 (prog: the commands' import of it)
from dynres_jax.commands.folder_lock import LOCK, hold, holder
from dynres_jax.commands.guard import guarded  # noqa: F401 (the commands' decorator: checks.guarded)
from dynres_jax.config import OMEGA_MAX, OMEGA_MIN
from dynres_jax.errors import InputError
from dynres_jax.io import files
from dynres_jax.sim import engines

RUN = guard.RUN


class Parser(OneLineParser):
    """A command's parser: a mistake is one line (``PROG: error: ...`` and where the options are), exit status 2; the
    ``--out`` it parsed is kept for ``guarded``'s line on an interrupt."""

    def parse_known_args(self, args=None, namespace=None):
        parsed, rest = super().parse_known_args(args, namespace)
        if getattr(parsed, "out", None) is not None:
            guard.running["out"] = parsed.out
        return parsed, rest


def parser(name: str, doc: str | None) -> Parser:
    """The parser of command ``name`` (its module docstring as the description; read from the calling module's source
    when ``python -OO`` stripped it, ``commands.docstring``)."""
    if doc is None:
        doc = docstring(sys._getframe(1).f_globals.get("__name__", ""))
    return Parser(prog=prog(name), description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)


# argparse types: a bad value is reported by argparse as "argument --FLAG: <message>", exit status 2.

def count(low: int = 1, high: int | None = None):
    """A whole number in [low, high]."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected a whole number in [{low}, {'∞' if high is None else high}], "
                                             f"got {value}")
        return value

    parse.__name__ = "count"  # argparse names the type in "invalid count value"
    return parse


def number(low: float = -math.inf, high: float = math.inf, *, above: bool = False):
    """A finite number in [low, high] (``above``: strictly greater than low)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(value) or value < low or value > high or (above and value == low):
            bounded = math.isfinite(low) or math.isfinite(high)
            bounds = f" in {'(' if above else '['}{low:g}, {high:g}]" if bounded else ""
            raise argparse.ArgumentTypeError(f"expected a finite number{bounds}, got {text}")
        return value

    parse.__name__ = "number"
    return parse


def stop_share(text: str) -> float | str:
    """A stop share in (0, 1], or "off" (no stop rule, where the task has one by default): ``stop_rule`` reads it."""
    if text.strip().lower() == "off":
        return "off"
    try:
        return number(0, 1, above=True)(text)
    except argparse.ArgumentTypeError as e:
        raise argparse.ArgumentTypeError(f"{e}; or 'off' for no stop rule") from None


def stop_rule(value: float | str | None) -> float | None:
    """--stop-share's parsed value as ``MPCConfig.stop_share``: "off" -> None (no rule)."""
    return None if value == "off" else value


seed = count(0, 2**32 - 1)  # NumPy's and JAX's seeds are unsigned 32-bit words
positive = number(0.0, above=True)
omega = count(OMEGA_MIN, OMEGA_MAX)
# Upper bounds from sense, checked before any work: past them a run fails by memory or time, not by a message.
samples = count(1, 2**16)  # action sequences optimised at once: 2^16 x 100 particles is 6.5 M particles a step
adam_steps = count(1, 100_000)  # Adam steps a plan
time_budget = number(0.0, 3600.0, above=True)  # seconds a decision
lr = number(0.0, 1.0, above=True)  # an Adam step: metres for the planner, a learning rate for training


def text(value: str) -> str:
    """Characters OpenCV's Hershey fonts draw (printable ASCII), not only spaces."""
    bad = sorted({c for c in value if not " " <= c <= "~"})
    if not value.strip() or bad:
        raise argparse.ArgumentTypeError(f"expected printable ASCII characters (OpenCV's fonts draw no others), got "
                                         f"{value!r}")
    return value


def out_file(text: str, suffixes: tuple[str, ...], beside: str = "", flag: str = "--out",
             inputs: dict | None = None) -> str:
    """An output file path given as ``flag``: not a folder, ending in one of ``suffixes``, a name the file system
    takes (with ``beside``, the suffix of a second file written next to it, e.g. ".json"), in a folder that exists
    and is writable or can be made (``_check_can_create``), and none of the command's ``inputs`` ({flag: path or
    None}: writing there would destroy it)."""
    for name, path in (inputs or {}).items():
        if path is not None and os.path.realpath(path) in {os.path.realpath(text), os.path.realpath(text + beside)}:
            raise InputError(f"{flag} {text!r} is the command's input {name}; writing there would destroy it: give "
                             "another file name")
    if os.path.isdir(text) or text.endswith(os.sep):
        raise InputError(f"{flag} {text!r} is a folder; give a file name ending in {' or '.join(suffixes)}")
    if not text.lower().endswith(suffixes):
        raise InputError(f"{flag} {text!r}: give a file name ending in {' or '.join(suffixes)}")
    _check_can_create(os.path.dirname(os.path.abspath(text)), flag)
    _check_name_length(os.path.abspath(text) + beside, flag)
    return text


def _check_name_length(path: str, flag: str = "--out") -> None:
    """InputError naming ``flag`` when a part of ``path`` is longer than its file system takes (NAME_MAX bytes)."""
    try:
        limit = os.pathconf(_nearest_existing(os.path.dirname(path)), "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    for part in path.split(os.sep):
        if len(os.fsencode(part)) > limit:
            raise InputError(f"{flag}: the name {part[:24]!r}... is {len(os.fsencode(part))} bytes; this file system "
                             f"takes at most {limit}")


def quick_sets(parser: argparse.ArgumentParser, args: argparse.Namespace, names) -> None:
    """parser.error when a flag --quick sets itself (``names``, dest names) was also given another value."""
    given = [n for n in names if getattr(args, n) != parser.get_default(n)]
    if args.quick and given:
        parser.error(f"--quick sets {', '.join('--' + n.replace('_', '-') for n in given)} itself; give them without "
                     "--quick, or --quick alone")


WORKERS_PER_CORE = 4  # --workers above this many C engine processes a host core is refused (each holds a MuJoCo)


def workers(lowest: int = 1):
    """--workers / --cpu-workers: a whole number of C engine processes in [lowest, 4 x this host's cores]."""
    cores = os.cpu_count() or 1
    top = WORKERS_PER_CORE * cores
    whole = count(lowest)

    def parse(text: str) -> int:
        value = whole(text)
        if value > top:
            raise argparse.ArgumentTypeError(f"{value} processes on this host's {cores} core(s): at most {top} "
                                             f"({WORKERS_PER_CORE} a core)")
        return value

    return parse


def check_workers(parser: argparse.ArgumentParser, workers: int | None, backend: str) -> None:
    """parser.error where --workers was given for an engine without worker processes (it would do nothing)."""
    if workers is not None and not engines.uses_workers(backend):
        parser.error(f"--workers {workers}: the engine {backend!r} runs no worker processes (only --backend mujoco "
                     "does)")


def add_engine(parser: argparse.ArgumentParser, default: str = "mujoco") -> None:
    """--backend, its choices the engine table's (``sim.engines.NAMES``)."""
    parser.add_argument("--backend", default=default, choices=engines.NAMES, help=engines.help_text(default))


def engine(parser: argparse.ArgumentParser, name: str) -> str:
    """The engine ``name`` made concrete (``engines.resolve``); parser.error naming a missing extra."""
    try:
        return engines.resolve(name)
    except InputError as e:
        parser.error(f"--backend: {e}")


# The output folder's record.

def add_fresh(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--fresh", action="store_true",
                        help="delete the files an earlier run of this command with other settings wrote in --out "
                             "(yours stay), and start afresh (default: a rerun resumes with the same settings, other "
                             "ones are refused)")


def settings(args: argparse.Namespace, ignore=()) -> dict:
    """The settings of a run worth recording: every argument but where it writes, how many processes it uses, its
    progress display and ``ignore`` (settings a resumed run may change)."""
    skip = {"out", "fresh", "workers", "cpu_workers", "quiet", "no_progress", "coordinator", "num_processes",
            "process_id", *ignore}
    return {k: v for k, v in sorted(vars(args).items()) if k not in skip}


def claim(out: str, command: str, config: dict, fresh: bool = False, inputs: dict | None = None) -> bool:
    """Make ``out`` this run's folder before any work; True when it resumes an earlier run of the same settings and
    inputs. ``inputs``: the files and folders the run reads, {flag: path, a list of paths, or None}; run.json keeps
    each one's SHA-256 (``digest``). InputError naming --out when it cannot be written, another run holds its lock
    (``LOCK``), it holds another command's run, a non-empty folder this package did not make, or a run of other
    settings or whose inputs changed since, naming the first (unless ``fresh``: then what the earlier runs listed as
    their own is deleted, ``files.remove_owned``; a user's file stays). From here on every file the run writes in
    ``out`` is listed (``files.own``). In a job, every process checks before process 0 writes anything, so all see the
    same folder and refuse it together; process 0 holds the lock."""
    hashes = check_out(out, command, config, fresh, inputs)  # a refusal creates nothing, not even the lock
    if not distributed.agree(hold(out) if distributed.is_writer() else True):
        raise InputError(f"--out {out!r} is in use by another run ({holder(out)}); wait for it to end or choose "
                         "another folder")
    earlier, afresh = _earlier(out, command, config, hashes, fresh)  # again, under the lock
    distributed.barrier(f"claim checked {os.path.abspath(out)}")
    if distributed.is_writer():
        try:
            files.check_writable(out)
        except OSError as e:
            raise InputError(f"--out: {e}") from None
        if afresh:
            files.remove_owned(out, keep=(RUN,))
        elif earlier is None:
            files.write_text(os.path.join(out, files.OWN), "")
        files.write_json(os.path.join(out, RUN), dict(command=command, config=config, inputs=hashes))
    distributed.barrier(f"claim written {os.path.abspath(out)}")
    files.own(out)
    return earlier is not None


def check_out(out: str, command: str, config: dict, fresh: bool = False, inputs: dict | None = None) -> dict:
    """``claim``'s refusals of ``out``, writing nothing, so that a command can give them before its slow set-up (a
    scene built); the inputs' hashes as run.json keeps them."""
    if os.path.exists(out) and not os.path.isdir(out):
        raise InputError(f"--out {out!r} is a file, not a folder")
    _check_can_create(out)
    _check_name_length(os.path.abspath(os.path.join(out, RUN)))
    if os.path.isdir(out) and not os.path.isfile(os.path.join(out, RUN)) and set(os.listdir(out)) - {LOCK}:
        raise InputError(f"--out {out!r} is not empty and holds no {RUN} (it was not made by a dynres command); "
                         "choose a new or empty folder")
    hashes = {flag: [[path, digest(path, flag)] for path in ([paths] if isinstance(paths, str) else paths)]
              for flag, paths in sorted((inputs or {}).items()) if paths is not None}
    _earlier(out, command, config, hashes, fresh)
    return hashes


def _earlier(out: str, command: str, config: dict, hashes: dict, fresh: bool) -> tuple[dict | None, bool]:
    """(the earlier run's record to resume, or None; whether --fresh starts it afresh) of ``out``'s run.json;
    InputError for another command's run, a damaged record, or other settings or changed inputs without ``fresh``."""
    record = os.path.join(out, RUN)
    if not os.path.isfile(record):
        return None, False
    now = json.loads(json.dumps(config))
    try:
        with open(record) as f:
            earlier = json.load(f)
        earlier_command = earlier["command"]  # a flag added since, at its default None, is what the earlier run did:
        earlier_config = {**{k: None for k, v in now.items() if v is None}, **earlier["config"]}
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"--out {out!r}: its {RUN} is damaged ({type(e).__name__}); choose another folder") from None
    if earlier_command != command:
        raise InputError(f"--out {out!r} holds a {earlier_command} run; choose another folder for {command}")
    if earlier_config != now:
        why = f"of other settings ({_differences(earlier_config, config)}); rerun with its settings to resume"
    else:
        why = _changed(earlier.get("inputs"), hashes)
    if not why:
        return earlier, False
    if not fresh:
        raise InputError(f"--out {out!r} holds a {command} run {why}, choose another --out, or pass --fresh to start "
                         "it afresh")
    if not os.path.isfile(os.path.join(out, files.OWN)):
        raise InputError(f"--out {out!r}: its run lists no files of its own (no {files.OWN}: it began before dynres "
                         "listed them), so --fresh cannot tell them from yours; delete them yourself or choose another "
                         "folder")
    files.owned(out)  # a damaged list refused before anything is deleted
    return None, True


def digest(path: str, flag: str) -> str | None:
    """SHA-256 of a file's bytes, or of a folder's files (each path in it with its bytes' hash; a lock and temporary
    files left out), or None when ``path`` does not exist; InputError naming ``flag`` when it cannot be read or is
    neither a file nor a folder (a FIFO, a device: ``files.kind``)."""
    kind = files.kind(path)
    if kind == "missing":
        return None
    if kind not in ("file", "folder"):  # a FIFO or a device would block or read nothing
        raise InputError(f"{flag} {path!r} is {kind}, not a file or folder")
    try:
        if kind == "file":
            with open(path, "rb") as f:
                return hashlib.file_digest(f, "sha256").hexdigest()
        found = {}
        for root, folders, names in os.walk(path):
            folders.sort()
            for name in names:
                if name != LOCK and not name.startswith(files.TMP_PREFIX):
                    found[os.path.relpath(os.path.join(root, name), path)] = digest(os.path.join(root, name), flag)
        return hashlib.sha256(json.dumps(found, sort_keys=True).encode()).hexdigest()
    except OSError as e:
        raise InputError(f"{flag} {path!r} cannot be read ({e.strerror or e})") from None


def _changed(earlier: dict | None, now: dict) -> str:
    """Why a run whose inputs had the hashes ``earlier`` cannot resume with ``now`` ("" when they are the same)."""
    if earlier is None:
        return "" if not now else ("that recorded no hashes of its inputs (it began before dynres recorded them), so a "
                                   "resume cannot prove them the same")
    for flag in sorted(set(earlier) | set(now)):
        for path, sha in now.get(flag, []):
            if [path, sha] not in earlier.get(flag, []):
                return f"whose input {flag} {path!r} changed since it began (its SHA-256 differs); restore it to resume"
    return "" if earlier == now else "of other inputs; rerun with its inputs to resume"


def _nearest_existing(path: str) -> str:
    """``path`` made absolute, or the nearest folder above it that exists."""
    folder = os.path.abspath(path)
    while not os.path.exists(folder):
        folder = os.path.dirname(folder)
    return folder


def _check_can_create(path: str, flag: str = "--out") -> None:
    """InputError naming ``flag`` unless ``path`` exists as a writable folder, or the nearest folder above it that
    exists is writable, takes a new folder (one is made and removed at once: /proc refuses even root) and no file or
    dangling symbolic link stands in the way."""
    target = os.path.normpath(os.path.abspath(path))  # "run/" is "run"
    folder = target
    while not os.path.exists(folder):
        if os.path.islink(folder):
            raise InputError(f"{flag} {path!r}: {folder!r} is a symbolic link to {os.readlink(folder)!r}, which does "
                             f"not exist: make that folder or give another {flag}")
        folder = os.path.dirname(folder)
    if not os.path.isdir(folder) or not os.access(folder, os.W_OK):
        why = "a file" if os.path.isfile(folder) else "not writable"
        raise InputError(f"{flag}: cannot write to {path!r} ({folder!r} is {why})")
    if folder != target:  # folders to make: try one
        try:
            os.rmdir(tempfile.mkdtemp(prefix=".dynres-probe-", dir=folder))
        except OSError as e:
            raise InputError(f"{flag}: cannot make {path!r} ({folder!r} takes no new folder: "
                             f"{e.strerror or e})") from None


def _differences(earlier: dict, now: dict) -> str:
    now = json.loads(json.dumps(now))
    keys = sorted(set(earlier) | set(now), key=lambda k: (k not in now, k))
    return "; ".join(f"--{k.replace('_', '-')} {earlier.get(k, 'unset')} there, {now.get(k, 'unset')} here"
                     for k in keys if earlier.get(k) != now.get(k))
