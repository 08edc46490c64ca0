"""The physics noise floor experiment: twin worlds, perturbation, sums and the floor (CPU, a tiny scene)."""

import argparse

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from dynres_jax.learn import data
from dynres_jax.models.dynamics import Dynamics, DynamicsConfig
from dynres_jax.sim.env import State
from studies import noise_floor

pytestmark = pytest.mark.slow  # end to end: CI's second tier (python -m pytest -m slow)

CONFIG = data.quick_config(backend="mujoco")


def _args(**kw):
    base = dict(worlds=2, pushes=2, twins=3, sigmas=[0.0, 1.0], omegas=[3, 6], seed=0,
                model_settings=(8, 256, DynamicsConfig().plate_half_width))
    return argparse.Namespace(**{**base, **kw})


@pytest.fixture(scope="module")
def scene():
    """Three models on the same pushes: a, its copy a2, and b (other weights; not residual, which starts as the
    sweep heuristic whatever the weights)."""
    a, b = (nnx.split(Dynamics(DynamicsConfig(hidden=8, residual=False), rngs=nnx.Rngs(s))) for s in (0, 1))
    return noise_floor.measure_scene(CONFIG, 0, _args(), {"a": a, "a2": a, "b": b}, pool=None)


def test_perturb_moves_only_piece_centres_in_the_plane():
    qpos = jnp.arange(2 * 15, dtype=jnp.float32).reshape(2, 15)
    states = State(qpos, jnp.zeros((2, 12)), None, None, None, jnp.zeros(2, bool))
    adr = np.array([0, 7])
    perturbed, moves = noise_floor.perturb(states, adr, 0.5, jax.random.PRNGKey(0))
    moved = np.asarray(perturbed.qpos) - np.asarray(qpos)
    changed = np.zeros(15, bool)
    changed[[0, 1, 7, 8]] = True
    assert np.all(moved[:, changed] != 0) and np.all(moved[:, ~changed] == 0)
    np.testing.assert_allclose(moved[:, [0, 7]], moves[..., 0], atol=1e-5)  # the moves it reports are the moves made
    np.testing.assert_allclose(moved[:, [1, 8]], moves[..., 1], atol=1e-5)
    assert np.all(np.asarray(noise_floor.perturb(states, adr, 0.0, jax.random.PRNGKey(0))[0].qpos) == qpos)


def test_distance_sum_equals_a_loop():
    rng = np.random.default_rng(0)
    a, b, valid = rng.normal(size=(3, 5, 3)), rng.normal(size=(3, 5, 3)), rng.uniform(size=(3, 5)) < 0.6
    loop = sum(np.sqrt(sum((a[i, j, c] - b[i, j, c]) ** 2 for c in range(3)))
               for i in range(3) for j in range(5) if valid[i, j])
    assert noise_floor.distance_sum(a, b, valid) == pytest.approx(loop)


def test_unperturbed_twins_agree_and_perturbed_ones_do_not(scene):
    """C MuJoCo is deterministic: twins with σ = 0 end the push exactly alike, so their distance is 0; σ = 1 mm
    moves the outcome."""
    for omega in ("3", "6"):
        s = scene["sums"][omega]
        assert s["particles"] > 0 and s["twins 0 mm"] == 0.0 and s["twins 1 mm"] > 0.0
        assert s["sweep heuristic"] > 0.0 and s["model a"] > 0.0


def test_held_out_median_equals_a_loop():
    rng = np.random.default_rng(1)
    twins = rng.normal(size=(4, 2, 3, 3))
    medians, held = noise_floor.held_out_median(twins)
    for j in range(4):
        others = [twins[i] for i in range(4) if i != j]
        for w in range(2):
            for p in range(3):
                for c in range(3):
                    values = sorted(o[w, p, c] for o in others)
                    assert medians[j, w, p, c] == pytest.approx(values[1])
        assert np.array_equal(held[j], twins[j])


