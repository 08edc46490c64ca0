"""Every command line in the README's shell blocks is one its command accepts as written: the flags exist and their
values parse. Each line's arguments go through the command's own parser (its ``main``, stopped right after
``parse_args``), so a renamed or removed flag fails here before a user meets it. The quick start's Python block runs in
test_readme.py; the main job and the tests run in CI itself."""

import argparse
import importlib
import re
import shlex
from pathlib import Path

import pytest

README = (Path(__file__).resolve().parents[1] / "README.md").read_text()


def command_lines(text: str) -> list[tuple[str, list[str]]]:
    """(experiments module, its arguments) for every ``python -m experiments.NAME ...`` in the ```bash blocks, with
    line continuations joined, comments dropped and shell variables (``$i``) set to 0."""
    found = []
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split(" #", 1)[0].replace("$i", "0")
            for m in re.finditer(r"python -m (experiments\.\w+)((?:\s+[^&;|]+)?)", line):
                found.append((m.group(1), shlex.split(m.group(2))))
    return found


LINES = command_lines(README)


class Parsed(Exception):
    """Raised by the patched parse_args: the line parsed, nothing runs."""


def test_the_readme_shows_the_commands_a_user_needs():
    """The parse below would pass vacuously on a README without commands: the main job, every task and the
    label -> regressor -> evaluate chain are there."""
    modules = {m for m, _ in LINES}
    assert {"experiments.gather", "experiments.redistribute", "experiments.sort", "experiments.label_resolution",
            "experiments.train_regressor", "experiments.evaluate", "experiments.plan"} <= modules
    assert len(LINES) >= 15


def test_a_renamed_flag_is_caught(monkeypatch):
    """The check itself can fail: a flag no command has is refused by the parser it reaches."""
    with pytest.raises(SystemExit):
        parse(monkeypatch, "experiments.gather", ["--no-such-flag", "1"])


def parse(monkeypatch, module: str, argv: list[str]) -> argparse.Namespace:
    """``module``'s main on ``argv`` up to its first parse_args: the namespace, or SystemExit(2) from argparse."""
    original = argparse.ArgumentParser.parse_args

    def parse_only(self, args=None, namespace=None):
        raise Parsed(original(self, args, namespace))

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_only)
    main = importlib.import_module(f"dynres_jax.commands.{module.split('.')[1]}").main  # the command's own parser
    with pytest.raises(Parsed) as parsed:
        main(argv)
    return parsed.value.args[0]


@pytest.mark.parametrize("module, argv", LINES, ids=[" ".join([m.split(".")[1], *a])[:60] for m, a in LINES])
def test_every_readme_command_line_parses(monkeypatch, tmp_path, module, argv):
    monkeypatch.chdir(tmp_path)  # relative paths (out/gather, runs/labels) resolve in a scratch folder
    args = parse(monkeypatch, module, argv)
    assert isinstance(args, argparse.Namespace)


def test_the_readme_writes_nothing_git_would_track():
    """Every ``--out`` of the README's commands inside the checkout, and the wheel folder it shows, is one .gitignore
    covers: following the README leaves a clean checkout (was: G.png, push.png, decision.jaxexport in the root)."""
    import shutil
    import subprocess

    root = Path(__file__).resolve().parents[1]
    if shutil.which("git") is None or not (root / ".git").exists():
        pytest.skip("not a git checkout")
    outs = {out for _, args in LINES if "--out" in args and not (out := args[args.index("--out") + 1]).startswith("/")}
    outs |= {f"{p}.json" for p in outs if p.endswith(".jaxexport")} | {"dist/"}
    assert "pip wheel . --no-deps -w dist/" in README and len(outs) >= 10
    ignored = subprocess.run(["git", "check-ignore", "--no-index", "--stdin"], input="\n".join(sorted(outs)),
                             cwd=root, capture_output=True, text=True).stdout.split()
    assert sorted(outs - set(ignored)) == []
