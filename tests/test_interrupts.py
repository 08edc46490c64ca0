"""Ctrl-C and SIGTERM end a command with one line saying what was kept and how to resume, never a traceback."""

import os
import signal
import subprocess
import sys
import time

import pytest


def _default_sigint():
    """In the child before it starts: SIGINT's default action. A child inherits an ignored SIGINT (as an xdist
    worker's may have it), and Python then installs no KeyboardInterrupt handler (a shell's background job)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.parametrize("signum, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_an_interrupted_command_ends_with_one_line_and_the_signals_status(tmp_path, signum, status):
    out = tmp_path / "sim"
    run = subprocess.Popen([sys.executable, "-m", "experiments.simulate", "--pieces", "20", "--pushes", "10000",
                            "--image-size", "32", "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True, env=dict(os.environ, JAX_PLATFORMS="cpu", PYTHONFAULTHANDLER="1"),
                           preexec_fn=_default_sigint)
    deadline = time.monotonic() + 120
    while not (out / "run.json").exists() and run.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert run.poll() is None, run.communicate()
    time.sleep(1.0)  # into the pushes
    run.send_signal(signum)  # Python runs the handler between bytecodes: after a compile in progress, which on a loaded
    try:  # 2-core CI machine took over 60 s once (idle: the command ends in < 1 s)
        _, err = run.communicate(timeout=180)
    except subprocess.TimeoutExpired:  # where it hangs: SIGABRT makes faulthandler print every thread's stack
        run.send_signal(signal.SIGABRT)
        pytest.fail(f"no exit 180 s after the signal; its stacks:\n{run.communicate()[1][-6000:]}")
    assert run.returncode == status, err
    assert "Traceback" not in err, err
    said = [line for line in err.splitlines() if ": interrupted" in line]  # the test's folder says it too
    assert said == [f"python -m experiments.simulate: interrupted; finished work is kept in {out}; rerun the same "
                    "command to resume"], err


def test_a_signal_python_drops_inside_a_destructor_still_ends_the_command(capsys):
    """Python ignores an exception raised in a ``__del__`` or a garbage-collection callback ("Exception ignored in",
    as JAX's ``_xla_gc_callback`` did on CI and the command ran on for minutes): the signal is sent again until the
    command has ended on it."""
    from dynres_jax.commands import checks, guard

    class SignalsInItsDestructor:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):  # the handler runs here, between bytecodes, and its exception is dropped
                time.sleep(0.001)

    laps = []

    @checks.guarded("simulate")
    def main(argv):
        SignalsInItsDestructor()  # deleted at once: its __del__ runs the handler
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            laps.append(time.monotonic())
            time.sleep(0.01)
        return 0

    with pytest.raises(SystemExit) as ended:
        main([])
    assert ended.value.code == 143
    assert laps and laps[-1] - laps[0] < 5  # ended by the resent signal, not by running to its end
    err = capsys.readouterr().err
    assert "interrupted" in err
    assert "Exception ignored" not in err and "Traceback" not in err, err  # the dropped one is not printed either
    assert signal.getsignal(signal.SIGTERM) is not guard._on_signal  # the handler is given back


def test_commands_keep_compiled_programs_between_runs(tmp_path):
    """guarded turns on JAX's persistent compilation cache under $XDG_CACHE_HOME/dynres-jax/jax (a rerun or a resume
    loads what the first run compiled); DYNRES_JAX_CACHE=off turns it off; a folder that cannot be made is one note."""
    probe = ("from dynres_jax.commands import guard\n"
             "guard.use_compilation_cache()\n"
             "import jax, jax.numpy as jnp\n"
             "print(jax.config.jax_compilation_cache_dir)\n"
             "jax.jit(lambda x: jnp.sin(x) * 2)(jnp.ones(3)).block_until_ready()\n")
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env.update(JAX_PLATFORMS="cpu", JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", XDG_CACHE_HOME=str(tmp_path))

    def run(**more):
        done = subprocess.run([sys.executable, "-c", probe], env=dict(env, **more), capture_output=True, text=True,
                              timeout=300)
        assert done.returncode == 0, done.stderr
        return done

    folder = tmp_path / "dynres-jax" / "jax"
    first = run()
    assert first.stdout.strip() == str(folder) and "compilation cache" not in first.stderr, first.stderr
    kept = sorted(folder.iterdir())
    assert kept  # the program is kept
    again = run()  # read back: no warning (JAX's eviction without filelock read nothing), nothing new written
    assert "compilation cache" not in again.stderr and sorted(folder.iterdir()) == kept, again.stderr
    assert run(DYNRES_JAX_CACHE="off", XDG_CACHE_HOME=str(tmp_path / "other")).stdout.strip() == "None"
    (tmp_path / "a_file").write_text("")
    blocked = run(XDG_CACHE_HOME=str(tmp_path / "a_file"))
    assert blocked.stdout.strip() == "None" and "no compilation cache" in blocked.stderr


def test_at_a_terminal_a_command_says_it_is_starting_before_its_imports(tmp_path):
    """The seconds JAX and MuJoCo take to import are not silent at a terminal: the first line comes before them
    (a pipe, as in logs and the tests' other runs, gets no such line)."""
    import pty

    leader, follower = pty.openpty()
    run = subprocess.Popen([sys.executable, "-X", "importtime", "-m", "experiments.goal", "--disc", "0", "0", "0.05",
                            "--out", str(tmp_path / "g.png")], stdout=subprocess.PIPE, stderr=follower,
                           env=dict(os.environ, JAX_PLATFORMS="cpu"))
    os.close(follower)
    said = b""
    while True:
        try:
            chunk = os.read(leader, 65536)
        except OSError:  # the child closed the terminal
            break
        if not chunk:
            break
        said += chunk
    assert run.wait(timeout=300) == 0
    lines = said.decode().splitlines()
    start = next(i for i, line in enumerate(lines) if "experiments.goal: starting" in line)
    first_jax = next(i for i, line in enumerate(lines) if line.split("|")[-1].strip() == "jax")
    assert start < first_jax  # said before JAX was imported


def test_a_signal_during_exit_after_the_command_ended_prints_nothing():
    """A Ctrl-C that arrives while the interpreter runs its exit hooks (JAX's clears its caches, seconds on a loaded
    machine) had nothing to stop but printed 'Exception ignored in atexit callback' and a traceback: once a command
    has ended, its exit ignores the signals. The probe's own hook stands in for JAX's (registered before guarded)."""
    probe = ("import atexit, os, signal, time\n"
             "def jax_like_clean_up():\n"
             "    os.kill(os.getpid(), signal.SIGINT)\n"
             "    time.sleep(0.5)\n"
             "    print('exit hook done', flush=True)\n"
             "atexit.register(jax_like_clean_up)\n"
             "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
             "from dynres_jax.commands import guard\n"
             "guard.guarded('simulate')(lambda argv: 0)([])\n")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, JAX_PLATFORMS="cpu"))
    assert done.returncode == 0 and "exit hook done" in done.stdout, done.stderr
    assert "Traceback" not in done.stderr and "Exception ignored" not in done.stderr, done.stderr


