"""The dynamics f(z, u, ω): shapes and size, masks inert, permutation equivariance, vmap/scan consistency, the pure
split/merge API, gradients through edges, bfloat16 edges against float32 and a tiny training run. Small sizes
(N = 24, H = 16) keep it fast on CPU."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import nnx

from dynres_jax.models.dynamics import (
    R_REF,
    REFERENCE,
    Dynamics,
    DynamicsConfig,
    count_params,
    edge_table,
    predict,
    resolution_code,
    rollout,
)
from dynres_jax.models.graph import build_edges, sweep_displacement

N, N_VALID, H = 24, 18, 16


def reference(**fields) -> DynamicsConfig:
    """The paper's architecture (``REFERENCE``: every option off) with ``fields`` changed."""
    return dataclasses.replace(REFERENCE, **fields)

PUSH = np.array([-0.06, 0.0, 0.02, 0.01], np.float32)


def scene(seed=0, n=N, n_valid=N_VALID, half_width=0.04):
    """A compact pile (dense enough for edges) in the first n_valid slots; the padding holds zeros."""
    rng = np.random.default_rng(seed)
    positions = np.zeros((n, 3), np.float32)
    positions[:n_valid, :2] = rng.uniform(-half_width, half_width, (n_valid, 2))
    positions[:n_valid, 2] = 0.007
    return positions, np.arange(n) < n_valid


@pytest.fixture(scope="module")
def split():
    return nnx.split(Dynamics(reference(hidden=H), rngs=nnx.Rngs(0)))


@pytest.fixture(scope="module")
def f(split):
    """Jitted single-scene f with the test model's parameters bound."""
    return jax.jit(functools.partial(predict, *split))


def expected_params(h):
    node_encoder = (5 * h + h) + (h * h + h)
    edge_encoder = (6 * h + h) + 2 * (h * h + h)
    propagators = (3 * h + 1) * h + h + (2 * h + 1) * h + h
    predictor = (h * h + h) + (3 * h + 3)
    return node_encoder + edge_encoder + propagators + predictor


def test_shapes_and_parameter_count(f):
    positions, mask = scene()
    out = f(positions, mask, PUSH, resolution_code(0.01))
    assert out.shape == (N, 3) and out.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(out)))
    paper = count_params(Dynamics(REFERENCE, rngs=nnx.Rngs(0)))
    assert paper == expected_params(64) == 38_403  # the reference's "about 38k"
    assert count_params(Dynamics(rngs=nnx.Rngs(0))) > paper  # the defaults are the shipped model: more inputs
    assert count_params(Dynamics(reference(hidden=H), rngs=nnx.Rngs(0))) == expected_params(H)


def naive_propnet(model, positions, mask, action, code):
    """The architecture written out plainly: concatenated propagator inputs, per-edge products, a loop over nodes'
    incoming edges as a masked sum."""
    cfg = model.config
    clean = jnp.where(mask[:, None], positions, 0.0)
    guess = sweep_displacement(clean, mask, action, cfg.plate_half_width)
    neighbours, edge_mask = build_edges(clean + guess, mask, cfg.edge_radius, cfg.k)
    n, k = neighbours.shape
    ones_n, ones_e = jnp.ones((n, 1)), jnp.ones((n, k, 1))
    node_code = model.node_encoder(jnp.concatenate([guess / cfg.length_scale, ones_n, code * ones_n], -1))
    rel = (clean[:, None] - clean[neighbours]) / cfg.length_scale
    edge_code = model.edge_encoder(jnp.concatenate([ones_e, ones_e, rel, code * ones_e], -1))
    effect = node_code
    for _ in range(cfg.propagation_steps):
        receiver = jnp.broadcast_to(effect[:, None], (n, k, cfg.hidden))
        edge_effect = nnx.relu(model.edge_propagator(
            jnp.concatenate([edge_code, receiver, effect[neighbours], code * ones_e], -1)))
        incoming = jnp.sum(edge_effect * edge_mask[..., None], axis=1)
        effect = nnx.relu(model.node_propagator(jnp.concatenate([node_code, incoming, code * ones_n], -1)) + effect)
    return jnp.where(mask[:, None], positions + model.predictor(effect) * cfg.length_scale, positions)


