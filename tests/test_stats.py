"""Paired statistics of the evaluation against hand computations and a plain loop."""

import numpy as np
import pytest

from dynres_jax.stats import mcnemar, paired_bootstrap, wilson


def test_mcnemar_by_hand():
    first = np.array([1, 1, 0, 0, 0, 0, 0, 0, 1, 1], bool)  # only here: episode 0; only in second: 2-6
    second = np.array([0, 1, 1, 1, 1, 1, 1, 0, 1, 1], bool)
    out = mcnemar(first, second)
    assert (out["first_only"], out["second_only"]) == (1, 5)
    assert out["p"] == pytest.approx(2 * (1 + 6) / 2**6)  # P(X <= 1), X ~ Binomial(6, 1/2), two-sided
    assert mcnemar(first, first)["p"] == 1.0
    assert mcnemar(np.ones(20, bool), np.zeros(20, bool))["p"] == pytest.approx(2 / 2**20)
    with pytest.raises(ValueError, match="paired successes"):
        mcnemar(first, second[:-1])


def test_paired_bootstrap_equals_a_loop_and_keeps_the_pairing():
    rng = np.random.default_rng(1)
    base = rng.normal(20, 5, 64)  # a large spread shared by both methods: the pairing removes it
    first, second = base + 0.5 + rng.normal(0, 0.1, 64), base
    out = paired_bootstrap(first, second, samples=2000, seed=3)
    draws = np.random.default_rng(3).integers(0, 64, size=(2000, 64))
    means = [np.mean([first[i] - second[i] for i in row]) for row in draws]
    assert out["mean"] == pytest.approx(np.mean(first - second))
    assert out["ci95"] == pytest.approx(tuple(np.percentile(means, [2.5, 97.5])))
    lo, hi = out["ci95"]
    assert 0.4 < lo < 0.5 < hi < 0.6  # paired: tight around +0.5; unpaired intervals would span about ±2.5
    assert paired_bootstrap(np.full(5, 3.0), np.full(5, 1.0))["ci95"] == (2.0, 2.0)
    with pytest.raises(ValueError, match="E >= 2"):
        paired_bootstrap([1.0], [2.0])


def test_wilson_by_hand():
    lo, hi = wilson(8, 10)
    z = 1.959963984540054
    centre = (0.8 + z**2 / 20) / (1 + z**2 / 10)
    half = z * np.sqrt(0.8 * 0.2 / 10 + z**2 / 400) / (1 + z**2 / 10)
    assert (lo, hi) == pytest.approx((centre - half, centre + half))
    assert wilson(0, 10)[0] == pytest.approx(0.0, abs=1e-12)
