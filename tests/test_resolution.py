"""Bayesian optimisation of ω and the regressor g, against hand computations."""

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from dynres_jax.config import OMEGA_MAX, OMEGA_MIN
from dynres_jax.resolution import bo as res
from dynres_jax.resolution import regressor as g


def matern_np(a, b, ls, var):
    k = np.zeros((len(a), len(b)))
    for i, x in enumerate(a):
        for j, y in enumerate(b):
            s = math.sqrt(5) * abs(x - y) / ls
            k[i, j] = var * (1 + s + s * s / 3) * math.exp(-s)
    return k


def test_posterior_equals_the_textbook_formula_and_padding_is_inert():
    omega = np.array([2, 25, 50, 75, 100, 40])
    target = np.array([3.0, 1.0, 0.5, 0.8, 2.0, 0.7])
    params = np.log([0.3, 1.5, 0.01])
    mask = np.array([True] * 6)
    y, mean, std = res._normalise(jnp.asarray(target), jnp.asarray(mask))
    gp = res.GP(res.scale_omega(omega), y, jnp.asarray(mask), mean, std, jnp.asarray(params))
    xs = np.array([10, 33, 60, 99])
    mu, sd = res.posterior(gp, xs)
    # by hand, in NumPy float64
    x, xq = (omega - 2) / 98, (xs - 2) / 98
    yn = (target - target.mean()) / target.std()
    k = matern_np(x, x, 0.3, 1.5) + (0.01 + 1e-6) * np.eye(6)
    ks = matern_np(x, xq, 0.3, 1.5)
    m_ref = ks.T @ np.linalg.solve(k, yn) * target.std() + target.mean()
    v_ref = 1.5 - np.einsum("ij,ij->j", ks, np.linalg.solve(k, ks))
    np.testing.assert_allclose(np.asarray(mu), m_ref, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(sd), np.sqrt(v_ref) * target.std(), rtol=1e-3, atol=1e-4)
    nll = res.neg_log_marginal_likelihood(jnp.asarray(params), jnp.asarray(x, jnp.float32), y, jnp.asarray(mask))
    ref = 0.5 * yn @ np.linalg.solve(k, yn) + 0.5 * np.linalg.slogdet(k)[1] + 3 * math.log(2 * math.pi)
    np.testing.assert_allclose(float(nll), ref, rtol=1e-4)
    # two garbage observations behind the mask change nothing
    pad = lambda a, v: np.concatenate([a, v])  # noqa: E731
    y2, mean2, std2 = res._normalise(jnp.asarray(pad(target, [1e6, -5.0])), jnp.asarray(pad(mask, [False, False])))
    gp2 = res.GP(res.scale_omega(pad(omega, [7, 8])), y2, jnp.asarray(pad(mask, [False, False])), mean2, std2,
                 jnp.asarray(params))
    mu2, sd2 = res.posterior(gp2, xs)
    np.testing.assert_allclose(np.asarray(mu2), np.asarray(mu), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(sd2), np.asarray(sd), rtol=1e-4)


def test_expected_improvement_by_hand():
    mean, std, best = 1.0, 0.5, 1.2
    gap = best - mean - 0.01
    z = gap / std
    ref = gap * 0.5 * (1 + math.erf(z / math.sqrt(2))) + std * math.exp(-z * z / 2) / math.sqrt(2 * math.pi)
    np.testing.assert_allclose(float(res.expected_improvement(mean, std, best)), ref, rtol=1e-5)


