"""The CNN-dynamics baseline: the sweep heuristic when untrained, masks inert, vmap, gradients in the action, the
splat against NumPy, training and checkpoints through ``train``, and its evaluation method. Small sizes (G = 16,
C = 8) keep it fast on CPU; the tiny data set is test_train's fixture."""

import dataclasses
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import test_dynamics
from flax import nnx
from test_dynamics import N_VALID, N
from test_train import CFG, shards  # noqa: F401  (shards: the module-scoped tiny data set)

from dynres_jax.commands import eval_dynamics, evaluate, train_dynamics
from dynres_jax.io import ckpt
from dynres_jax.learn import targets
from dynres_jax.learn.train import TrainConfig, card, make_step, resident, train
from dynres_jax.models.cnn_dynamics import PILE_SHARE, CNNDynamics, CNNDynamicsConfig, sample, splat, tent_weights
from dynres_jax.models.dynamics import Dynamics, count_params, predict, resolution_code
from dynres_jax.models.graph import sweep_rollout
from dynres_jax.models.registry import SHIPPED_DYNAMICS, build_model, load_dynamics, make_model

SMALL = CNNDynamicsConfig(grid=16, channels=8)
HW = SMALL.bin_half_width
PUSH = np.array([-0.06, 0.0, 0.03, 0.01], np.float32)
scene = functools.partial(test_dynamics.scene, half_width=0.05)  # the GNN tests' padded pile, a little wider


def perturbed(config=SMALL, seed=1):
    """A model whose zero-initialised head is redrawn, as after some training: its field is not zero."""
    model = CNNDynamics(config, rngs=nnx.Rngs(seed))
    kernel = model.head.kernel[...]
    model.head.kernel[...] = 0.1 * jax.random.normal(jax.random.PRNGKey(seed), kernel.shape)
    return model


@pytest.fixture(scope="module")
def split():
    return nnx.split(perturbed())


@pytest.fixture(scope="module")
def f(split):
    return jax.jit(functools.partial(predict, *split))


def expected_params(g_channels):
    c = g_channels
    conv = lambda n_in, n_out, k=3: k * k * n_in * n_out + n_out  # noqa: E731
    return conv(4, c) + 5 * conv(c, c) + 2 * conv(2 * c, c) + conv(c, 2, 1)


def test_parameter_count_and_bad_config():
    default = count_params(nnx.eval_shape(lambda: CNNDynamics(rngs=nnx.Rngs(0))))
    assert default == expected_params(32) == 84_418
    assert count_params(nnx.eval_shape(lambda: CNNDynamics(SMALL, rngs=nnx.Rngs(0)))) == expected_params(8)
    for bad, message in ((dict(grid=10), "grid must be a multiple of 4"), (dict(grid=4), r"in \[8, 512\]"),
                         (dict(grid=4096), r"in \[8, 512\]"), (dict(channels=0), r"channels must be in \[1, 4096\]"),
                         (dict(channels=10**6), "channels must be in"), (dict(length_scale=0.0), "length_scale"),
                         (dict(length_scale=5.0), "at most 1 m"),
                         (dict(grid=8.0), "CNNDynamicsConfig.grid must be an int")):
        with pytest.raises((ValueError, TypeError), match=message):
            CNNDynamicsConfig(**bad)


def test_untrained_residual_model_is_the_sweep_heuristic():
    positions, mask = scene()
    actions = np.array([PUSH, [0.03, 0.04, -0.02, -0.02], [0.0, -0.05, 0.0, 0.04]], np.float32)
    model = CNNDynamics(SMALL, rngs=nnx.Rngs(0))
    got = np.asarray(model.rollout(positions, mask, actions, resolution_code(0.01)))
    expected = np.asarray(sweep_rollout(jnp.asarray(positions), mask, actions, SMALL.plate_half_width))
    np.testing.assert_allclose(got, expected, atol=1e-6)
    assert np.any(np.abs(got[0] - positions)[mask] > 1e-3)  # the push moves something
    np.testing.assert_array_equal(got[:, ~mask], np.broadcast_to(positions[~mask], got[:, ~mask].shape))


def test_padding_inert(f):
    positions, mask = scene()
    reference = np.asarray(f(positions, mask, PUSH, 0.3))
    np.testing.assert_array_equal(reference[~mask], positions[~mask])
    rng = np.random.default_rng(1)
    for garbage in (rng.uniform(-1e3, 1e3, (N - N_VALID, 3)), np.full((N - N_VALID, 3), np.nan)):
        noisy = positions.copy()
        noisy[~mask] = garbage
        out = np.asarray(f(noisy, mask, PUSH, 0.3))
        np.testing.assert_array_equal(out[mask], reference[mask])
        np.testing.assert_array_equal(out[~mask], noisy[~mask])
    longer = np.concatenate([positions, np.full((5, 3), np.nan, np.float32)])  # more slots, same particles
    out = np.asarray(jax.jit(functools.partial(predict, *nnx.split(perturbed())))(
        longer, np.concatenate([mask, np.zeros(5, bool)]), PUSH, 0.3))
    np.testing.assert_allclose(out[:N][mask], reference[mask], atol=1e-6)


