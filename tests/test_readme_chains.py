"""Every command line of the README's shell blocks runs, in the README's order, in one scratch folder, at the
smallest sizes: each line exactly as written with size flags appended (argparse keeps the last value), so the chains
the README promises (simulate -> goal -> plan -> robot and export, generate_data -> train_dynamics -> eval_dynamics,
label_resolution -> train_regressor -> tradeoff) hand each other real files. The robot-side snippet of the deployment
section then runs on what export and simulate wrote. The launcher lines (srun, the hand-joined processes) are left to
tests/test_distributed.py, the set-up block to CI itself (it is CI's own command)."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from test_readme_commands import README, command_lines

pytestmark = pytest.mark.slow  # about ten minutes of end-to-end commands: CI's second tier

ROOT = Path(__file__).resolve().parents[1]
FEW = ["--samples", "4", "--adam-steps", "2"]
SMALLEST = {  # appended to every line of the command: the smallest run that still writes every file
    "gather": ["--mpc-steps", "1", *FEW], "redistribute": ["--mpc-steps", "1", *FEW],
    "sort": ["--mpc-steps", "1", *FEW], "simulate": ["--pushes", "1"], "goal": [], "plan": FEW,
    "robot": ["--steps", "1", *FEW], "generate_data": ["--quick"],
    "train_dynamics": ["--recipe", "quick", "--steps", "4"], "eval_dynamics": ["--windows", "4"],
    "label_resolution": ["--scenes", "8", "--batch", "4", "--evals", "6", "--repeats", "1", *FEW],
    "train_regressor": ["--steps", "4"], "evaluate": ["--quick", "--episodes", "2", "--mpc-steps", "1"],
    "tradeoff": ["--quick", "--scenes", "2", "--samples", "4"],
    "export": [],  # as written: the robot-side snippet calls it with 100 Adam steps, at most what it was exported with
}
PLANNED = ["--worlds", "10"]  # generate_data --planned: the ten quick episodes in one shard: the planner compiles once


def chain() -> list[tuple[str, list[str]]]:
    """The README's command lines in order, without the launcher examples (they need several processes)."""
    return [(m, a) for m, a in command_lines(README) if "--coordinator" not in a and not any("/shared" in x for x in a)]


def test_the_chain_holds_every_kind_of_line():
    """The run below would pass vacuously on a README without its chains: they are there, and every command has its
    smallest sizes."""
    names = [m.split(".")[1] for m, _ in chain()]
    assert set(names) <= set(SMALLEST), set(names) - set(SMALLEST)
    for first, then in (("simulate", "goal"), ("goal", "plan"), ("generate_data", "train_dynamics"),
                        ("train_dynamics", "eval_dynamics"), ("label_resolution", "train_regressor")):
        assert names.index(first) < names.index(then)


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    """Every line run in order in one folder: {index: CompletedProcess}; a line whose predecessor failed still runs
    (its own failure is reported beside the first)."""
    folder = tmp_path_factory.mktemp("readme")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    done = {}
    for i, (module, argv) in enumerate(chain()):
        extra = SMALLEST[module.split(".")[1]] + (PLANNED if "--planned" in argv else [])
        done[i] = subprocess.run([sys.executable, "-m", module, *argv, *extra], cwd=folder, env=env,
                                 capture_output=True, text=True, timeout=900)
        print(f"[readme chain] {i + 1}/{len(chain())} {module} {' '.join(argv)}: exit {done[i].returncode}",
              file=sys.__stderr__, flush=True)
    return folder, done


@pytest.mark.parametrize("i", range(len(chain())), ids=[" ".join([m.split(".")[1], *a])[:50] for m, a in chain()])
def test_each_readme_line_runs_as_written(ran, i):
    _, done = ran
    out = done[i]
    assert out.returncode == 0, f"{' '.join(out.args[2:])}\n{out.stderr[-2000:]}"


def test_the_chains_hand_each_other_files(ran):
    folder, _ = ran
    for path in ("out/gather/metrics.json", "out/letter/metrics.json", "out/sort/metrics.json",
                 "out/sim/frame/depth.png", "out/G.png", "out/push.png", "out/robot/metrics.json",
                 "runs/dynamics/eval", "runs/regressor", "runs/eval", "runs/tradeoff", "out/decision.jaxexport",
                 "out/decision.jaxexport.json"):
        assert (folder / path).exists(), path


def test_the_robot_side_snippet_runs_on_the_exported_file(ran):
    """The deployment section's Python block, as written, with what the README's own commands wrote: a push in
    metres inside the bin, no error bit."""
    folder, _ = ran
    section = README.split("## Deployment", 1)[1].split("\n## ", 1)[0]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    script = code + "\nimport numpy as np\nprint('push', np.asarray(out['push']).tolist(), int(out['error']))\n"
    (folder / "robot_side.py").write_text(script)
    out = subprocess.run([sys.executable, "robot_side.py"], cwd=folder, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    push, error = re.search(r"^push (\[.*\]) (\d+)$", out.stdout, re.M).groups()
    push = [float(x) for x in push.strip("[]").split(",")]
    assert int(error) == 0 and len(push) == 4 and all(abs(x) < 0.5 for x in push), out.stdout