def test_matches_naive_propnet(split, f):
    """The split-kernel evaluation equals the plain PropNet formulation (a check on the kernel slices' order)."""
    positions, mask = scene(6)
    expected = naive_propnet(nnx.merge(*split), positions, mask, PUSH, 0.7)
    np.testing.assert_allclose(f(positions, mask, PUSH, 0.7), expected, atol=1e-5)


def perturbed(config, scale=0.02, seed=1):
    """nnx.split of a model whose every parameter has N(0, scale²) noise added (so a residual model's correction is
    not zero)."""
    graphdef, state = nnx.split(Dynamics(config, rngs=nnx.Rngs(0)))
    leaves, tree = jax.tree.flatten(state)
    keys = jax.random.split(jax.random.PRNGKey(seed), len(leaves))
    return graphdef, jax.tree.unflatten(tree, [x + scale * jax.random.normal(k, x.shape) for x, k in zip(
        leaves, keys, strict=True)])


@pytest.mark.slow
@pytest.mark.parametrize("config", [reference(hidden=H), reference(residual=True, push_frame=True)])
def test_bfloat16_edges_agree_with_float32(config):
    """bfloat16 edges move predictions by a small fraction of the displacement (measured here: 0.1-0.2 % on average,
    0.4 % at most, e.g. 0.6 mm of 25 cm; 0.03 mm on the shipped checkpoint) and gradients w.r.t. the push by under
    1 %; the output stays float32."""
    graphdef, state = perturbed(config)
    positions, mask = scene(4, n=60, n_valid=50, half_width=0.05)
    code = resolution_code(0.01)

    def f(action, edge_dtype):
        return predict(graphdef, state, positions, mask, action, code, edge_dtype=edge_dtype)

    out = {d: jax.jit(f, static_argnums=1)(PUSH, d) for d in ("float32", "bfloat16")}
    assert out["bfloat16"].dtype == jnp.float32
    error = np.linalg.norm(np.asarray(out["bfloat16"] - out["float32"]), axis=-1)[mask]
    moved = np.linalg.norm(np.asarray(out["float32"]) - positions, axis=-1)[mask]
    assert 0 < error.mean() <= 0.005 * moved.mean() and error.max() <= 0.01 * moved.max(), (error.max(), moved.max())
    np.testing.assert_array_equal(out["bfloat16"][~mask], positions[~mask])
    grads = [np.asarray(jax.jit(jax.grad(lambda a, d=d: jnp.sum(f(a, d)[mask, :2].mean(0) ** 2)))(PUSH))
             for d in ("float32", "bfloat16")]
    assert np.linalg.norm(grads[1] - grads[0]) <= 0.05 * np.linalg.norm(grads[0])


WORLD_EDGES = reference(hidden=H, push_frame=True, world_edges=True, residual=True)
CONTEXT = reference(hidden=H, push_frame=True, world_edges=True, residual=True, bin_position=True)  # all on


@pytest.mark.parametrize("config,edge_dtype", [  # CONTEXT: world edges in float32 too; two cases in the slow tier
    (reference(hidden=H), "float32"), pytest.param(WORLD_EDGES, "bfloat16", marks=pytest.mark.slow),
    pytest.param(CONTEXT, "float32", marks=pytest.mark.slow)])