def test_vmap_over_scenes_equals_loop(split, f):
    batched, positions, masks, actions, codes = test_dynamics.check_vmap_over_scenes(split, f, scene, PUSH, 6)
    assert not np.allclose(batched[0], f(positions[0], masks[0], actions[0], codes[2]))  # the code is used


def test_gradient_in_the_action_is_finite_and_nonzero():
    """Through the network alone (non-residual: the sweep enters only as the image's displacement channels); a
    zero-length push, the sweep's degenerate case, keeps it finite."""
    positions, mask = scene()
    graphdef, state = nnx.split(CNNDynamics(dataclasses.replace(SMALL, residual=False), rngs=nnx.Rngs(2)))
    loss = lambda a: jnp.sum(predict(graphdef, state, positions, mask, a, 0.0)[mask, :2] ** 2)  # noqa: E731
    grads = np.asarray(jax.jit(jax.vmap(jax.grad(loss)))(jnp.asarray(np.stack([PUSH, np.zeros(4, np.float32)]))))
    assert np.all(np.isfinite(grads)) and np.any(np.abs(grads[0]) > 1e-6), grads


def numpy_splat(positions, grid, half_width):
    """Brute force: every particle adds the tent weights max(0, 1 - |u - ix|) max(0, 1 - |v - iy|) to every cell,
    (u, v) its position in cell-centre units clamped to [0, G - 1]."""
    c = 2 * half_width / grid
    uv = np.clip((positions[:, :2].astype(np.float64) + half_width) / c - 0.5, 0, grid - 1)
    image = np.zeros((grid, grid))
    for u, v in uv:
        for iy in range(grid):
            for ix in range(grid):
                image[iy, ix] += max(0.0, 1 - abs(u - ix)) * max(0.0, 1 - abs(v - iy))
    return image


def test_splat_conserves_mass_and_matches_numpy():
    rng = np.random.default_rng(3)
    positions, mask = scene(4, n=40, n_valid=33, half_width=HW)  # the whole bin, walls' half-cells included
    positions[0, :2] = [HW, -HW]  # corners and a cell centre exactly
    positions[1, :2] = [-HW, HW - 1e-4]
    positions[2, :2] = [-HW + HW / SMALL.grid, 0.0]
    positions[~mask] = rng.uniform(-1, 1, (40 - 33, 3))  # padding far outside the bin deposits nothing
    image = np.asarray(splat(positions, mask, SMALL.grid, HW))
    total = PILE_SHARE * SMALL.grid**2
    np.testing.assert_allclose(image.sum(), total, rtol=1e-5)
    expected = numpy_splat(positions[mask], SMALL.grid, HW) * total / mask.sum()
    np.testing.assert_allclose(image, expected, atol=1e-5)
    assert np.all(np.asarray(splat(positions, np.zeros(40, bool), SMALL.grid, HW)) == 0)  # no particle: empty
    wx, wy = tent_weights(jnp.asarray(positions), SMALL.grid, HW)
    for w in (np.asarray(wx), np.asarray(wy)):
        np.testing.assert_allclose(w.sum(1), 1.0, rtol=1e-6)
        assert np.all(w >= 0) and np.all(np.sum(w > 0, axis=1) <= 2)


def test_sample_is_exact_on_linear_fields():
    """Bilinear sampling reproduces a linear field at any point inside the square of cell centres."""
    g = SMALL.grid
    c = 2 * HW / g
    axis = -HW + (np.arange(g) + 0.5) * c
    y, x = np.meshgrid(axis, axis, indexing="ij")
    field = np.stack([2 * x - 3 * y + 0.1, x + 0.5 * y], axis=-1).astype(np.float32)  # [G, G, 2]
    pts = np.random.default_rng(5).uniform(-HW + c / 2, HW - c / 2, (50, 2)).astype(np.float32)
    got = np.asarray(sample(jnp.asarray(field), jnp.asarray(pts), HW))
    expected = np.stack([2 * pts[:, 0] - 3 * pts[:, 1] + 0.1, pts[:, 0] + 0.5 * pts[:, 1]], -1)
    np.testing.assert_allclose(got, expected, atol=1e-5)


CNN_CFG = dataclasses.replace(CFG, steps=8, eval_every=8, ckpt_every=8, lr=3e-3, model=SMALL)


@pytest.fixture(scope="module")
def cnn_run(shards, tmp_path_factory):  # noqa: F811
    out = tmp_path_factory.mktemp("cnn_run")
    return str(out), train(CNN_CFG, shards, str(out), progress=False)


