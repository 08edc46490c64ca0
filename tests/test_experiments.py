"""Command-line entry points: each one's --help, and the simulator demo end to end on a tiny scene."""

import json
import os
import re
import runpy
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from dynres_jax.commands import simulate

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = sorted(p.stem for p in (ROOT / "experiments").glob("*.py") if '"__main__"' in p.read_text())


def readme_commands() -> list[tuple[str, list[str]]]:
    """Every ``python -m experiments.X ARGS`` the README shows, in code blocks (continuation lines joined) and
    inline code (which may wrap), as (module, args); chained commands and trailing comments cut off; a shell loop's
    variable (``$i``) stands for 0."""
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```[^\n]*\n(.*?)```", text, re.S)
    lines = [line for b in blocks for line in b.replace("\\\n", " ").splitlines()]
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    lines += [span.replace("\n", " ") for span in re.findall(r"`([^`]+)`", prose)]
    found = []
    for line in lines:
        for m in re.finditer(r"python -m (experiments\.\w+)([^&|;]*)", line):
            found.append((m.group(1), shlex.split(re.sub(r"\$\w+", "0", m.group(2)), comments=True)))
    return sorted(set((module, tuple(args)) for module, args in found))


def _help(module: str, args, monkeypatch, capsys) -> str:
    """The module run as ``python -m`` with args + --help, in this process; its printed help."""
    monkeypatch.setattr(sys, "argv", [module, *args, "--help"])
    with pytest.raises(SystemExit) as exit_:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    assert exit_.value.code == 0
    return capsys.readouterr().out


def test_the_readme_shows_commands():
    assert len(readme_commands()) >= 10 and {m for m, _ in readme_commands()} <= {f"experiments.{c}" for c in COMMANDS}


RERUN = "ignore:.*found in sys.modules:RuntimeWarning"  # runpy re-running an imported module is what we want


@pytest.mark.filterwarnings(RERUN)
@pytest.mark.parametrize("module", COMMANDS)
def test_help(module, monkeypatch, capsys):
    assert "usage" in _help(f"experiments.{module}", [], monkeypatch, capsys)


@pytest.mark.filterwarnings(RERUN)
@pytest.mark.parametrize("module, args", readme_commands(), ids=lambda x: " ".join(x) if isinstance(x, tuple) else x)
def test_readme_command_parses(module, args, monkeypatch, capsys):
    """The README's command, as written, with --help appended: its flags and choices are ones the command takes
    (argparse rejects an unknown flag or a bad choice before it acts on --help)."""
    assert "usage" in _help(module, args, monkeypatch, capsys)


def test_simulate_demo_writes_its_files(tmp_path, capsys):
    simulate.main(["--kind", "coffee", "candy", "--pieces", "3", "2", "--pushes", "1", "--image-size", "48",
                   "--layout", "two_blobs", "--out", str(tmp_path)])
    said = capsys.readouterr().err.splitlines()  # a start line before the scene is built, then the pushes' progress
    assert said[0].endswith(f"simulate: 1 push(es) of 3 + 2 coffee + candy pieces on mujoco, into {tmp_path}; "
                            "building the scene") and said[-1].startswith("pushes: 1/1 push"), said
    for name in ("pushes.gif", "final_rgb.png", "final_depth.png", "actions.json"):
        assert (tmp_path / name).stat().st_size > 0
    record = json.loads((tmp_path / "actions.json").read_text())
    assert len(record["actions"]) == 1 and record["broken"] is False
    # the last frame as a camera saves it: what the README's real-camera lines read
    from dynres_jax.commands import goal
    from dynres_jax.io.frames import load_frame

    frame = tmp_path / "frame"
    obs, camera = load_frame(str(frame / "depth.png"), str(frame / "rgb.png"), str(frame / "camera.json"))
    assert obs.depth.shape == (48, 48) == (camera.height, camera.width) and float(obs.depth.min()) > 0
    goal.main(["--disc", "0", "0", "0.05", "--camera", str(frame / "camera.json"), "--out", str(tmp_path / "g.png")])
    assert (tmp_path / "g.png").stat().st_size > 0


def test_the_dynres_command_runs_every_command(capsys):
    """``dynres NAME`` reaches the same parser as ``python -m experiments.NAME``; every shim is a dynres command; an
    unknown name is refused with the list."""
    from dynres_jax.commands import COMMANDS as DYNRES
    from dynres_jax.commands import main

    assert sorted(DYNRES) == [c for c in COMMANDS if c != "benchmark"]
    for name in ("gather", "train-regressor"):
        with pytest.raises(SystemExit) as exit_:
            main([name, "--help"])
        assert exit_.value.code == 0 and "usage" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_:
        main(["gahter"])
    assert exit_.value.code == 2 and re.search("unknown command 'gahter'.*gather", capsys.readouterr().err)


def test_usage_and_errors_name_the_command_as_it_was_run():
    """Run as the installed ``dynres`` script, errors say ``dynres NAME``; as a module, ``python -m experiments.NAME``.
    A bad flag is one line naming it and where the options are, not the usage block."""
    script = "import sys; sys.argv[0] = {!r}; from dynres_jax.commands import main; main(['goal', '--disc', '0'])"
    for argv0, named in (("/venv/bin/dynres", "dynres goal"), ("-m", "python -m experiments.goal")):
        result = subprocess.run([sys.executable, "-c", script.format(argv0)], capture_output=True, text=True,
                                env=dict(os.environ, JAX_PLATFORMS="cpu"))
        assert result.returncode == 2, result.stderr
        assert re.fullmatch(f"{named}: error: argument --disc: .* \\(options: {named} --help\\)\n", result.stderr), \
            result.stderr


def test_a_bad_recipe_is_one_line_too(capsys):
    """train_dynamics reads --recipe before its parser (the recipe sets the defaults): its mistake is one line too."""
    from dynres_jax.commands import train_dynamics

    with pytest.raises(SystemExit) as exit_:
        train_dynamics.main(["--recipe", "nope"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and "error: argument --recipe: invalid choice" in err, err