def test_pair_table_equals_per_edge_codes(config, edge_dtype):
    """Edge codes gathered from the pair table give the per-edge predictions (to float rounding) and gradients
    w.r.t. the push, vmapped over pushes from one padded pile as the planner calls it; a two-push rollout uses the
    table for the first push only; a table built beforehand (``edge_table``, as the planner's per-plan hook) gives the
    same as one built in the call. A model whose edges are in the push frame refuses the table by name."""
    graphdef, state = perturbed(config)
    positions, mask = scene(5, n=40, n_valid=30, half_width=0.05)
    positions[~mask] = np.nan  # padding stays inert with the table too
    rng = np.random.default_rng(0)
    pushes = np.concatenate([rng.uniform(-0.06, 0.0, (6, 2)), rng.uniform(0.0, 0.06, (6, 2))], 1).astype(np.float32)
    code = resolution_code(0.01)

    def run(actions, pair_table, prebuilt=False):  # actions [6, T, 4] -> (positions after each push [6, T, N, 3],
        # summed x of the valid ones at the end)
        table = edge_table(graphdef, state, positions, mask, code, edge_dtype=edge_dtype) if prebuilt else None
        steps = jax.vmap(lambda a: rollout(graphdef, state, positions, mask, a, code, edge_dtype=edge_dtype,
                                           pair_table=pair_table, table=table))(actions)
        return steps, jnp.sum(jnp.where(mask[:, None], steps[:, -1], 0.0)[..., 0], axis=-1)

    actions = np.stack([pushes, pushes[::-1]], 1)  # two pushes: step 0 uses the table, step 1 does without
    (a, _), (b, _), (c, _) = (jax.jit(run, static_argnums=(1, 2))(actions, *t)
                              for t in ((False, False), (True, False), (False, True)))
    np.testing.assert_allclose(b, a, atol=2e-6 if edge_dtype == "float32" else 1e-4)
    np.testing.assert_allclose(c, b, atol=1e-7)
    assert np.all(np.isnan(np.asarray(b)[:, :, ~mask])) and np.all(np.isfinite(np.asarray(b)[:, :, mask]))
    grads = [jax.jit(jax.grad(lambda x, t=t: run(x, t)[1].sum()))(pushes[:, None]) for t in (False, True)]
    np.testing.assert_allclose(grads[1], grads[0], rtol=1e-3, atol=1e-5)
    with pytest.raises(ValueError, match="pair_table needs PropNet edge codes that do not depend on the push"):
        Dynamics(reference(hidden=H, push_frame=True), rngs=nnx.Rngs(0))(positions, mask, PUSH, code,
                                                                              pair_table=True)
    with pytest.raises(ValueError, match="pair_table needs PropNet edge codes that do not depend on the push"):
        Dynamics(reference(hidden=H, push_frame=True), rngs=nnx.Rngs(0)).edge_table(positions, mask, code)


@pytest.mark.parametrize("pair", [False, True])
@pytest.mark.parametrize("k", [4, 200])
def test_incoming_gradient_equals_autodiff_of_the_formula(pair, k):
    """The propagation step's hand-written gradient (``incoming_effects``: receiver terms through the forward pass's
    active-edge counts, sender terms through recomputed active edges) equals autodiff of the plain formula
    Σ_j edge_mask_ij ReLU(c_ij + r_i + s_nij) in every input (r and s side by side), with repeated and masked
    neighbours, on the per-edge constants and on the pair table; with k = 200 most edges are active, so counts pass
    int8's 127."""
    from dynres_jax.models.propagation import incoming_effects

    rng = np.random.default_rng(1)
    n, h = 12, 8
    neighbours = jnp.asarray(rng.integers(0, n, (n, k)), jnp.int32)
    edge_mask = jnp.asarray(rng.uniform(size=(n, k)) < 0.7)
    constant = jnp.asarray(rng.normal(size=(n, n if pair else k, h)) + (4.0 if k > 127 else 0.0), jnp.float32)
    node_terms = jnp.asarray(rng.normal(size=(n, 2 * h)), jnp.float32)  # receiver | sender
    grad = jnp.asarray(rng.normal(size=(n, h)), jnp.float32)

    def formula(c, terms):
        c = jnp.take_along_axis(c, neighbours[..., None], axis=1) if pair else c
        r, s = terms[:, :h], terms[:, h:]
        return jnp.sum(jnp.where(edge_mask[..., None], jax.nn.relu(c + r[:, None] + s[neighbours]), 0.0), axis=1)

    ours = lambda c, terms: incoming_effects(pair, c, neighbours, edge_mask, terms)  # noqa: E731
    (a, vjp_a), (b, vjp_b) = (jax.vjp(f, constant, node_terms) for f in (formula, ours))
    np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-6)
    # the senders' sums are in fixed point, whose error is relative to the channel's total (propagation, "Repeatable
    # sums"), not to each sum: 1e-6 of the largest gradient
    for x, y in zip(vjp_b(grad), vjp_a(grad), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6 * float(np.abs(y).max()))