@pytest.mark.slow
def test_training_reduces_the_loss_and_the_checkpoint_restores(cnn_run, shards):  # noqa: F811
    """The rollout loss over the batches training saw (replayed: a step's batch depends on (seed, step) only) is
    lower with the checkpoint's parameters than with the initial ones (the sweep heuristic)."""
    out, last = cnn_run
    assert np.isfinite(last["val_rmse_mm"])
    model, meta, _ = ckpt.load_module(f"{out}/ckpt", build_model)
    assert isinstance(model, CNNDynamics) and meta["model_class"] == "cnn" and meta["step"] == CNN_CFG.steps
    assert model.config == SMALL
    train_set = targets.load_shards(shards, "train")
    graphdef, initial = nnx.split(make_model(SMALL, CNN_CFG.seed))
    _, loss = make_step(graphdef, optax.adam(0.0), train_set.camera, CNN_CFG)
    key = jax.random.PRNGKey(CNN_CFG.seed)
    frames, keys = resident(train_set), [jax.random.fold_in(key, i) for i in range(CNN_CFG.steps)]
    before = np.mean([float(loss(initial, frames, k)["mse"]) for k in keys])
    after = np.mean([float(loss(nnx.split(model)[1], frames, k)["mse"]) for k in keys])
    assert after < before, (before, after)
    _, n_max, name = load_dynamics("learned", f"{out}/ckpt", SMALL.plate_half_width)  # the planner's loader
    assert n_max == CNN_CFG.n_max and f"step {CNN_CFG.steps}" in name


def test_checkpoint_round_trip_is_bit_identical(tmp_path):
    model = perturbed(seed=7)
    cfg = dataclasses.replace(CNN_CFG, model=SMALL)
    ckpt.save_module(tmp_path / "ckpt", 3, model, card(cfg, step=3))
    restored, meta, _ = ckpt.load_module(tmp_path / "ckpt", build_model)
    assert type(restored) is CNNDynamics and meta["model_class"] == "cnn"
    positions, mask = scene(2)
    f = jax.jit(predict)
    np.testing.assert_array_equal(np.asarray(f(*nnx.split(restored), positions, mask, PUSH, 0.4)),
                                  np.asarray(f(*nnx.split(model), positions, mask, PUSH, 0.4)))


def test_shipped_gnn_card_still_builds_a_dynamics():
    meta = ckpt.load_meta(SHIPPED_DYNAMICS)
    legacy = {k: v for k, v in meta.items() if k != "model_class"}  # cards written before the CNN existed: gnn
    assert meta["model_class"] == "gnn" and type(build_model(legacy)) is Dynamics
    model, _, _ = ckpt.load_module(SHIPPED_DYNAMICS, build_model)
    assert type(model) is Dynamics and model.config.residual and model.config.push_frame
    with pytest.raises(ValueError, match="model_class"):
        build_model({**meta, "model_class": "transformer"})
    with pytest.raises(ValueError, match="DynamicsConfig or a CNNDynamicsConfig"):
        TrainConfig(model=dict(hidden=3))


@pytest.mark.slow  # 60 s on the 2-core CPU: CI's second tier
def test_eval_dynamics_on_a_cnn_checkpoint(cnn_run, shards, tmp_path):  # noqa: F811
    out, _ = cnn_run
    result = eval_dynamics.main(["--ckpt", f"{out}/ckpt", "--data", shards, "--out", str(tmp_path),
                                 "--omegas", "8", "--windows", "4"])
    for method in eval_dynamics.METHODS:
        assert len(result["omegas"]["8"][method]) == CNN_CFG.horizon and all(np.isfinite(result["omegas"]["8"][method]))


def test_command_lines_name_the_problem(tmp_path, capsys):
    missing = str(tmp_path / "no_cnn_here")
    with pytest.raises(SystemExit):
        evaluate.main(["--methods", "50", "cnn", "--cnn-ckpt", missing, "--out", str(tmp_path / "eval")])
    assert missing in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a GNN checkpoint is not a CNN one
        evaluate.main(["--methods", "cnn", "--cnn-ckpt", SHIPPED_DYNAMICS, "--out", str(tmp_path / "eval")])
    assert "not a cnn" in capsys.readouterr().err
    assert not os.path.exists(tmp_path / "eval")
    for argv in (["--model", "cnn", "--hidden", "8"], ["--model", "gnn", "--grid", "16"], ["--model", "cnn",
                                                                                          "--grid", "10"]):
        with pytest.raises(SystemExit):
            train_dynamics.main(["--data", str(tmp_path), "--out", str(tmp_path / "run"), *argv])
        assert capsys.readouterr().err.strip().splitlines()[-1].count("error") == 1
