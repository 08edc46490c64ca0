"""Commands and the library under environments a user may have set (issue 70, item 5): JAX_ENABLE_X64=1 (explicit
dtypes in every carry), PYTHONOPTIMIZE=2 (no docstrings: help text read from the source), PYTHONIOENCODING=ascii
(output escapes what the terminal cannot show). Each in a subprocess, at tiny sizes."""

import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

PLANNER = """
import jax, jax.numpy as jnp, numpy as np
from dynres_jax.control.planner import PlannerConfig, plan
from dynres_jax.models.registry import SHIPPED_DYNAMICS, load_dynamics, sweep_dynamics
assert jax.config.jax_enable_x64
pos = jnp.asarray(np.random.default_rng(0).uniform(-0.05, 0.05, (12, 3)) * [1, 1, 0], jnp.float32)
cost = lambda final, m: jnp.sum(jnp.where(m, jnp.sum(final[:, :2] ** 2, -1), 0.0))
dynamics = sweep_dynamics(0.04) if "{model}" == "sweep" else load_dynamics("learned", SHIPPED_DYNAMICS, 0.04).dynamics
result = plan(dynamics(0.01), cost, pos, jnp.ones(12, bool), jax.random.PRNGKey(0),
              config=PlannerConfig(samples=4, adam_steps=2))
print("planned", result.best.dtype, np.isfinite(np.asarray(result.best)).all())
"""


def _run(code_or_args, timeout=300, **env):
    args = ["-c", code_or_args] if isinstance(code_or_args, str) else code_or_args
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "JAX_PLATFORMS": "cpu", **env})


@pytest.mark.parametrize("model", ["sweep", "learned"])
def test_the_planner_runs_under_x64(model):
    """The planner's Adam loop keeps float32 costs and an int32 best index under JAX_ENABLE_X64=1 (argmin is int64
    there, a goal's float64 fields made float64 costs)."""
    done = _run(PLANNER.replace("{model}", model), JAX_ENABLE_X64="1")
    assert done.returncode == 0 and "planned float32 True" in done.stdout, done.stderr[-2000:]


@pytest.mark.slow
def test_a_command_under_x64_plans_in_float32(tmp_path):
    """A command computes in float32 whatever JAX_ENABLE_X64 says (``checks.guarded``): the goal and a plan on a
    saved frame run and print their JSON."""
    made = _run(f"""
import jax, numpy as np
from dynres_jax.config import CameraConfig, SceneConfig, SimConfig
from dynres_jax.control.goals import disc_goal
from dynres_jax.io import frames
from dynres_jax.sim.env import PileEnv
env = PileEnv(SimConfig(scene=SceneConfig(pieces=(8,)), camera=CameraConfig(width=48, height=48)), backend="mujoco")
frames.save_frame({str(tmp_path)!r}, env.reset(jax.random.PRNGKey(0)).obs, env.camera)
frames.save_goal({str(tmp_path / "goal.png")!r}, disc_goal(env.camera, np.zeros(2), 0.06))
""")
    assert made.returncode == 0, made.stderr[-2000:]
    f = {n: str(tmp_path / n) for n in ("depth.png", "rgb.png", "camera.json", "goal.png")}
    done = _run(["-m", "experiments.plan", "--depth", f["depth.png"], "--rgb", f["rgb.png"], "--camera",
                 f["camera.json"], "--goal", f["goal.png"], "--resolution", "6", "--samples", "4", "--adam-steps", "2",
                 "--out", str(tmp_path / "push.png")], JAX_ENABLE_X64="1")
    assert done.returncode == 0 and '"push"' in done.stdout, done.stderr[-2000:]


def test_every_help_prints_under_python_oo():
    """PYTHONOPTIMIZE=2 strips docstrings; every command's --help still prints, its description read from the
    source (``commands.docstring``), and so does ``dynres --help``."""
    done = _run("""
import contextlib, io
from dynres_jax.commands import COMMANDS, main
assert main.__doc__ is None  # -OO in force
for name in ("--help", *COMMANDS):
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        try:
            main([name] if name == "--help" else [name, "--help"])
        except SystemExit as e:
            assert e.code in (0, None), (name, e.code)
    text = out.getvalue()
    assert ("usage:" in text or name == "--help") and len(text.split("\\n\\n")) > 2, (name, text[:300])
    print("ok", name)
""", timeout=600, PYTHONOPTIMIZE="2")
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.count("ok ") == 1 + len(__import__("dynres_jax.commands").commands.COMMANDS)


def test_an_ascii_terminal_gets_escapes_not_a_crash(tmp_path):
    """PYTHONIOENCODING=ascii: "ω" and "±" in a command's output come out escaped, exit status 0."""
    done = _run(["-m", "experiments.plan", "--help"], PYTHONIOENCODING="ascii")
    assert done.returncode == 0 and "\\u03c9" in done.stdout and "\\xb1" in done.stdout, done.stderr[-2000:]
    done = _run(["-m", "experiments.goal", "--letter", "ω", "--out", str(tmp_path / "g.png")], PYTHONIOENCODING="ascii")
    assert done.returncode == 2 and "\\u03c9" in done.stderr and done.stderr.count("\n") == 1, done.stderr