def test_float32_edges_are_the_default_path(split):
    """edge_dtype="float32" is the default call, op for op (no bfloat16 anywhere); bfloat16 edges put their matrix
    products in bfloat16."""
    positions, mask = scene()
    call = lambda **kw: jax.make_jaxpr(functools.partial(predict, *split, **kw))(positions, mask, PUSH, 0.3)
    assert str(call(edge_dtype="float32")) == str(call()) and "bf16" not in str(call())
    assert "bf16" in str(call(edge_dtype=jnp.bfloat16))
    np.testing.assert_array_equal(predict(*split, positions, mask, PUSH, 0.3, edge_dtype="float32"),
                                  predict(*split, positions, mask, PUSH, 0.3))


def test_resolution_code():
    radii = jnp.array([0.005, R_REF, 0.1])
    codes = resolution_code(radii)
    assert codes.dtype == jnp.float32 and float(codes[1]) == 0.0
    assert np.all(np.diff(np.asarray(codes)) < 0)  # denser sample (smaller r) -> larger code
    np.testing.assert_allclose(codes, 0.5 * np.log((1 / radii**2) / (1 / R_REF**2)), rtol=1e-5)
    assert np.isfinite(float(resolution_code(0.0)))  # the radius of bad perception input


@pytest.mark.parametrize("edge_dtype", ["float32", "bfloat16"])
def test_padding_inert(split, edge_dtype):
    f = jax.jit(functools.partial(predict, *split, edge_dtype=edge_dtype))
    positions, mask = scene()
    code = resolution_code(0.01)
    reference = np.asarray(f(positions, mask, PUSH, code))
    np.testing.assert_array_equal(reference[~mask], positions[~mask])
    rng = np.random.default_rng(1)
    for garbage in (rng.uniform(-1e3, 1e3, (N - N_VALID, 3)), np.zeros((N - N_VALID, 3)) + PUSH[2],
                    np.full((N - N_VALID, 3), np.nan)):
        noisy = positions.copy()
        noisy[~mask] = garbage
        out = np.asarray(f(noisy, mask, PUSH, code))
        np.testing.assert_array_equal(out[mask], reference[mask])
        np.testing.assert_array_equal(out[~mask], noisy[~mask])


@pytest.mark.parametrize("edge_dtype", ["float32", "bfloat16"])
def test_masked_particles_get_no_gradient(split, edge_dtype):
    positions, mask = scene()
    loss = lambda p: jnp.sum(predict(*split, p, mask, PUSH, 0.0, edge_dtype=edge_dtype)[mask] ** 2)
    grad = np.asarray(jax.jit(jax.grad(loss))(jnp.asarray(positions)))
    assert np.all(grad[~mask] == 0) and np.all(np.isfinite(grad)) and np.any(grad[mask] != 0)


def test_permutation_equivariance(f):
    positions, mask = scene(2)
    positions[~mask] = 5.0
    perm = np.random.default_rng(3).permutation(N)
    out = np.asarray(f(positions, mask, PUSH, 0.5))
    out_perm = np.asarray(f(positions[perm], mask[perm], PUSH, 0.5))
    np.testing.assert_allclose(out_perm, out[perm], atol=1e-6)