def test_the_interrupt_line_says_what_was_kept_and_nothing_when_nothing_was(tmp_path, monkeypatch):
    """A task command claims its --out (run.json) before its first step: interrupted then, it says no work was kept;
    after a step it names the steps kept."""
    from dynres_jax.commands import guard

    (tmp_path / guard.RUN).write_text("{}")
    monkeypatch.setitem(guard.running, "out", str(tmp_path))
    monkeypatch.setitem(guard.running, "kept", None)  # given back as it was after the test
    guard.kept("")
    assert guard._interrupted("gather") == ("python -m experiments.gather: interrupted before any work was kept; "
                                            "rerun the same command to start again")
    guard.kept(guard.span("the episode's step", 1, 6))
    assert guard._interrupted("gather").endswith(f"kept in {tmp_path} (the episode's step 1 of 6); rerun the same "
                                                 "command to resume")
    guard.kept(guard.span("the episode's step", 3, 6))
    assert "(the episode's steps 1-3 of 6)" in guard._interrupted("gather")


def test_a_program_whose_clean_up_hangs_after_a_signal_still_ends(tmp_path):
    """A clean-up that waits forever once the command is ending (a process pool's lock held by a killed worker:
    ``evaluate`` stopped mid-compile hung so) cannot keep a program alive: EXIT_GRACE after the signal it exits with
    the signal's status and the one line. The probe's clean-up hangs inside the exception's handling, where the resent
    signal is ignored; without the deadline it would never end."""
    probe = ("import os, signal, sys, threading, time\n"
             "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
             "from dynres_jax.commands import guard\n"
             "guard.EXIT_GRACE = 2.0\n"
             "stuck = threading.Lock(); stuck.acquire()\n"
             "def main(argv=None):\n"
             "    try:\n"
             "        os.kill(os.getpid(), signal.SIGTERM)\n"
             "        time.sleep(60)\n"
             "    except KeyboardInterrupt:\n"
             "        print('cleaning up', flush=True)\n"
             "        stuck.acquire()  # never given: the resent signal is ignored while one is handled\n"
             "guard.guarded('evaluate')(main)()\n")
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, JAX_PLATFORMS="cpu"))
    assert "cleaning up" in done.stdout, done.stderr  # it did hang in its clean-up
    assert done.returncode == 143, done.stderr
    assert time.monotonic() - t0 < 60
    said = [line for line in done.stderr.splitlines() if ": interrupted" in line]
    assert said == ["python -m experiments.evaluate: interrupted before any work was kept; rerun the same command "
                    "to start again"], done.stderr
    assert "Traceback" not in done.stderr, done.stderr