def test_achievable_floor_is_zero_without_perturbation_and_lies_above_the_floor(scene):
    """σ = 0: every twin ends alike, so their median predicts the held-out one exactly. σ = 1 mm: the median of
    two twins errs at least half the twins' distance on average (the floor bounds every predictor; loosely here)."""
    for omega in ("3", "6"):
        s = scene["sums"][omega]
        assert s["achievable 0 mm"] == 0.0 and s["achievable 1 mm"] > 0.0
        assert s["achievable 1 mm"] >= 0.5 * s["twins 1 mm"] / 2


def test_regions_partition_the_particles_and_the_sums(scene):
    for omega in ("3", "6"):
        s = scene["sums"][omega]
        parts = [f" | {r}" for r in noise_floor.SWEEP_REGIONS]
        assert sum(s["particles" + p] for p in parts) == s["particles"]
        assert s["particles | swept"] > 0 and s["particles | off the path"] > 0
        for name in ("sweep heuristic", "model a", "twins 1 mm", "achievable 1 mm"):
            assert sum(s[name + p] for p in parts) == pytest.approx(s[name])


def test_every_model_is_scored_on_the_same_particles(scene):
    """A model under two names scores the same; another model's weights score differently."""
    for omega in ("3", "6"):
        s = scene["sums"][omega]
        assert s["model a"] == s["model a2"] and s["model a"] != s["model b"]


def test_summary_is_sums_over_particles_and_the_floor_half_the_twins():
    scenes = [{"sums": {"5": {"model m": 0.2, "sweep heuristic": 0.4, "twins 1 mm": 0.1, "particles": 10}}},
              {"sums": {"5": {"model m": 0.1, "sweep heuristic": 0.2, "twins 1 mm": 0.3, "particles": 30}}}]
    got = noise_floor.summarise(scenes, [5], [1.0])["5"]
    assert got["model m"] == pytest.approx(0.3 / 40 * 1000) and got["sweep heuristic"] == pytest.approx(0.6 / 40 * 1000)
    assert got["floor 1 mm"] == pytest.approx(0.4 / 40 * 1000 / 2) and got["particles"] == 40
    assert "| 5 | 15.00 | 7.50 |" in noise_floor.table({"5": got}, [1.0], ["m"])


def test_region_means_divide_by_the_region_particles():
    sums = {"model m": 0.2, "sweep heuristic": 0.4, "twins 1 mm": 0.1, "achievable 1 mm": 0.08, "particles": 10,
            "model m | swept": 0.15, "sweep heuristic | swept": 0.3, "twins 1 mm | swept": 0.06,
            "achievable 1 mm | swept": 0.05, "particles | swept": 2}
    got = noise_floor.summarise([{"sums": {"5": sums}}], [5], [1.0])["5"]
    swept = got["regions"]["swept"]
    assert swept["model m"] == pytest.approx(75.0) and swept["floor 1 mm"] == pytest.approx(15.0)
    assert swept["achievable 1 mm"] == pytest.approx(25.0) and swept["particles"] == 2
    assert got["regions"]["band edge"]["particles"] == 0
    text = noise_floor.table({"5": got}, [1.0], ["m"])
    assert "achievable 1 mm" in text and "| 2.50 |" in text  # model / achievable: 20 / 8
    row = "| 5 | swept | 20% | 150.00 | 75.00 | 30.00 | 15.00 | 25.00 |"
    assert row in noise_floor.region_table({"5": got}, [1.0], ["m"])


def test_plot_writes_a_png(tmp_path):
    summary = {"5": {"model m": 3.0, "sweep heuristic": 4.0, "floor 0.1 mm": 0.5, "floor 1 mm": 1.0}}
    noise_floor.plot(summary, [0.1, 1.0], ["m"], str(tmp_path / "floor.png"))
    assert (tmp_path / "floor.png").read_bytes()[:4] == b"\x89PNG"


def test_models_are_named_by_their_run_folder():
    assert noise_floor.model_name("runs/big/ckpt") == "big" and noise_floor.model_name("runs/x") == "x"
    assert noise_floor.model_name(noise_floor.SHIPPED_DYNAMICS) == "shipped"