def check_vmap_over_scenes(split, f, scene, push, valid_in_second):
    """predict vmapped over three scenes (the second cut to ``valid_in_second`` particles: different resolutions in
    one batch), pushes and codes equals one call each; returns (batched, positions, masks, actions, codes)."""
    scenes = [scene(seed) for seed in range(3)]
    positions = np.stack([s[0] for s in scenes])
    masks = np.stack([s[1] for s in scenes])
    masks[1, valid_in_second:] = False
    actions = np.stack([push, push[[2, 3, 0, 1]], np.array([0.0, -0.05, 0.0, 0.03], np.float32)])
    codes = resolution_code(jnp.array([0.01, 0.03, 0.02]))
    batched = jax.jit(jax.vmap(predict, in_axes=(None, None, 0, 0, 0, 0)))(*split, positions, masks, actions, codes)
    for b in range(3):
        np.testing.assert_allclose(batched[b], f(positions[b], masks[b], actions[b], codes[b]), atol=1e-6)
    return batched, positions, masks, actions, codes


def test_vmap_over_scenes_equals_loop(split, f):
    check_vmap_over_scenes(split, f, scene, PUSH, 10)


def test_vmap_over_codes_equals_calls(split, f):
    positions, mask = scene()
    codes = resolution_code(jnp.array([0.005, 0.01, 0.05]))
    batched = jax.jit(jax.vmap(predict, in_axes=(None, None, None, None, None, 0)))(*split, positions, mask, PUSH,
                                                                                      codes)
    singles = [np.asarray(f(positions, mask, PUSH, c)) for c in codes]
    for b in range(3):
        np.testing.assert_allclose(batched[b], singles[b], atol=1e-6)
    assert not np.allclose(singles[0][mask], singles[2][mask])  # the code is used


def test_rollout_equals_chained_predict(split, f):
    positions, mask = scene()
    actions = np.array([PUSH, [0.03, 0.03, -0.02, -0.01], [0.0, -0.05, 0.0, 0.04]], np.float32)
    states = jax.jit(rollout)(*split, positions, mask, actions, 0.2)
    assert states.shape == (3, N, 3)
    current = positions
    for t in range(3):
        current = f(current, mask, actions[t], 0.2)
        np.testing.assert_allclose(states[t], current, atol=1e-5)
    model = nnx.merge(*split)
    np.testing.assert_allclose(model.rollout(positions, mask, actions, 0.2), states, atol=1e-5)
    sequences = np.stack([actions, actions[::-1]])  # vmap over action sequences, as the planner does
    batched = jax.jit(jax.vmap(rollout, in_axes=(None, None, None, None, 0, None)))(*split, positions, mask,
                                                                                      sequences, 0.2)
    np.testing.assert_allclose(batched[0], states, atol=1e-5)
    np.testing.assert_allclose(batched[1], jax.jit(rollout)(*split, positions, mask, actions[::-1], 0.2), atol=1e-5)


def test_far_from_push_deterministic_and_finite(f):
    positions, mask = scene(4, half_width=0.02)
    positions[mask, :2] += 0.15  # the pile sits in a corner; the push is across the bin from it
    action = np.array([-0.15, -0.15, -0.1, -0.15], np.float32)
    assert np.all(sweep_displacement(positions, mask, action, 0.04) == 0)
    first, second = f(positions, mask, action, 0.0), f(positions, mask, action, 0.0)
    np.testing.assert_array_equal(first, second)
    assert np.all(np.isfinite(np.asarray(first)))


def test_split_merge_round_trip(split, f):
    positions, mask = scene()
    model = nnx.merge(*split)
    again = nnx.merge(*nnx.split(model))
    np.testing.assert_array_equal(again(positions, mask, PUSH, 0.1), model(positions, mask, PUSH, 0.1))
    resplit = jax.jit(functools.partial(predict, *nnx.split(again)))
    np.testing.assert_array_equal(resplit(positions, mask, PUSH, 0.1), f(positions, mask, PUSH, 0.1))