def test_standard_output_that_takes_nothing_is_named_not_a_full_disk(tmp_path):
    """A command whose record cannot be printed (stdout is /dev/full) says so in one line, status 1, its file written;
    it said "No space left on device; free space and rerun", as if its files had not been written."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full here")
    with open("/dev/full", "w") as full:
        done = subprocess.run([sys.executable, "-m", "experiments.goal", "--disc", "0", "0", "0.08", "--out",
                               str(tmp_path / "g.png")], stdout=full, stderr=subprocess.PIPE, text=True, timeout=300,
                              env=dict(os.environ, JAX_PLATFORMS="cpu"))
    assert done.returncode == 1 and (tmp_path / "g.png").is_file(), done.stderr
    assert done.stderr.strip().splitlines()[-1] == ("python -m experiments.goal: error: cannot write to standard "
                                                    "output (No space left on device); the command's files are "
                                                    "written"), done.stderr
    assert "Traceback" not in done.stderr and "free space" not in done.stderr


def test_an_interrupted_evaluation_names_the_methods_it_kept(tmp_path, monkeypatch):
    """evaluate keeps a method whole (METHOD.json; a job's processes their parts): interrupted in its first, nothing
    was kept (it said "finished work is kept" and a rerun started from step 1); after one, that one."""
    from dynres_jax.commands import evaluate, guard

    (tmp_path / guard.RUN).write_text("{}")
    monkeypatch.setitem(guard.running, "out", str(tmp_path))
    monkeypatch.setitem(guard.running, "kept", None)
    evaluate._say_kept(["50", "100", "adaptive"], ["50", "100", "adaptive"])
    assert "interrupted before any work was kept" in guard._interrupted("evaluate")
    evaluate._say_kept(["50", "100", "adaptive"], ["100", "adaptive"])
    assert f"kept in {tmp_path} (method 50 finished; a rerun goes on with the others)" in guard._interrupted(
        "evaluate")
    evaluate._say_kept(["50", "100", "adaptive"], ["adaptive"])
    assert "(methods 50, 100 finished;" in guard._interrupted("evaluate")


def test_the_console_script_runs_its_command_as_the_program(tmp_path, monkeypatch, capsys):
    """``dynres NAME ...`` (commands.main without arguments: the console script) runs the command as the program, so a
    signal's deadline (EXIT_GRACE) is armed; called with a list (a test, a notebook), it is not."""
    from dynres_jax import commands
    from dynres_jax.commands import guard

    argv = ["goal", "--disc", "0", "0", "0.05", "--out", str(tmp_path / "g.png")]
    monkeypatch.setattr(sys, "argv", ["dynres", *argv])
    commands.main()
    assert guard.running["program"] and (tmp_path / "g.png").is_file()
    commands.main(argv)
    assert not guard.running["program"]


def test_a_file_size_limit_is_one_line_like_a_full_disk(capsys):
    """A write past ``ulimit -f`` (EFBIG) ends a command in one line naming the limit, as a full disk does (a
    20-line traceback before)."""
    import errno

    from dynres_jax.commands import checks

    @checks.guarded("export")
    def main(argv):
        raise OSError(errno.EFBIG, "File too large")

    with pytest.raises(SystemExit) as ended:
        main([])
    err = capsys.readouterr().err
    assert ended.value.code == 1 and "Traceback" not in err
    assert err.strip() == ("python -m experiments.export: error: File too large; raise the file-size limit (ulimit -f) "
                           "and rerun the same command")
