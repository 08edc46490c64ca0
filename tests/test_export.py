"""Exported planner: the file reloaded with jax.export alone plans exactly what the live planner plans."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from dynres_jax import export as ex
from dynres_jax.commands import export as export_cli
from dynres_jax.config import CameraConfig
from dynres_jax.control.decision import goal_cost
from dynres_jax.control.goals import disc_goal, make_goal
from dynres_jax.control.planner import PlannerConfig, plan
from dynres_jax.io import ckpt
from dynres_jax.models.dynamics import Dynamics, DynamicsConfig
from dynres_jax.models.registry import load_dynamics
from dynres_jax.sim.camera import Camera

N_MAX, STEP, Q = 12, 7, 16
CAMERA = Camera.top_down(CameraConfig(width=32, height=32))
CONFIG = PlannerConfig(samples=4, adam_steps=3, horizon=2)


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    """A randomly initialised tiny Dynamics model saved as a checkpoint (the card as train.py writes it)."""
    cfg = DynamicsConfig(hidden=16, propagation_steps=1, push_frame=True, residual=True, world_edges=False,
                         bin_position=False)
    directory = tmp_path_factory.mktemp("ckpt")
    ckpt.save_module(directory, STEP, Dynamics(cfg, rngs=nnx.Rngs(3)),
                     {"dynamics": dataclasses.asdict(cfg), "train": {"n_max": N_MAX}, "step": STEP})
    return str(directory)


def particles(seed, omega):
    pos = jax.random.uniform(jax.random.PRNGKey(seed), (N_MAX, 3), minval=-0.06, maxval=0.06).at[:, 2].set(0.007)
    mask = jnp.arange(N_MAX) < omega
    return jnp.where(mask[:, None], pos, 0.0), mask, jnp.float32(0.015)


GOALS = {"left disc": ([-0.05, 0.02], 0.05), "right disc": ([0.06, -0.03], 0.07)}


@pytest.fixture(scope="module")
def exported_file(tiny_ckpt, tmp_path_factory):
    exported, info = ex.export_checkpoint(tiny_ckpt, CONFIG, CAMERA, goal_samples=Q, platforms=("cpu",))
    path = str(tmp_path_factory.mktemp("export") / "planner.jaxexport")
    assert ex.save(exported, path, info) > 0
    return path


@pytest.fixture(scope="module")
def reloaded(exported_file):
    """The file read back with jax alone (none of this package's code); one object, so it compiles once."""
    with open(exported_file, "rb") as f:
        return jax.export.deserialize(bytearray(f.read()))


@pytest.mark.parametrize("goal_name, seed, warm", [("left disc", 1, False), ("right disc", 2, True)])
def test_reloaded_file_plans_exactly_like_the_live_planner(tiny_ckpt, reloaded, goal_name, seed, warm):
    centre, radius_m = GOALS[goal_name]
    goal = make_goal(disc_goal(CAMERA, centre, radius_m), CAMERA, n_samples=Q)
    positions, mask, radius = particles(seed, omega=9 if warm else 6)
    key = jax.random.PRNGKey(seed)
    init = jnp.array([[-0.1, 0.0, 0.0, 0.01], [0.1, 0.05, 0.0, 0.0]], jnp.float32)
    out = reloaded.call(positions, mask, radius, *goal, key, init, jnp.asarray(warm))

    dynamics, n_max, _ = load_dynamics("learned", tiny_ckpt, 0.04)
    assert n_max == N_MAX
    live = plan(dynamics(radius), goal_cost(goal, CAMERA), positions, mask, key, CONFIG, init if warm else None)
    np.testing.assert_array_equal(np.asarray(out["best"]), np.asarray(live.best))
    np.testing.assert_array_equal(np.asarray(out["best_cost"]), np.asarray(live.best_cost))
    np.testing.assert_array_equal(np.asarray(out["history"]), np.asarray(live.history))
    assert out["best"].shape == (CONFIG.horizon, 4) and out["history"].shape == (CONFIG.adam_steps,)
    # the convenience wrapper passes the same arguments
    again = ex.call(reloaded, positions, mask, radius, goal, key, init if warm else None)
    np.testing.assert_array_equal(np.asarray(again["best"]), np.asarray(live.best))


def test_wrong_input_shapes_are_jax_errors(exported_file):
    exported = ex.load(exported_file)  # the library's loader
    goal = make_goal(disc_goal(CAMERA, [0.0, 0.0], 0.05), CAMERA, n_samples=Q)
    positions, mask, radius = particles(0, 5)
    with pytest.raises(ValueError, match="shape"):
        exported.call(positions[:5], mask[:5], radius, *goal, jax.random.PRNGKey(0), jnp.zeros((2, 4)), False)


def test_one_file_for_cpu_and_cuda(tiny_ckpt):
    """jax.export lowers the planner for both platforms at once, on a machine without a GPU, and the file reads back
    with both. (Running it costs a second compilation of the planner; done by hand: it runs on the CPU, with plans
    equal to the live ones up to rounding, dynres_jax/export.py.)"""
    exported, info = ex.export_checkpoint(tiny_ckpt, CONFIG, CAMERA, goal_samples=Q, platforms=("cpu", "cuda"))
    assert tuple(exported.platforms) == ("cpu", "cuda") and info["platforms"] == ["cpu", "cuda"]
    again = jax.export.deserialize(exported.serialize())
    assert tuple(again.platforms) == ("cpu", "cuda") and again.in_avals == exported.in_avals


def test_cli_writes_the_file_and_its_sidecar(tiny_ckpt, tmp_path, capsys):
    camera_json = tmp_path / "camera.json"
    camera_json.write_text(CAMERA.to_json())
    out = tmp_path / "robot" / "planner.jaxexport"
    summary = export_cli.main(["--ckpt", tiny_ckpt, "--out", str(out), "--samples", "4", "--adam-steps", "3",
                               "--horizon", "2", "--camera", str(camera_json), "--goal-samples", str(Q),
                               "--platforms", "cpu"])
    assert out.stat().st_size == summary["bytes"] > 0
    assert "signature: (positions: float32[12, 3]" in capsys.readouterr().out
    info = json.loads((tmp_path / "robot" / "planner.jaxexport.json").read_text())
    assert [i["name"] for i in info["inputs"]] == list(ex.INPUT_NAMES)
    shapes = {i["name"]: (i["shape"], i["dtype"]) for i in info["inputs"]}
    assert shapes["positions"] == ([N_MAX, 3], "float32") and shapes["goal_distance"] == ([32, 32], "float32")
    assert shapes["goal_samples"] == ([Q, 2], "float32") and shapes["key"] == ([2], "uint32")
    assert shapes["init"] == ([2, 4], "float32") and shapes["warm"] == ([], "bool")
    assert [o["name"] for o in info["outputs"]] == list(ex.OUTPUT_NAMES)
    assert info["planner"]["samples"] == 4 and info["planner"]["adam_steps"] == 3 and info["planner"]["horizon"] == 2
    assert info["planner"]["reach"] == pytest.approx(0.2 + 0.005 + 0.002)  # pushes may start outside a wall
    assert info["checkpoint"]["step"] == STEP and info["platforms"] == ["cpu"] and info["n_max"] == N_MAX
    exported = ex.load(str(out))
    assert [list(a.shape) for a in exported.in_avals] == [i["shape"] for i in info["inputs"]]
    assert not any(p.name.startswith(".tmp-") for p in out.parent.iterdir())  # atomic writes left nothing behind


def test_cli_missing_checkpoint_and_help(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        export_cli.main(["--ckpt", str(tmp_path / "nowhere"), "--out", str(tmp_path / "p.jaxexport")])
    assert exit_info.value.code == 2 and "no checkpoint" in capsys.readouterr().err
    assert not (tmp_path / "p.jaxexport").exists()
    with pytest.raises(SystemExit) as exit_info:
        export_cli.main(["--help"])
    assert exit_info.value.code == 0 and "jax.export.deserialize" in capsys.readouterr().out