def test_gradients_reach_every_layer_and_the_action(split):
    positions, mask = scene()
    graphdef, state = split

    def loss(state, action):
        return jnp.sum(predict(graphdef, state, positions, mask, action, 0.0)[mask] ** 2)

    g_state, g_action = jax.jit(jax.grad(loss, argnums=(0, 1)))(state, jnp.asarray(PUSH))
    for path, leaf in jax.tree_util.tree_leaves_with_path(g_state):
        assert np.all(np.isfinite(leaf)) and np.any(leaf != 0), jax.tree_util.keystr(path)
    assert np.all(np.isfinite(g_action)) and np.any(g_action != 0)


def test_training_reduces_loss():
    """100 Adam steps fit next = current + sweep displacement on a few scenes and pushes: the loss drops >= 5x."""
    rng = np.random.default_rng(5)
    scenes = [scene(seed, n_valid=int(rng.integers(8, N + 1))) for seed in range(4)]
    positions = jnp.asarray(np.stack([s[0] for s in scenes]))
    masks = jnp.asarray(np.stack([s[1] for s in scenes]))
    starts = rng.uniform(-0.06, 0.0, (4, 2))
    actions = jnp.asarray(np.concatenate([starts, starts + rng.uniform(0.0, 0.05, (4, 2))], 1), jnp.float32)
    codes = resolution_code(jnp.array([0.01, 0.02, 0.015, 0.03]))
    targets = positions + jax.vmap(sweep_displacement, in_axes=(0, 0, 0, None))(positions, masks, actions, 0.04)

    graphdef, state = nnx.split(Dynamics(reference(hidden=H), rngs=nnx.Rngs(1)))
    optimiser = optax.adam(3e-3)

    def loss_fn(state):
        pred = jax.vmap(predict, in_axes=(None, None, 0, 0, 0, 0))(graphdef, state, positions, masks, actions, codes)
        err = jnp.sum(jnp.square(pred - targets), axis=-1)
        return jnp.sum(jnp.where(masks, err, 0.0)) / jnp.sum(masks)

    @jax.jit
    def train(state):
        def step(carry, _):
            state, opt_state = carry
            loss, grads = jax.value_and_grad(loss_fn)(state)
            updates, opt_state = optimiser.update(grads, opt_state, state)
            return (optax.apply_updates(state, updates), opt_state), loss

        (state, _), losses = jax.lax.scan(step, (state, optimiser.init(state)), length=100)
        return loss_fn(state), losses

    final, losses = train(state)
    assert np.isfinite(float(final)) and float(final) * 5 <= float(losses[0]), (float(losses[0]), float(final))


def test_residual_model_starts_as_the_sweep_heuristic_and_push_frame_is_rotation_invariant():
    """residual: an untrained model predicts exactly the sweep heuristic (padding untouched); push_frame: rotating
    the scene and the push together about the origin rotates the prediction (the model sees only the push frame)."""
    from dynres_jax.models.graph import sweep_displacement

    p = jax.random.uniform(jax.random.PRNGKey(0), (20, 3), minval=-0.05, maxval=0.05).at[:, 2].set(0.005)
    mask = jnp.ones(20, bool).at[-3:].set(False)
    a = jnp.array([-0.06, 0.0, 0.06, 0.02])
    model = Dynamics(reference(residual=True, push_frame=True), rngs=nnx.Rngs(0))
    clean = jnp.where(mask[:, None], p, 0.0)
    np.testing.assert_allclose(np.asarray(model(p, mask, a, 0.3)),
                               np.asarray(p + jnp.where(mask[:, None], sweep_displacement(
                                   clean, mask, a, model.config.plate_half_width), 0.0)), atol=1e-7)
    trained = Dynamics(reference(push_frame=True), rngs=nnx.Rngs(1))
    c, s = np.cos(0.7), np.sin(0.7)
    rot = jnp.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], jnp.float32)
    turned = trained(p @ rot.T, mask, jnp.concatenate([a[:2] @ rot[:2, :2].T, a[2:] @ rot[:2, :2].T]), 0.3)
    np.testing.assert_allclose(np.asarray(turned), np.asarray(trained(p, mask, a, 0.3) @ rot.T), atol=2e-5)


