"""The planner benchmark runs end to end at its quick sizes and reports positive timings."""

import pytest

from experiments import bench_planner


@pytest.fixture(scope="module")
def result():
    return bench_planner.run(quick=True)


def test_jax_section(result):
    assert result["batch"] == result["samples"] * result["resamples"]
    jax_part = result["jax"]
    for key in ("ms_per_step", "plan_s", "short_plan_s", "plan_ms_per_step", "compile_s", "compile_short_s"):
        assert jax_part[key] > 0, key
    assert jax_part["steps"] == result["steps"] > jax_part["short_steps"]
    assert jax_part["params"] == 38403 and jax_part["device"]
    assert isinstance(result["plan_meets_goal"], bool)


def test_torch_section(result):
    pytest.importorskip("torch")
    torch_part = result["torch"]
    assert torch_part["ms_per_step"] > 0 and torch_part["device"]
    assert torch_part["params"] == result["jax"]["params"]
    assert result["speedup"] == pytest.approx(torch_part["ms_per_step"] / result["jax"]["ms_per_step"])
    assert isinstance(result["speedup_meets_goal"], bool)