def test_bayesian_optimisation_finds_the_minimum_of_a_known_curve():
    """Ten evaluations of a smooth curve with its minimum at ω = 37 (the reference's schedule: five fixed starts,
    then EI), vmapped over two scenes whose curves differ: each label lands near its own minimum."""
    curve = lambda w, m: ((w - m) / 30.0) ** 2  # noqa: E731
    minima = jnp.array([37.0, 80.0])
    k = 10
    omega = jnp.zeros((2, k), jnp.int32).at[:, :5].set(jnp.array([2, 25, 50, 75, 100]))
    mask = jnp.zeros((2, k), bool).at[:, :5].set(True)
    target = jnp.where(mask, curve(omega, minima[:, None]), 0.0)
    step = jax.jit(jax.vmap(res.next_omega))
    for i in range(5, k):
        nxt = step(omega, target, mask, jax.random.split(jax.random.PRNGKey(i), 2))
        assert not jnp.any((omega == nxt[:, None]) & mask).item()  # never an ω already tried
        omega, mask = omega.at[:, i].set(nxt), mask.at[:, i].set(True)
        target = target.at[:, i].set(curve(nxt, minima))
    label, mean = jax.vmap(res.best_omega)(omega, target, mask, jax.random.split(jax.random.PRNGKey(0), 2))
    assert mean.shape == (2, 99)
    assert abs(int(label[0]) - 37) <= 3 and abs(int(label[1]) - 80) <= 3


def test_regressor_input_channels_and_distance_transform_by_brute_force():
    rng = np.random.default_rng(0)
    cur = np.zeros((64, 64), bool)
    cur[8:20, 30:50] = True
    goal = rng.uniform(size=(64, 64)) > 0.995
    x = np.asarray(g.regressor_input(cur, goal, size=16))
    assert x.shape == (16, 16, 6)
    cells = cur.reshape(16, 4, 16, 4).mean(axis=(1, 3))
    np.testing.assert_allclose(x[..., 0], cells)
    occ = np.argwhere(cells > 0.5)
    for i in range(16):
        for j in range(16):
            ref = min(math.hypot(i - a, j - b) for a, b in occ) / 16
            assert abs(x[i, j, 2] - min(ref, math.sqrt(2))) < 1e-5
    np.testing.assert_allclose(x[..., 4], np.maximum(x[..., 0] - x[..., 1], 0))


def test_regressor_range_and_choose_omega_batches():
    model = g.Regressor(width=4, rngs=nnx.Rngs(0))
    masks = jnp.asarray(np.random.default_rng(1).uniform(size=(3, 64, 64)) > 0.7)
    omega = g.choose_omega(*nnx.split(model), jax.vmap(g.regressor_input)(masks, masks[::-1]))
    assert omega.shape == (3,) and omega.dtype == jnp.int32
    assert np.all((np.asarray(omega) >= OMEGA_MIN) & (np.asarray(omega) <= OMEGA_MAX))
    x = g.regressor_input(masks[1], masks[1])
    one = g.choose_omega(*nnx.split(model), x)
    assert int(one) == int(np.clip(np.round(float(model(x))), 2, 100))


def test_gp_noise_never_below_the_measured_floor():
    """With a noise floor (target units²) the fitted noise variance, back in target units, is at least the floor;
    a floor of 0 fits as before; a floor beyond the target's variance is held at LOG_BOUNDS' ceiling."""
    omega = jnp.array([2, 25, 50, 75, 100, 37, 60, 0])
    target = jnp.sin(omega / 15.0) * 3.0 + 10.0
    mask = jnp.arange(8) < 7
    key = jax.random.PRNGKey(0)
    plain = res.fit_gp(omega, target, mask, key)
    np.testing.assert_array_equal(res.fit_gp(omega, target, mask, key, noise_floor=0.0).log_params, plain.log_params)
    assert float(jnp.exp(plain.log_params[2]) * plain.y_std**2) < 0.5  # a smooth curve: little noise fitted
    for floor in (0.5, 2.0):
        gp = res.fit_gp(omega, target, mask, key, noise_floor=floor)
        assert float(jnp.exp(gp.log_params[2]) * gp.y_std**2) >= floor * (1 - 1e-4)
    huge = res.fit_gp(omega, target, mask, key, noise_floor=1e6)
    np.testing.assert_allclose(float(huge.log_params[2]), res.LOG_BOUNDS[2, 1], rtol=1e-6)
