"""Repeatable sums (``models.propagation``, "Repeatable sums"): the fixed-point scatter-add behind every gradient
of the graph network's gathers gives the same bits in any order of addition, within float32's error of the true
sum, and NaN where a float sum would be."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from dynres_jax.models.dynamics import Dynamics, DynamicsConfig
from dynres_jax.models.propagation import FIXED_POINT_BITS, exact_scatter_add, gather_rows


def edges(seed, rows=6, terms=400, channels=5):
    """index [terms], values [terms, channels] with magnitudes spread over nine decades."""
    rng = np.random.default_rng(seed)
    scale = 10.0 ** rng.uniform(-6, 3, (terms, 1))
    return rng.integers(0, rows, terms), (rng.normal(size=(terms, channels)) * scale).astype(np.float32)


@pytest.mark.parametrize("seed", range(3))
def test_sum_is_within_float32_error_of_a_numpy_loop(seed):
    index, values = edges(seed)
    reference = np.zeros((6, values.shape[1]))
    for i, v in zip(index, values, strict=True):
        reference[i] += v.astype(np.float64)
    ours = np.asarray(exact_scatter_add(index, values, 6))
    total = np.abs(values.astype(np.float64)).sum(axis=0)
    counts = np.bincount(index, minlength=6)[:, None]
    # each term rounded to 2^-31 of twice the channel's total, then the sum rounded to float32
    bound = counts * 2.0 ** -FIXED_POINT_BITS * total + np.abs(reference) * 2.0 ** -23
    assert np.all(np.abs(ours - reference) <= bound)


def test_any_order_gives_the_same_bits_where_a_float_scatter_does_not():
    """Permuting the terms leaves every bit of the result; a float32 scatter-add of the same terms in those orders
    differs (so the test would catch a plain float sum)."""
    index, values = edges(7)
    ours = np.asarray(exact_scatter_add(index, values, 6))
    float_sums, rng = [], np.random.default_rng(0)
    for _ in range(5):
        order = rng.permutation(len(index))
        np.testing.assert_array_equal(np.asarray(exact_scatter_add(index[order], values[order], 6)), ours)
        float_sums.append(np.asarray(jnp.zeros((6, 5)).at[index[order]].add(values[order])))
    assert any(np.any(a != float_sums[0]) for a in float_sums[1:])


def test_non_finite_terms_give_nan_not_garbage():
    index, values = edges(1)
    values[3, 2], values[5, 4] = np.nan, np.inf
    ours = np.asarray(exact_scatter_add(index, values, 6))
    assert np.all(np.isnan(ours[:, [2, 4]])) and np.all(np.isfinite(ours[:, [0, 1, 3]]))


def test_zero_terms_sum_to_zero():
    np.testing.assert_array_equal(exact_scatter_add(np.array([0, 2]), np.zeros((2, 3), np.float32), 4),
                                  np.zeros((4, 3)))


def test_gather_rows_is_a_gather_with_the_gathers_gradient():
    rng = np.random.default_rng(2)
    x = jnp.asarray(rng.normal(size=(9, 4)), jnp.float32)
    index = jnp.asarray(rng.integers(0, 9, (9, 3)))
    weights = jnp.asarray(rng.normal(size=(9, 3, 4)), jnp.float32)
    np.testing.assert_array_equal(gather_rows(x, index), x[index])
    ours = jax.grad(lambda x: jnp.sum(jnp.sin(gather_rows(x, index)) * weights))(x)
    plain = jax.grad(lambda x: jnp.sum(jnp.sin(x[index]) * weights))(x)
    np.testing.assert_allclose(ours, plain, rtol=1e-5, atol=1e-6)
    batched = jax.vmap(jax.grad(lambda x: jnp.sum(jnp.sin(gather_rows(x, index)) * weights)))(jnp.stack([x, 2 * x]))
    np.testing.assert_allclose(batched[0], ours, rtol=1e-6)


@pytest.mark.parametrize("processor", ["propnet", "gns"])
def test_model_gradients_equal_autodiff_of_plain_gathers(processor, monkeypatch):
    """The graph network's gradients w.r.t. the pushes and the positions through a two-push rollout (the second
    push gathers predicted positions; GNS gathers sender terms) equal those of the same model with plain indexing
    in place of ``gather_rows``."""
    from dynres_jax.models import dynamics, propagation

    model = Dynamics(DynamicsConfig(hidden=16, processor=processor), rngs=nnx.Rngs(0))
    graphdef, state = nnx.split(model)
    rng = np.random.default_rng(3)
    n = 40
    positions = jnp.asarray(np.c_[rng.uniform(-0.05, 0.05, (n, 2)), rng.uniform(0, 0.01, n)], jnp.float32)
    mask = jnp.asarray(rng.uniform(size=n) < 0.9)
    actions = jnp.asarray([[-0.08, 0.0, 0.04, 0.01], [0.0, -0.08, 0.01, 0.05]], jnp.float32)

    def grads():
        loss = lambda p, a: jnp.sum(jnp.square(dynamics.rollout(graphdef, state, p, mask, a, 0.2)[-1]))  # noqa: E731
        return jax.grad(loss, argnums=(0, 1))(positions, actions)

    ours = grads()
    for module in (dynamics, propagation):
        monkeypatch.setattr(module, "gather_rows", lambda x, index: x[index])
    plain = grads()
    assert float(jnp.abs(ours[0]).max()) > 0 and float(jnp.abs(ours[1]).max()) > 0
    for a, b in zip(ours, plain, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
