"""The flag table (commands/flags.py): committed as the commands' parsers describe themselves, it refuses a bad flag
in one line before any heavy import, and lets through every line the commands themselves accept."""

import subprocess
import sys

import pytest
from test_readme_commands import LINES

from dynres_jax.commands import COMMANDS, flags


@pytest.fixture(scope="module")
def committed():
    import json

    with open(flags.TABLE, encoding="utf-8") as f:
        return json.load(f)


def test_the_committed_table_is_the_commands_own(committed):
    assert committed == flags.table(), "run: python -m dynres_jax.commands.flags"


@pytest.mark.parametrize("name", COMMANDS)
def test_an_unknown_flag_is_one_line_exit_2(name, capsys, committed):
    required = [x for row in committed[name] if row["required"] and row["options"] for x in (row["options"][0], "x")]
    with pytest.raises(SystemExit) as exit_:
        flags.precheck(name, [*required, "--no-such-flag"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and "error: unrecognized arguments: --no-such-flag" in err


def test_a_missing_required_flag_and_a_bad_choice_are_refused(capsys):
    for name, argv, said in (("evaluate", [], "--out"), ("evaluate", ["--task", "nope", "--out", "x"], "--task"),
                             ("gather", ["--objective", "hingy"], "--objective"),
                             ("sort", ["--kind", "coffee", "coffee", "extra", "--mpc-steps"], "--mpc-steps")):
        with pytest.raises(SystemExit):
            flags.precheck(name, argv)
        assert said in capsys.readouterr().err


@pytest.mark.parametrize("module, argv", LINES, ids=[" ".join([m.split(".")[1], *a])[:60] for m, a in LINES])
def test_every_readme_line_passes(module, argv):
    flags.precheck(module.split(".")[1], argv)  # raises SystemExit if refused


def test_a_refusal_imports_nothing_heavy():
    """`python -m experiments.gather --bogus` answers without JAX, MuJoCo or Flax in the process."""
    code = ("import sys\nfrom dynres_jax.commands import entry\ntry:\n    entry('gather')(['--bogus'])\n"
            "except SystemExit as e:\n"
            "    print(e.code, sorted(m for m in ('jax', 'mujoco', 'flax') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "2 []", out.stdout + out.stderr
    assert "unrecognized arguments: --bogus" in out.stderr
