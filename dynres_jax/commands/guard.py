"""How a command ends: ``guarded``, the decorator of every command's ``main``. A user's mistake found at any point is
one line with exit status 2; Ctrl-C and SIGTERM one line saying what was kept and how to resume; a full disk, a
closed pipe and a JAX platform that cannot start each one line too; never a traceback for any of these. And the
persistent compilation cache every command uses (``use_compilation_cache``)."""

from __future__ import annotations

import atexit
import errno
import functools
import os
import signal
import sys
import threading
import time
import traceback

import jax

from dynres_jax.commands.flags import prog
from dynres_jax.errors import InputError, JobError

RUN = "run.json"  # the output folder's record (``checks.claim``): a folder that has one holds finished work
running: dict[str, str | None] = {"out": None}  # the --out of the command running here (``checks.Parser`` sets it)


def kept(what: str) -> None:
    """Say what the running command has saved so far (e.g. "steps 1-3 of 20"), for the line an interrupt ends with;
    "" for nothing yet (its --out holds only its settings)."""
    running["kept"] = what


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the command is, so it unwinds as Ctrl-C does."""


_signalled: list[int] = []  # the signal a command is ending on, until guarded's except clause takes it (then cleared)
EXIT_GRACE = 20.0  # s: a command run as a program that has not exited this long after a signal exits anyway


def _on_signal(signum, frame):
    """SIGINT and SIGTERM: raise where the command is. Python drops an exception raised inside a garbage-collection
    callback or a ``__del__`` (JAX's ``_xla_gc_callback`` swallowed one once, and the command ran on), so the first
    signal also starts a thread that sends it again every second until ``guarded`` has caught it."""
    if isinstance(sys.exc_info()[1], KeyboardInterrupt):
        return  # one is being handled already (guarded's except clause): a resent signal adds nothing
    if not _signalled:
        _signalled.append(signum)
        threading.Thread(target=_resend, args=(signum,), daemon=True).start()
        if running.get("program") and not running.get("deadline"):
            running["deadline"] = True
            threading.Thread(target=_exit_at_deadline, args=(signum,), daemon=True).start()
    raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt


def _exit_at_deadline(signum: int) -> None:
    """EXIT_GRACE after the first signal, end a program still running: a clean-up that waits on a lock a killed
    worker held (a process pool shut down mid-compile) or on a worker that never answers would hang it for good.
    Finished work is on disk already (every file is written whole, atomically); the line says so unless said."""
    time.sleep(EXIT_GRACE)
    try:  # to the file descriptor: the stream's lock may be held by the stuck main thread
        os.write(2, ("" if running.get("said") else _interrupted(running["name"]) + "\n").encode())
    except OSError:
        pass
    os._exit(143 if signum == signal.SIGTERM else 130)


def _quiet_unraisable(unraisable) -> None:
    """``sys.unraisablehook`` while a command runs: the signal's exception Python drops inside a garbage-collection
    callback or a ``__del__`` is not printed ("Exception ignored in: <function _xla_gc_callback>", a traceback, then
    the one line): the signal is sent again until it ends the command (``_resend``). Anything else as Python has it."""
    if not isinstance(unraisable.exc_value, KeyboardInterrupt):
        sys.__unraisablehook__(unraisable)


def _resend(signum: int) -> None:
    while True:
        time.sleep(1.0)
        if not _signalled:
            return
        os.kill(os.getpid(), signum)


def span(what: str, done: int, total: int) -> str:
    """Finished items in words for ``kept``: "the episode's step 1 of 20", "the episode's steps 1-3 of 20"."""
    return f"{what} 1 of {total}" if done == 1 else f"{what}s 1-{done} of {total}"


def _kept() -> str:
    """What the ended command kept, for its last line ("" when its --out holds no finished work)."""
    out, what = running["out"], running.get("kept")
    if not out or not os.path.isfile(os.path.join(out, RUN)) or what == "":
        return ""
    return f"finished work is kept in {out}{f' ({what})' if what else ''}; "


def _interrupted(name: str) -> str:
    """The line an interrupted command ends with: what it kept and how to go on."""
    if _kept():
        return f"{prog(name)}: interrupted; {_kept()}rerun the same command to resume"
    return f"{prog(name)}: interrupted before any work was kept; rerun the same command to start again"


def _ignore_signals() -> None:
    """At exit, once a command has ended: Ctrl-C and SIGTERM have nothing left to stop, and one arriving while JAX's
    own exit hook clears its caches printed 'Exception ignored in atexit callback' and a traceback."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, signal.SIG_IGN)


def guarded(name: str):
    """Decorator of a command's ``main(argv)``: an ``InputError`` raised anywhere in it (a damaged file found while
    reading, a folder of another run) is printed as one line naming the input, exit status 2, as argparse does; a
    ``JobError`` (a peer that never joined) the same way with status 1, as is a full disk (what was kept, how to
    resume), whatever library wrapped its OSError; a JAX platform that cannot start
    (``JAX_PLATFORMS`` naming a missing or unknown one) the same way with status 2; a closed standard output
    (``| head``) ends the command quietly, as Unix tools do, status 1; SIGINT (Ctrl-C) and SIGTERM end it with one
    line saying what was kept and how to resume, status 130 and 143 as a shell reports those signals."""

    def wrap(main):
        @functools.wraps(main)
        def run(argv=None):
            running.update(out=None, kept=None, name=name, said=False, deadline=False, stdout_failed=False,
                           program=argv is None)  # run as a program (its own process), not called by a test
            for stream in (sys.stdout, sys.stderr):  # "ω" on an ASCII terminal (PYTHONIOENCODING=ascii): \u03c9
                if hasattr(stream, "reconfigure"):
                    stream.reconfigure(errors="backslashreplace")
            jax.config.update("jax_enable_x64", False)  # float32 whatever JAX_ENABLE_X64 says: resumes, checkpoints
            # and exported files keep one precision
            use_compilation_cache()
            in_main = threading.current_thread() is threading.main_thread()  # signal handlers are set only there
            if in_main:  # after JAX's exit hook is registered (on import), so it runs first (last in, first out)
                atexit.unregister(_ignore_signals)
                atexit.register(_ignore_signals)
            # SIGINT only where Python's own handler is set: an ignored one (a shell's background job) stays ignored
            ours = [signal.SIGTERM] + ([signal.SIGINT] if signal.getsignal(signal.SIGINT)
                                       is signal.default_int_handler else [])
            previous = {s: signal.signal(s, _on_signal) for s in ours} if in_main else {}
            unraisable, sys.unraisablehook = sys.unraisablehook, _quiet_unraisable
            stdout, sys.stdout = sys.stdout, _Watched(sys.stdout)
            try:
                return main(argv)
            except KeyboardInterrupt as e:
                _signalled.clear()  # stops _resend
                for s in previous:  # a second Ctrl-C while the line prints is ignored
                    signal.signal(s, signal.SIG_IGN)
                print(("\n" if sys.stderr.isatty() else "") + _interrupted(name), file=sys.stderr)  # past a bar
                running["said"] = True
                raise SystemExit(143 if isinstance(e, Terminated) else 130) from None
            except (InputError, JobError) as e:
                print(f"{prog(name)}: error: {' '.join(str(e).split())}", file=sys.stderr)
                raise SystemExit(2 if isinstance(e, InputError) else 1) from None
            except BrokenPipeError:
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
                raise SystemExit(1) from None
            except Exception as e:
                if _platform_failed(e):
                    why = str(e).splitlines()[0] if str(e) else ("JAX cannot start that platform here (no plugin or "
                                                                 "device)")
                    print(f"{prog(name)}: error: JAX_PLATFORMS={os.environ.get('JAX_PLATFORMS', '')!r}: {why}",
                          file=sys.stderr)
                    raise SystemExit(2) from None
                if isinstance(e, OSError) and running["stdout_failed"]:  # stdout, not a file
                    print(f"{prog(name)}: error: cannot write to standard output ({e.strerror or e}); the command's "
                          "files are written", file=sys.stderr)
                    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
                    raise SystemExit(1) from None
                full = _disk_full(e)
                if full is None:
                    raise
                remedy = "raise the file-size limit (ulimit -f)" if full.errno == errno.EFBIG else "free space"
                print(f"{prog(name)}: error: {full.strerror or 'no space left'}"
                      f"{f' writing {full.filename!r}' if full.filename else ''}; {_kept()}{remedy} and rerun the "
                      "same command", file=sys.stderr)
                raise SystemExit(1) from None
            finally:
                sys.unraisablehook, sys.stdout = unraisable, stdout
                _signalled.clear()
                for s, handler in previous.items():  # None: a handler set outside Python
                    signal.signal(s, handler if handler is not None else signal.SIG_DFL)

        return run

    return wrap


class _Watched:
    """sys.stdout while a command runs: the stream itself, except that a write or flush that fails says so
    (``running["stdout_failed"]``), so an OSError from standard output (/dev/full, a full disk behind a redirection)
    is told apart from one writing a file."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text):
        return self._watched(self._stream.write, text)

    def flush(self):
        return self._watched(self._stream.flush)

    def _watched(self, call, *args):
        try:
            return call(*args)
        except OSError:
            running["stdout_failed"] = True
            raise

    def __getattr__(self, name):
        return getattr(self._stream, name)


def compilation_cache_dir() -> str | None:
    """Where commands keep compiled programs between runs: JAX_COMPILATION_CACHE_DIR if set, else
    $XDG_CACHE_HOME/dynres-jax/jax (~/.cache/...); None with DYNRES_JAX_CACHE=off."""
    if os.environ.get("DYNRES_JAX_CACHE", "").lower() == "off":
        return None
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return os.environ["JAX_COMPILATION_CACHE_DIR"]
    home = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(home, "dynres-jax", "jax")


def use_compilation_cache() -> None:
    """JAX's persistent compilation cache in ``compilation_cache_dir()``: a rerun, a resume after Ctrl-C and the main
    job's second run load what the first compiled (on a 2-core CPU compiling is most of a short run) instead of
    compiling again. A loaded program is the one the compiler wrote, so results do not change. Programs that compiled
    in under a second are not kept; the folder is the user's to delete. A folder that cannot be made leaves the cache
    off, said in one line."""
    folder = compilation_cache_dir()
    if folder is None or jax.config.jax_compilation_cache_dir == folder:
        return
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as e:
        print(f"note: no compilation cache ({folder!r}: {e.strerror or e}); every run compiles afresh "
              "(DYNRES_JAX_CACHE=off silences this)", file=sys.stderr)
        return
    jax.config.update("jax_compilation_cache_dir", folder)  # no size limit: JAX's eviction needs the filelock
    # package, and without it the cache reads nothing back


def _disk_full(e: BaseException) -> OSError | None:
    """The OSError of a full disk, a quota or a file-size limit (ENOSPC, EDQUOT, EFBIG: ``ulimit -f``) in ``e``'s chain
    of causes (a library may wrap it)."""
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
            return e
        e = e.__cause__ or e.__context__
    return None


def _platform_failed(e: BaseException) -> bool:
    """Whether ``e`` is JAX failing to start the platforms JAX_PLATFORMS names: its "Unable to initialize backend", or
    the bare assertion its backend setup raises for a platform without a plugin (``JAX_PLATFORMS=cuda`` on a CPU)."""
    if not isinstance(e, RuntimeError | AssertionError):
        return False
    if "Unable to initialize backend" in str(e):
        return True
    if not isinstance(e, AssertionError) or not os.environ.get("JAX_PLATFORMS"):
        return False
    frames = traceback.extract_tb(e.__traceback__)
    if frames and frames[-1].filename.endswith("xla_bridge.py"):
        return True
    try:  # raised inside a jitted function, JAX's traceback filtering hid the frame: ask JAX once more
        jax.devices()
    except (RuntimeError, AssertionError):
        return True
    return False
