"""An output folder loses no file: --fresh deletes only what the runs listed as their own, a second run on a held
folder is refused in one line while a stale lock is taken over, and an atomic write fits any legal file name."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from dynres_jax.commands import checks, folder_lock
from dynres_jax.errors import InputError
from dynres_jax.io import files

HOLD = """import fcntl, os, sys
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)
fcntl.flock(fd, fcntl.LOCK_EX)
os.write(fd, b"pid %d on here" % os.getpid())
print("held", flush=True)
sys.stdin.read()
"""


def _hold(out: str) -> subprocess.Popen:
    """Another process holding ``out``'s lock until its stdin closes."""
    proc = subprocess.Popen([sys.executable, "-c", HOLD, os.path.join(out, checks.LOCK)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline() == "held\n"
    return proc


def test_fresh_deletes_only_the_runs_files(tmp_path):
    out = str(tmp_path / "run")
    assert not checks.claim(out, "demo", {"a": 1})
    files.write_json(os.path.join(out, "result.json"), {"x": 1})
    files.write_text(os.path.join(out, "parts", "0.json"), "{}")
    files.record(os.path.join(out, "ckpt", "3"), whole=True)  # as ckpt.save does: orbax writes the step's folder
    os.makedirs(os.path.join(out, "ckpt", "3"))
    open(os.path.join(out, "ckpt", "3", "data"), "w").close()
    os.makedirs(os.path.join(out, "ckpt", "best_by_hand"))  # the user's own, beside the steps
    with open(os.path.join(out, "ckpt", "best_by_hand", "weights.txt"), "w") as f:
        f.write("mine")
    killed = files.tmp_prefix(os.path.join(out, "result.json")) + "a1b2"
    open(os.path.join(out, killed), "w").close()
    with open(os.path.join(out, "notes.txt"), "w") as f:  # the user's own
        f.write("mine")
    assert checks.claim(out, "demo", {"a": 1})  # the same settings resume
    with pytest.raises(InputError, match="other settings"):
        checks.claim(out, "demo", {"a": 2})
    assert not checks.claim(out, "demo", {"a": 2}, fresh=True)
    assert sorted(os.listdir(out)) == sorted(["notes.txt", "ckpt", checks.RUN, checks.LOCK, files.OWN])
    assert os.listdir(os.path.join(out, "ckpt")) == ["best_by_hand"]  # the step went, the user's folder stayed
    with open(os.path.join(out, checks.RUN)) as f:
        assert json.load(f)["config"] == {"a": 2}
    files.write_text(os.path.join(out, "result.json"), "new")
    assert files.owned(out) == ["result.json"]  # the new run lists its own from an empty list


def test_fresh_refuses_a_run_without_a_list(tmp_path):
    out = str(tmp_path / "run")
    checks.claim(out, "demo", {"a": 1})
    os.unlink(os.path.join(out, files.OWN))  # a run begun before lists
    with pytest.raises(InputError, match="lists no files of its own"):
        checks.claim(out, "demo", {"a": 2}, fresh=True)
    assert os.path.exists(os.path.join(out, checks.RUN))


def test_a_held_folder_is_refused_in_one_line(tmp_path, capsys):
    out = str(tmp_path / "run")
    os.makedirs(out)
    holder = _hold(out)
    try:
        main = checks.guarded("demo")(lambda argv: checks.claim(out, "demo", {}))
        with pytest.raises(SystemExit) as e:
            main([])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"--out {out!r} is in use by another run (pid {holder.pid} " in err
        assert os.listdir(out) == [checks.LOCK]  # nothing written
    finally:
        holder.communicate("")
    assert not checks.claim(out, "demo", {})  # its holder gone: a stale lock, taken over
    with open(os.path.join(out, checks.LOCK)) as f:
        assert f.read().startswith(f"pid {os.getpid()} ")


def test_a_finished_run_leaves_no_lock(tmp_path):
    out = str(tmp_path / "run")
    claim = "import sys; from dynres_jax.commands import checks; checks.claim(sys.argv[1], 'demo', {})"
    subprocess.run([sys.executable, "-c", claim, out], check=True)
    assert sorted(os.listdir(out)) == sorted([checks.RUN, files.OWN])
    assert checks.claim(out, "demo", {})  # and the folder resumes
    key = os.path.realpath(out)
    fd, path, pid = folder_lock._locks[key]
    folder_lock._locks[key] = (fd, path, pid + 1)  # as a forked child (a worker) sees it at its exit
    folder_lock.release()
    assert checks.LOCK in os.listdir(out)  # the parent's lock stays
    folder_lock._locks[key] = (fd, path, pid)
    folder_lock.release()
    assert checks.LOCK not in os.listdir(out) and key not in folder_lock._locks


def test_a_folder_holding_only_a_lock_counts_as_empty(tmp_path):
    out = str(tmp_path / "run")
    os.makedirs(out)
    open(os.path.join(out, checks.LOCK), "w").close()
    assert not checks.claim(out, "demo", {})
    with open(os.path.join(out, "theirs.txt"), "w") as f:
        f.write("x")
    os.unlink(os.path.join(out, checks.RUN))
    with pytest.raises(InputError, match="not empty"):
        checks.claim(out, "demo", {})


def test_a_dangling_link_as_out_is_refused_before_any_work(tmp_path):
    """--out a symbolic link to a folder that does not exist: refused by check_out (what commands call before their
    set-up) naming the link's target, and nothing made; a link to an existing folder is that folder."""
    out = tmp_path / "run"
    os.symlink(tmp_path / "gone", out)
    for given in (str(out), str(out) + os.sep, str(out / "sub")):  # the link itself, with a slash, above the folder
        with pytest.raises(InputError, match="symbolic link to .*gone.*does not exist"):
            checks.check_out(given, "demo", {})
    with pytest.raises(InputError, match="symbolic link to"):
        checks.out_file(str(out / "push.png"), (".png",))
    assert sorted(os.listdir(tmp_path)) == ["run"]
    os.makedirs(tmp_path / "gone")
    assert not checks.claim(str(out), "demo", {})
    assert os.path.isfile(tmp_path / "gone" / checks.RUN)


def test_a_folder_that_takes_no_new_folder_is_refused_before_any_work():
    """An output under a folder that refuses new entries even to root (/proc): refused by the checks a command makes
    before its work (it planned 20 s and ended in a FileNotFoundError traceback), and nothing is left there."""
    if not os.path.isdir("/proc"):
        pytest.skip("no /proc here")
    with pytest.raises(InputError, match="cannot make .*takes no new folder"):
        checks.out_file("/proc/dynres-nope/push.png", (".png",))
    with pytest.raises(InputError, match="takes no new folder"):
        checks.check_out("/proc/dynres-nope/run", "demo", {})


def test_a_255_byte_name_writes_atomically(tmp_path):
    path = str(tmp_path / ("é" * 125 + "x.txt"))  # 255 bytes in UTF-8
    assert len(os.fsencode(os.path.basename(path))) == 255
    files.write_text(path, "whole")
    with open(path) as f:
        assert f.read() == "whole"
    assert os.listdir(tmp_path) == [os.path.basename(path)]


def test_a_resume_whose_input_changed_is_refused(tmp_path):
    out, ckpt, goal = str(tmp_path / "run"), tmp_path / "ckpt", tmp_path / "goal.png"
    (ckpt / "3").mkdir(parents=True)
    (ckpt / "3" / "data").write_bytes(b"model")
    goal.write_bytes(b"goal")
    inputs = {"--ckpt": str(ckpt), "--goal": str(goal), "--regressor": None}
    assert not checks.claim(out, "demo", {}, inputs=inputs)
    with open(os.path.join(out, checks.RUN)) as f:
        assert json.load(f)["inputs"]["--goal"] == [[str(goal), checks.digest(str(goal), "--goal")]]
    (ckpt / checks.LOCK).write_text("pid 1")  # a lock is not content
    assert checks.claim(out, "demo", {}, inputs=inputs)
    (ckpt / "3" / "data").write_bytes(b"other model")
    with pytest.raises(InputError, match=f"input --ckpt '{ckpt}' changed since it began"):
        checks.claim(out, "demo", {}, inputs=inputs)
    (ckpt / "3" / "data").write_bytes(b"model")
    goal.write_bytes(b"another goal")
    with pytest.raises(InputError, match="input --goal"):
        checks.claim(out, "demo", {}, inputs=inputs)
    assert not checks.claim(out, "demo", {}, fresh=True, inputs=inputs)  # --fresh starts afresh on the new goal
    assert checks.claim(out, "demo", {}, inputs=inputs)


def test_a_run_without_input_hashes_is_not_resumed(tmp_path):
    out, goal = str(tmp_path / "run"), tmp_path / "goal.png"
    goal.write_bytes(b"goal")
    checks.claim(out, "demo", {})
    assert checks.claim(out, "demo", {})  # no inputs: nothing to prove
    with open(os.path.join(out, checks.RUN), "w") as f:
        json.dump({"command": "demo", "config": {}}, f)  # a run begun before inputs were recorded
    with pytest.raises(InputError, match="recorded no hashes of its inputs"):
        checks.claim(out, "demo", {}, inputs={"--goal": str(goal)})


def test_a_flag_added_since_at_its_default_none_resumes_an_earlier_run(tmp_path):
    """A run recorded before a flag existed resumes under that flag's default (None), and not under another value."""
    out = str(tmp_path / "run")
    assert not checks.claim(out, "demo", {"a": 1})
    assert checks.claim(out, "demo", {"a": 1, "stop_share": None})
    with pytest.raises(InputError, match="other settings"):
        checks.claim(out, "demo", {"a": 1, "stop_share": 0.9})


def test_a_task_command_refuses_its_folder_and_goal_before_building_the_scene(tmp_path, monkeypatch, capsys):
    """A task command's --out of other settings and a goal PNG of another camera's size are refused in one line
    before the simulator is built (it took 9-13 s on a CPU)."""
    from dynres_jax.commands import gather, redistribute, task
    from dynres_jax.config import CameraConfig
    from dynres_jax.control.goals import disc_goal
    from dynres_jax.io.frames import save_goal
    from dynres_jax.sim.camera import Camera

    def no_scene(*args):
        raise AssertionError("the scene was built before the refusal")

    monkeypatch.setattr(task, "make_env", no_scene)
    out, small = str(tmp_path / "run"), str(tmp_path / "goal64.png")
    checks.claim(out, "gather", {"seed": -1})
    save_goal(small, disc_goal(Camera.top_down(CameraConfig(width=64, height=64)), np.zeros(2), 0.05))
    save_goal(str(tmp_path / "goal.png"), disc_goal(Camera.top_down(CameraConfig()), np.zeros(2), 0.05))
    tiny = ["--mpc-steps", "1", "--samples", "4", "--adam-steps", "1", "--dynamics", "sweep", "--pieces", "20"]
    for main, argv, words in [(gather.main, ["--out", out], "of other settings"),
                              (redistribute.main, ["--goal-png", small, "--out", str(tmp_path / "r")],
                               "is (64, 64), the camera's images are")]:
        with pytest.raises(SystemExit) as e:
            main([*tiny, *argv])
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.count("\n") == 1 and words in err, err
    inputs = {}
    monkeypatch.setattr(checks, "check_out", lambda out, command, config, fresh, given: inputs.update(given))
    with pytest.raises(AssertionError, match="scene was built"):  # the goal PNG is among the inputs a resume proves
        redistribute.main([*tiny, "--goal-png", str(tmp_path / "goal.png"), "--out", str(tmp_path / "g")])
    assert inputs["--goal-png"] == str(tmp_path / "goal.png")


def test_an_output_file_never_overwrites_the_commands_input(tmp_path, capsys):
    """--out naming one of the command's own inputs (the frame plan reads, the mask goal reads, a file the export's
    sidecar would replace) is refused in one line, and the input is left as it was."""
    from dynres_jax.commands import goal
    from dynres_jax.config import CameraConfig
    from dynres_jax.control.goals import disc_goal
    from dynres_jax.io.frames import save_goal
    from dynres_jax.sim.camera import Camera

    mask = str(tmp_path / "mask.png")
    save_goal(mask, disc_goal(Camera.top_down(CameraConfig()), np.zeros(2), 0.05))
    before = open(mask, "rb").read()
    with pytest.raises(SystemExit) as e:
        goal.main(["--mask", mask, "--out", mask])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and "is the command's input --mask" in err, err
    assert open(mask, "rb").read() == before
    camera = str(tmp_path / "d.jaxexport.json")
    with pytest.raises(InputError, match="input --camera"):
        checks.out_file(str(tmp_path / "d.jaxexport"), (".jaxexport",), beside=".json", inputs={"--camera": camera})
    assert checks.out_file(str(tmp_path / "e.jaxexport"), (".jaxexport",), beside=".json", inputs={"--camera": camera})


def test_a_folder_and_a_link_to_it_are_one_input(tmp_path, capsys):
    """Data, labels or label runs named twice, once through a symbolic link, are refused as named twice (training
    on them counted every episode twice; a run's reliability against itself read as Spearman 1)."""
    from dynres_jax.commands import tradeoff, train_dynamics, train_regressor

    (tmp_path / "d").mkdir()
    os.symlink(tmp_path / "d", tmp_path / "link")
    d, link = str(tmp_path / "d"), str(tmp_path / "link")
    for main, argv in [(train_dynamics.main, ["--data", d, link]), (train_regressor.main, ["--labels", d, link]),
                       (tradeoff.main, ["--reliability", d, link])]:
        with pytest.raises(SystemExit) as e:
            main([*argv, "--out", str(tmp_path / "out")])
        err = capsys.readouterr().err
        assert e.value.code == 2 and "twice" in err, err
