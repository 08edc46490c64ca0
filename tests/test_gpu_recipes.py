"""The GPU run recipes (scripts/recipes/*.toml) and their launcher (scripts/gpu.py), without a GPU: every recipe
parses, fills in (every {var} defined), prints its stages in a dry run and names modules and scripts that exist; a
toy recipe runs for real (two waves, GPU assignment, a done marker, a stop, a failing stage)."""

import importlib.util
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
spec = importlib.util.spec_from_file_location("gpu", ROOT / "scripts" / "gpu.py")
gpu = importlib.util.module_from_spec(spec)
spec.loader.exec_module(gpu)
RECIPES = sorted(p.stem for p in (ROOT / "scripts" / "recipes").glob("*.toml"))
EXAMPLES = {"JOBS": "scripts/ladder/call1.jobs", "REF": ".", "STAGE": "c"}  # the required variables' values


@pytest.fixture(autouse=True)
def _two_gpus(monkeypatch):
    monkeypatch.setenv("GPUS", "2")  # no nvidia-smi call; GPU i mod 2


def expanded(name):
    recipe = tomllib.loads((ROOT / "scripts" / "recipes" / f"{name}.toml").read_text())
    values = gpu.variables(recipe, {k: EXAMPLES[k] for k in recipe.get("require", {})})
    return recipe, gpu.expand(recipe, values)


def test_recipes_are_there():
    assert len(RECIPES) >= 28 and "ladder" in RECIPES and "judge" in RECIPES
    assert not list((ROOT / "scripts").glob("gpu_*.sh"))  # every old script is a recipe now


@pytest.mark.parametrize("name", RECIPES)
def test_recipe_fills_in_and_names_what_exists(name, monkeypatch):
    monkeypatch.chdir(ROOT)
    recipe, stages = expanded(name)  # an undefined {var} raises here
    assert recipe["stage"] and stages
    assert (ROOT / "scripts" / "recipes" / f"{name}.toml").read_text().startswith("# ")  # what it measures, where
    named = 0
    for s in stages:
        text = " ".join([s["cmd"], s["report"], *s["env"].values()])
        assert not gpu.VAR.search(text), f"{name}: {s['name']} left a {{var}}"
        for module in re.findall(r"python -m ([\w.]+)", text):
            path = ROOT / module.replace(".", "/")
            assert path.with_suffix(".py").exists() or (path / "__init__.py").exists(), f"{name}: no module {module}"
            named += 1
        for script in re.findall(r"(?:python|bash) \"?(?:\$here/)?(scripts/[\w/]+\.(?:py|sh))", text):
            assert (ROOT / script).exists(), f"{name}: no {script}"
            named += 1
        for other in re.findall(r"scripts/gpu\.py\"? (\w+)", text):
            assert other in RECIPES, f"{name}: no recipe {other}"
    assert named, f"{name} runs no module or script"


@pytest.mark.parametrize("name", RECIPES)
def test_dry_run_prints_every_stage(name, monkeypatch, capsys, tmp_path):
    monkeypatch.chdir(ROOT)
    monkeypatch.setenv("WORK", str(tmp_path / "work"))
    monkeypatch.setenv("OUT", str(tmp_path / "out"))
    recipe = tomllib.loads((ROOT / "scripts" / "recipes" / f"{name}.toml").read_text())
    sets = [f"--set={k}={EXAMPLES[k]}" for k in recipe.get("require", {})]
    assert gpu.main([name, "--dry-run", *sets]) == 0
    printed = capsys.readouterr().out
    assert len(re.findall(r"^wave -?\d+, GPU", printed, re.M)) == len(expanded(name)[1]) >= 1
    assert not (tmp_path / "work").exists() and not (tmp_path / "out").exists()  # ran nothing, made nothing


TOY = """
# a toy: two waves, a marker, GPUs, a template
log = "{OUT}/stages.log"
dirs = ["{OUT}"]
[vars]
OUT = "unset"
WORD = "hello"
LAST = "ok"
[templates.say]
cmd = "echo {WORD} {what} > {OUT}/{what}.txt"
[[stage]]
template = "say"
for = { what = "a b" }
wave = 1
gpu = "{i}"
cmd = "echo {WORD} {what} $CUDA_VISIBLE_DEVICES > {OUT}/{what}.txt"
[[stage]]
template = "say"
what = "skipped"
wave = 1
done = "{OUT}/marker"
[[stage]]
name = "second wave"
cmd = "cat {OUT}/a.txt {OUT}/b.txt > {OUT}/both.txt"
[[stage]]
name = "{what} stage"
for = { what = "{LAST}" }
wave = 3
cmd = "[ {what} != broken ] || exit 3; [ {what} != stop ] || exit 75; touch {OUT}/{what}"
[[stage]]
name = "after"
cmd = "touch {OUT}/after"
"""


@pytest.mark.parametrize("last", ["fine", "broken", "stop"])
def test_toy_recipe_runs(last, tmp_path, monkeypatch, capsys):
    recipe = tmp_path / "toy.toml"
    recipe.write_text(TOY)
    out = tmp_path / "out"
    out.mkdir()
    (out / "marker").touch()
    monkeypatch.setenv("WORD", "hi")  # the environment wins over a default
    status = gpu.main([str(recipe), "--set", f"OUT={out}", "--set", f"LAST=ok {last}"])
    printed = capsys.readouterr().out
    assert (out / "a.txt").read_text() == "hi a 0\n" and (out / "b.txt").read_text() == "hi b 1\n"  # GPU i mod 2
    assert (out / "both.txt").read_text() == "hi a 0\nhi b 1\n"  # the second wave saw the first's files
    assert not (out / "skipped.txt").exists() and "skipped" in printed  # its done marker existed
    assert (out / "ok").exists()  # beside the last stage, in its wave
    assert "second wave: done" in (out / "stages.log").read_text()
    if last == "fine":
        assert status == 0 and (out / "fine").exists() and (out / "after").exists()
    elif last == "broken":
        assert status == 1 and not (out / "after").exists()
        assert "broken stage: FAILED (exit 3)" in printed and "failed: broken stage" in printed
    else:
        assert status == 0 and not (out / "after").exists() and "stops the run" in printed