def test_bin_position_breaks_translation_invariance_only_where_asked():
    """Push-frame nodes with world-frame edges see only relative positions: moving the scene and the push together
    moves the prediction with them. bin_position adds where the particles are in the bin, so the same move changes
    what the model predicts (it can learn the walls); padding stays inert either way."""
    p = jax.random.uniform(jax.random.PRNGKey(2), (20, 3), minval=-0.05, maxval=0.05).at[:, 2].set(0.005)
    mask = jnp.ones(20, bool).at[-3:].set(False)
    a = jnp.array([-0.06, 0.0, 0.06, 0.02])
    shift = jnp.array([0.08, -0.05, 0.0])
    for bin_position in (False, True):
        model = Dynamics(reference(hidden=H, push_frame=True, world_edges=True, bin_position=bin_position),
                         rngs=nnx.Rngs(3))
        moved = model(p + shift, mask, a + jnp.tile(shift[:2], 2), 0.3) - shift
        here = model(p, mask, a, 0.3)
        gap = float(jnp.abs(moved - here)[mask].max())
        assert (gap > 1e-3) if bin_position else (gap < 1e-5), (bin_position, gap)
        garbage = p.at[~mask].set(1e4)
        np.testing.assert_array_equal(np.asarray(model(garbage, mask, a, 0.3))[np.asarray(mask)],
                                      np.asarray(here)[np.asarray(mask)])


@pytest.fixture(scope="module")
def context_split():
    return perturbed(CONTEXT)


def test_context_options_keep_padding_inert_equivariance_and_vmap(context_split):
    """With every option on (the shipped model's): garbage (even NaN) in padded rows changes nothing, the output is
    permutation equivariant and vmap over scenes of different resolutions equals one call each."""
    f = jax.jit(functools.partial(predict, *context_split))
    positions, mask = scene(4)
    reference = np.asarray(f(positions, mask, PUSH, 0.4))
    garbage = positions.copy()
    garbage[~mask] = np.nan
    out = np.asarray(f(garbage, mask, PUSH, 0.4))
    np.testing.assert_array_equal(out[mask], reference[mask])
    assert np.all(np.isnan(out[~mask]))
    perm = np.random.default_rng(5).permutation(N)
    np.testing.assert_allclose(np.asarray(f(positions[perm], mask[perm], PUSH, 0.4)), reference[perm], atol=1e-6)
    check_vmap_over_scenes(context_split, f, scene, PUSH, 10)


GNS = reference(hidden=H, processor="gns", propagation_steps=2, residual=True)


def _np_mlp(layers, x):
    """A Sequential of Linear / relu / LayerNorm layers in NumPy (float64)."""
    for layer in layers:
        if isinstance(layer, nnx.Linear):
            x = x @ np.asarray(layer.kernel[...], np.float64) + np.asarray(layer.bias[...], np.float64)
        elif isinstance(layer, nnx.LayerNorm):
            mean, var = x.mean(-1, keepdims=True), x.var(-1, keepdims=True)
            x = (x - mean) / np.sqrt(var + layer.epsilon) * np.asarray(layer.scale[...]) + np.asarray(layer.bias[...])
        elif isinstance(layer, nnx.Sequential):
            x = _np_mlp(layer.layers, x)
        else:
            x = np.maximum(x, 0.0)
    return x


