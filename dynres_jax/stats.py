"""Statistics of paired evaluations: every method sees the same episodes, so methods are compared episode by episode.

- ``paired_bootstrap``: the mean of per-episode differences with a 95 % percentile-bootstrap interval (episodes
  resampled with replacement, the same draw for both methods: the pairing is kept); ``bootstrap_mean`` of any values.
- ``mcnemar``: the exact McNemar test on paired successes (a two-sided binomial test on the discordant pairs).
- ``wilson``: the 95 % Wilson interval of one success rate.
"""

from __future__ import annotations

from math import comb

import numpy as np

BOOTSTRAP_SAMPLES = 10_000
Z95 = 1.959963984540054


def paired_bootstrap(first, second, *, samples: int = BOOTSTRAP_SAMPLES, seed: int = 0) -> dict:
    """first, second [E]: one value per episode of two methods on the same episodes -> {"mean": mean of
    first - second, "ci95": (lo, hi) its 95 % percentile-bootstrap interval, "episodes": E}."""
    first, second = np.asarray(first, np.float64), np.asarray(second, np.float64)
    if first.shape != second.shape or first.ndim != 1 or len(first) < 2:
        raise ValueError(f"paired values must be two [E] arrays with E >= 2, got {first.shape} and {second.shape}")
    delta = first - second
    return dict(bootstrap_mean(delta, np.random.default_rng(seed), samples), episodes=len(delta))


def bootstrap_mean(values, rng: np.random.Generator, samples: int = BOOTSTRAP_SAMPLES) -> dict:
    """values [E] -> {"mean": their mean, "ci95": (lo, hi) its 95 % percentile-bootstrap interval} (values resampled
    with replacement, ``samples`` times, from ``rng``)."""
    values = np.asarray(values, np.float64)
    draws = rng.integers(0, len(values), size=(samples, len(values)))
    lo, hi = np.percentile(values[draws].mean(axis=1), [2.5, 97.5])
    return dict(mean=float(values.mean()), ci95=(float(lo), float(hi)))


def mcnemar(first, second) -> dict:
    """first, second [E] bool: each episode's success under two methods -> {"first_only": episodes only the first
    solved, "second_only": only the second, "p": exact two-sided McNemar p-value (1 when no pair is discordant)}."""
    first, second = np.asarray(first, bool), np.asarray(second, bool)
    if first.shape != second.shape or first.ndim != 1:
        raise ValueError(f"paired successes must be two [E] arrays, got {first.shape} and {second.shape}")
    b, c = int(np.sum(first & ~second)), int(np.sum(~first & second))
    n = b + c
    p = 1.0 if n == 0 else min(1.0, 2 * sum(comb(n, k) for k in range(min(b, c) + 1)) / 2**n)
    return dict(first_only=b, second_only=c, p=float(p))


def wilson(k: int, n: int) -> tuple[float, float]:
    """95 % Wilson interval of a success rate k / n."""
    p = k / n
    centre = (p + Z95**2 / (2 * n)) / (1 + Z95**2 / n)
    half = Z95 * np.sqrt(p * (1 - p) / n + Z95**2 / (4 * n * n)) / (1 + Z95**2 / n)
    return float(centre - half), float(centre + half)
