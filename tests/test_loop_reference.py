"""The closed loop behaves as recorded (tests/loop_reference.py): seeded Gather at a fixed ω and adaptive under a
frozen time budget, Redistribute, Sort and a small evaluation (fixed, adaptive, oracle; a depth camera's errors) give
the pushes, ω, Adam steps and scores they gave when the reference was written."""

import json

import numpy as np
import pytest
from loop_reference import REFERENCE, record


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return record(str(tmp_path_factory.mktemp("reference")))


def _compare(got, want, where):
    if isinstance(want, dict):
        assert set(got) == set(want), f"{where}: keys {sorted(got)} != {sorted(want)}"
        for k in want:
            _compare(got[k], want[k], f"{where}.{k}")
    elif isinstance(want, list) and want and all(isinstance(x, dict | str) for x in want):
        assert len(got) == len(want), f"{where}: {len(got)} entries, recorded {len(want)}"
        for i, (g, w) in enumerate(zip(got, want, strict=True)):
            _compare(g, w, f"{where}[{i}]")
    elif isinstance(want, str | bool) or want is None:
        assert got == want, f"{where}: {got!r} != {want!r}"
    else:
        np.testing.assert_allclose(np.asarray(got, np.float64), np.asarray(want, np.float64), rtol=1e-6, atol=1e-7,
                                   err_msg=where)


@pytest.mark.parametrize("case", ["gather_fixed", "gather_adaptive", "redistribute", "sort", "evaluate",
                                  "evaluate_oracle", "evaluate_sensor"])
def test_the_loop_repeats_its_recorded_behaviour(runs, case):
    with open(REFERENCE) as f:
        want = json.load(f)[case]
    _compare(runs[case], want, case)