def numpy_gns(model, positions, mask, action, code):
    """GNS written out with NumPy loops over nodes and their edges: concatenated [edge, receiver, sender] inputs to
    each step's edge MLP, messages summed per receiver, residuals on nodes and edges."""
    cfg = model.config
    clean = np.where(mask[:, None], positions, 0.0)
    guess = np.asarray(sweep_displacement(clean, mask, action, cfg.plate_half_width), np.float64)
    neighbours, edge_mask = (np.asarray(x) for x in build_edges(clean + guess, mask, cfg.edge_radius, cfg.k))
    n, k = neighbours.shape
    nodes = _np_mlp(model.node_encoder.layers, np.concatenate([guess / cfg.length_scale, np.ones((n, 1)),
                                                               code * np.ones((n, 1))], -1))
    edges = np.zeros((n, k, cfg.hidden))
    for i in range(n):
        for e in range(k):
            rel = (clean[i] - clean[neighbours[i, e]]) / cfg.length_scale
            edges[i, e] = _np_mlp(model.edge_encoder.layers, np.concatenate([rel, [np.linalg.norm(rel), code]]))
    for step in model.steps.layers:
        new_edges, summed = edges.copy(), np.zeros((n, cfg.hidden))
        for i in range(n):
            for e in range(k):
                if edge_mask[i, e]:
                    x = np.concatenate([edges[i, e], nodes[i], nodes[neighbours[i, e]]])
                    m = _np_mlp([step.edge_in, "relu", step.edge_out, step.edge_norm], x)
                    new_edges[i, e] += m
                    summed[i] += m
        nodes = nodes + _np_mlp([step.node_mlp, step.node_norm], np.concatenate([nodes, summed], -1))
        edges = new_edges
    out = positions + _np_mlp(model.predictor.layers, nodes) * cfg.length_scale + guess
    return np.where(mask[:, None], out, positions)


def test_gns_matches_a_numpy_loop():
    """The GNS processor (split first layer, gathered sender terms, masked messages) equals a plain loop over every
    node and edge; perturbed parameters, so every layer matters."""
    graphdef, state = perturbed(GNS, scale=0.1)
    positions, mask = scene(8)
    got = jax.jit(predict)(graphdef, state, positions, mask, PUSH, 0.3)
    expected = numpy_gns(nnx.merge(graphdef, state), positions, mask, PUSH, 0.3)
    np.testing.assert_allclose(np.asarray(got), expected, atol=2e-5)
    assert np.abs(expected - positions)[mask].max() > 1e-3  # the push moves particles


def test_gns_padding_is_inert_and_the_planner_runs_it():
    """Padding slots (holding garbage) change no valid particle's prediction; the planner's dynamics (no pair table
    for gns) rolls the model out as predict does; bfloat16 edges and pair tables are refused."""
    from dynres_jax.models.registry import learned_dynamics

    graphdef, state = perturbed(GNS, scale=0.1)
    positions, mask = scene(9, n=N, n_valid=N_VALID)
    small = jax.jit(predict)(graphdef, state, positions[:N_VALID], mask[:N_VALID], PUSH, 0.3)
    garbage = positions.copy()
    garbage[N_VALID:] = 7.0
    large = jax.jit(predict)(graphdef, state, garbage, mask, PUSH, 0.3)
    np.testing.assert_allclose(np.asarray(large[:N_VALID]), np.asarray(small), atol=1e-5)
    model = nnx.merge(graphdef, state)
    radius = R_REF * np.exp(-0.3)
    planned = learned_dynamics(model)(radius)(positions, mask, PUSH[None])
    np.testing.assert_allclose(np.asarray(planned[0]), np.asarray(predict(graphdef, state, positions, mask, PUSH,
                                                                          resolution_code(radius))), atol=1e-6)
    with pytest.raises(ValueError, match="float32 only"):
        predict(graphdef, state, positions, mask, PUSH, 0.3, edge_dtype=jnp.bfloat16)
    with pytest.raises(ValueError, match="gns processor has none"):
        predict(graphdef, state, positions, mask, PUSH, 0.3, pair_table=True)
    with pytest.raises(ValueError, match="processor must be one of"):
        DynamicsConfig(processor="mlp")
