"""The planner benchmark runs end to end at its quick sizes and reports positive timings, at float32 and with
bfloat16 edges, and how close the bfloat16 plan is to the float32 one; the shipped checkpoint is timed too."""

import pytest

from benchmarks import bench_planner

pytestmark = pytest.mark.slow  # end to end: CI's second tier (python -m pytest -m slow)


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


def test_bf16_section(result):
    f32, bf16 = result["jax"], result["jax_bf16"]
    assert f32["edge_dtype"] == "float32" and bf16["edge_dtype"] == "bfloat16"
    for key in ("ms_per_step", "plan_s", "short_plan_s", "compile_s", "compile_short_s", "prediction_max_mm"):
        assert bf16[key] > 0, key
    assert bf16["steps"] == f32["steps"] and bf16["params"] == f32["params"] and bf16["quality_model"]
    assert bf16["prediction_mean_mm"] <= bf16["prediction_max_mm"] < 5.0  # mm: bfloat16 moves no particle far
    # Both plans improve on the unpushed piles, and the bfloat16 plan is about as good, judged by the float32 model.
    assert max(bf16["float32_best_cost"], bf16["best_cost_in_float32"]) < bf16["initial_cost"]
    assert bf16["best_cost_in_float32"] == pytest.approx(bf16["float32_best_cost"], rel=0.1)
    assert isinstance(result["plan_bf16_meets_goal"], bool)


def test_torch_section(result):
    pytest.importorskip("torch")
    torch_part = result["torch"]
    assert torch_part["ms_per_step"] > 0 and torch_part["device"]
    assert torch_part["params"] == result["jax"]["params"]
    # The peer scores its pushes with the planner's own objective c: on the same piles it agrees with JAX's c (to
    # the rounding of JAX's default matmul precision on GPUs, TF32, in the projection to pixels: about 0.02 px).
    assert len(torch_part["objective_px"]) == result["resamples"]
    assert torch_part["objective_max_abs_px"] < 1e-3 * max(map(abs, torch_part["objective_px"]))
    by_coverage = torch_part["ms_per_step_by_coverage"]
    assert set(by_coverage) == {"broadcast", "cdist"} and torch_part["ms_per_step"] == min(by_coverage.values())
    assert torch_part["ms_per_step_network_only"] > 0
    assert result["speedup_vs_network_only_peer"] == pytest.approx(
        torch_part["ms_per_step_network_only"] / result["jax"]["ms_per_step"])
    assert result["speedup"] == pytest.approx(torch_part["ms_per_step"] / result["jax"]["ms_per_step"])
    assert result["speedup_bf16"] == pytest.approx(torch_part["ms_per_step"] / result["jax_bf16"]["ms_per_step"])
    assert isinstance(result["speedup_meets_goal"], bool) and isinstance(result["speedup_bf16_meets_goal"], bool)
    assert result["speedup_shipped"] == pytest.approx(torch_part["ms_per_step"] / result["jax_shipped"]["ms_per_step"])


def test_stage_times(result):
    assert set(result["jax_stages"]) == {"edges_ms", "cost_ms", "dynamics_ms"}
    assert all(v > 0 for v in result["jax_stages"].values())


def test_shipped_section(result):
    """The shipped checkpoint's architecture is timed too (the repository ships one)."""
    shipped = result["jax_shipped"]
    assert shipped["ms_per_step"] > 0 and shipped["plan_s"] > 0 and shipped["edge_dtype"] == "float32"
    assert shipped["model"].startswith("shipped checkpoint") and shipped["config"]["world_edges"]
