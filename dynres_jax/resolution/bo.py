"""Bayesian optimisation of ω per scene (paper Sec. IV-C), which labels the data set of ``resolution.regressor``.

For one scene, ``c+(ω) = c*(ω) + w_R · c(z_0, y_g) · ω`` is observed at a few integer ω in [OMEGA_MIN, OMEGA_MAX]; a
Gaussian process with a Matern-5/2 kernel plus white noise models it (inputs scaled to [0, 1], targets normalised to
zero mean and unit variance), its three hyperparameters (length scale, signal and noise variance, as logs) fitted by
maximising the log marginal likelihood with Adam from several starts. The next ω maximises Expected Improvement over
the untried integers; the label is the argmin of the posterior mean. Every function takes padded observations (x [K],
y [K], mask [K]), so one compiled function serves any number of observations and ``jax.vmap`` runs the BO of many
scenes at once. Masked observations are inert.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.scipy.special import ndtr

from dynres_jax.config import OMEGA_MAX, OMEGA_MIN

W_R = 1e-3  # the reference's weight of the resolution penalty
LOG_BOUNDS = np.log(np.array([[0.03, 3.0], [0.05, 20.0], [1e-4, 1.0]]))  # length scale, signal var, noise var
_JITTER = 1e-6


def scale_omega(omega):
    """ω -> [0, 1] (the GP's input)."""
    return (jnp.asarray(omega, jnp.float32) - OMEGA_MIN) / (OMEGA_MAX - OMEGA_MIN)


def penalised(c_star, c_start, omega, w_r: float = W_R):
    """The BO target c+(ω) = c*(ω) + w_R · c(z_0, y_g) · ω (paper Eq. 8)."""
    return c_star + w_r * c_start * jnp.asarray(omega, jnp.float32)


# ---------------------------------------------------------------------------------------------------------------
# Gaussian process
# ---------------------------------------------------------------------------------------------------------------
def matern52(a, b, lengthscale, variance):
    """Matern-5/2 kernel between a [K] and b [L] (scaled inputs) -> [K, L]."""
    r = jnp.abs(a[:, None] - b[None, :]) / lengthscale
    s = jnp.sqrt(5.0) * r
    return variance * (1.0 + s + s**2 / 3.0) * jnp.exp(-s)


class GP(NamedTuple):
    """A fitted GP over padded observations: x [K] scaled ω, y [K] normalised targets (0 where masked), mask [K],
    y_mean and y_std (the normalisation), log_params [3] (log length scale, signal variance, noise variance)."""

    x: jax.Array
    y: jax.Array
    mask: jax.Array
    y_mean: jax.Array
    y_std: jax.Array
    log_params: jax.Array


def _normalise(y, mask):
    m = mask.astype(jnp.float32)
    n = jnp.maximum(jnp.sum(m), 1.0)
    mean = jnp.sum(y * m) / n
    std = jnp.sqrt(jnp.sum(jnp.square(y - mean) * m) / n)
    std = jnp.where(std > 1e-9, std, 1.0)
    return jnp.where(mask, (y - mean) / std, 0.0), mean, std


def _gram(x, mask, log_params):
    """Masked covariance of the observations: K_f + σ_n² I on valid rows, the identity on masked ones."""
    ls, var, noise = jnp.exp(log_params)
    outer = mask[:, None] & mask[None, :]
    k = matern52(x, x, ls, var) + (noise + _JITTER) * jnp.eye(x.shape[0])
    return jnp.where(outer, k, jnp.eye(x.shape[0]))


def neg_log_marginal_likelihood(log_params, x, y, mask):
    """-log p(y | x, θ) of normalised targets (masked rows contribute nothing)."""
    chol = jnp.linalg.cholesky(_gram(x, mask, log_params))
    alpha = jax.scipy.linalg.cho_solve((chol, True), y)
    n = jnp.sum(mask)
    return 0.5 * y @ alpha + jnp.sum(jnp.log(jnp.diag(chol))) + 0.5 * n * jnp.log(2 * jnp.pi)


def fit_gp(omega, target, mask, key, starts: int = 8, steps: int = 150, noise_floor=0.0) -> GP:
    """Fit the GP to observations omega [K] (integers), target [K] (c+), mask [K]: Adam on the log
    hyperparameters from ``starts`` random starts within LOG_BOUNDS (clipped to them), keeping the best.
    noise_floor: the least noise variance, in target units² (the measured variance of an observation, e.g. of a mean
    of repeated plans); the fitted noise never goes below it (nor below LOG_BOUNDS' floor, nor above its ceiling)."""
    x = scale_omega(omega)
    mask = jnp.asarray(mask, bool)
    y, mean, std = _normalise(jnp.asarray(target, jnp.float32), mask)
    lo, hi = jnp.asarray(LOG_BOUNDS[:, 0]), jnp.asarray(LOG_BOUNDS[:, 1])
    floor = jnp.log(jnp.clip(jnp.asarray(noise_floor, jnp.float32) / jnp.square(std), 1e-30, 1.0))
    lo = lo.at[2].set(jnp.minimum(jnp.maximum(lo[2], floor), hi[2]))
    init = lo + (hi - lo) * jax.random.uniform(key, (starts, 3))
    loss = lambda p: neg_log_marginal_likelihood(p, x, y, mask)  # noqa: E731
    opt = optax.adam(0.05)

    def descend(p):
        def step(carry, _):
            p, state = carry
            updates, state = opt.update(jax.grad(loss)(p), state)
            return (jnp.clip(optax.apply_updates(p, updates), lo, hi), state), None

        return jax.lax.scan(step, (p, opt.init(p)), None, length=steps)[0][0]

    fitted = jax.vmap(descend)(init)
    losses = jax.vmap(loss)(fitted)
    best = fitted[jnp.argmin(jnp.where(jnp.isfinite(losses), losses, jnp.inf))]
    return GP(x, y, mask, mean, std, best)


def posterior(gp: GP, omega):
    """Posterior mean and standard deviation of c+ (original units) at omega [L] -> ([L], [L])."""
    ls, var, _ = jnp.exp(gp.log_params)
    xs = scale_omega(omega)
    chol = jnp.linalg.cholesky(_gram(gp.x, gp.mask, gp.log_params))
    k_star = jnp.where(gp.mask[:, None], matern52(gp.x, xs, ls, var), 0.0)  # [K, L]
    mean = k_star.T @ jax.scipy.linalg.cho_solve((chol, True), gp.y)
    v = jax.scipy.linalg.solve_triangular(chol, k_star, lower=True)
    variance = jnp.maximum(var - jnp.sum(v**2, axis=0), 1e-12)
    return gp.y_mean + gp.y_std * mean, gp.y_std * jnp.sqrt(variance)


def expected_improvement(mean, std, best, xi: float = 0.01):
    """EI for minimisation: E[max(best - f - xi, 0)] under f ~ N(mean, std²) (xi in the targets' units)."""
    gap = best - mean - xi
    z = gap / std
    return gap * ndtr(z) + std * jnp.exp(-0.5 * z**2) / jnp.sqrt(2 * jnp.pi)


CANDIDATES = np.arange(OMEGA_MIN, OMEGA_MAX + 1)  # every integer ω (NumPy: no device work at import)


def next_omega(omega, target, mask, key, noise_floor=0.0):
    """The next ω to try: the untried integer in [OMEGA_MIN, OMEGA_MAX] of largest Expected Improvement over the
    best observed c+ (noise_floor: ``fit_gp``'s). Pure; vmap over scenes."""
    gp = fit_gp(omega, target, mask, key, noise_floor=noise_floor)
    mean, std = posterior(gp, CANDIDATES)
    best = jnp.min(jnp.where(mask, target, jnp.inf))
    ei = expected_improvement(mean, std, best, xi=0.01 * gp.y_std)
    cands = jnp.asarray(CANDIDATES)
    tried = jnp.any((cands[:, None] == jnp.asarray(omega)[None, :]) & jnp.asarray(mask)[None, :], axis=1)
    return cands[jnp.argmax(jnp.where(tried, -jnp.inf, ei))]


def best_omega(omega, target, mask, key, noise_floor=0.0):
    """The BO label: (argmin over integer ω of the GP posterior mean, the mean curve [len(CANDIDATES)];
    noise_floor: ``fit_gp``'s)."""
    mean, _ = posterior(fit_gp(omega, target, mask, key, noise_floor=noise_floor), CANDIDATES)
    return jnp.asarray(CANDIDATES)[jnp.argmin(mean)], mean
