"""``benchmark all``: one Markdown table, a row per figure, each ratio computed from the two figures beside it."""

import json
import re

import pytest

from benchmarks import bench_perception, bench_planner, bench_sim, benchmark


def _results():
    """Inputs shaped like the three benchmarks' results (different numbers in every field)."""
    sim = dict(device="dev", host_cores=16, pieces=100, variants={
        name: dict(mjx=dict(rows=[dict(worlds=w, world_steps_per_s=590 * p, pushes_per_s=p)
                                  for w, p in [(16, 3.0 * i + 1), (4096, 50.0 * i + 7)]]),
                   c_mujoco=dict(cores=16, pushes_per_s=20.0 + i))
        for i, name in enumerate(["a", "b"])})
    sim["variants"]["b"]["mjx"]["whole_push"] = dict(worlds=4096, pushes_per_s=44.0, seconds=93.1)
    per = dict(fps=dict(clouds=1024, points=20000, n=100, median_ms=12.5), fps_numpy=dict(batch_ms_scaled=33280.0),
               h=dict(omega=50, observations=1024, image=256, median_ms=81.6),
               h_max_points=dict(max_points=8192, median_ms=17.3))
    planner = dict(batch=1500, particles=100, steps=200, plan_goal_s=1.0, speedup=31.73 / 4.29,
                   speedup_bf16=31.73 / 2.61, torch=dict(ms_per_step=31.73),
                   jax=dict(device="gpu: H200", jax_version="0", ms_per_step=4.29, plan_s=0.86, compile_s=2.5),
                   jax_bf16=dict(ms_per_step=2.61, plan_s=0.55, compile_s=2.7, quality_model="shipped checkpoint",
                                 prediction_mean_mm=0.03, prediction_max_mm=0.4, best_cost_in_float32=7.5,
                                 float32_best_cost=7.4),
                   jax_shipped=dict(ms_per_step=5.02, plan_s=1.01, compile_s=2.9, model="shipped checkpoint"),
                   speedup_shipped=31.73 / 5.02)
    return sim, per, planner


def _cells(row):
    return [c.strip() for c in row.strip("|").split("|")]


def _number(cell):
    return float(re.findall(r"[\d,]+\.?\d*", cell.split(":")[-1])[-1].replace(",", ""))


@pytest.fixture
def written(tmp_path, monkeypatch):
    sim, per, planner = _results()
    monkeypatch.setattr(bench_sim, "run", lambda *a, **k: sim)
    monkeypatch.setattr(bench_perception, "run", lambda quick: per)
    monkeypatch.setattr(bench_planner, "run", lambda quick: planner)
    path = tmp_path / "bench.json"
    benchmark.main(["all", "--json", str(path)])
    return json.loads(path.read_text()), (tmp_path / "bench.json.md").read_text()


def test_all_writes_json_and_one_table(written):
    result, table = written
    assert set(result) == {"quick", "sim", "perception", "planner"}
    rows = [r for r in table.splitlines() if r.startswith("| ") and not r.startswith("| benchmark")]
    assert len(rows) == 2 + 8  # a row per simulator variant, FPS, h, and the planner step and whole plan at each dtype
    # and with the shipped model
    assert "bfloat16 edges (vs float32, shipped checkpoint: predictions 0.03 mm mean" in table
    assert "gpu: H200" in table


def test_every_ratio_is_how_many_times_faster_ours_is(written):
    _, table = written
    rows = [_cells(r) for r in table.splitlines() if r.startswith("| ") and not r.startswith("| benchmark")]
    for what, ours, peer, ratio in rows:
        a, b = _number(ours), _number(peer)
        expected = a / b if "pushes/s" in what else b / a  # a rate: ours over peer; a time: peer over ours
        assert float(ratio.rstrip("x").replace(",", "")) == pytest.approx(expected, rel=0.02, abs=0.06), what
    sim_rows = [r for r in rows if r[0].startswith("simulator")]
    # a: its best world count; b: its whole pushes, which are what C MuJoCo (whole pushes) is compared with
    assert [_number(r[1]) for r in sim_rows] == [7.0, 44.0]


def test_sim_table_adds_the_whole_pushes_row():
    table = benchmark.sim_table(_results()[0])
    assert "| b | 4096 | 33,630 | 57.0 | 21.0 | 2.71x |" in table
    assert "| b, whole pushes | 4096 | - | 44.0 | 21.0 | 2.10x |" in table
    assert "a, whole pushes" not in table


def test_warp_without_the_extra_is_one_line(capsys):
    """``benchmark warp`` on a machine without MuJoCo Warp: exit status 2 and one line naming the extra, before any
    work (it was a traceback around that line)."""
    from dynres_jax.errors import InputError
    from dynres_jax.sim.physics import warp

    try:
        warp.check_installed()
        pytest.skip("MuJoCo Warp is installed here")
    except InputError:
        pass
    with pytest.raises(SystemExit) as stop:
        benchmark.main(["warp", "--quick"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and 'pip install "dynres-jax[warp]"' in err and "Traceback" not in err


def test_the_warp_benchmark_reports_a_failing_graph_mode_as_a_row(monkeypatch):
    """A graph mode that raises (JAX's died with CUDA_ERROR_NOT_SUPPORTED on an H200) is a row naming the error, C is
    measured first whatever Warp does, and the table is written; when no Warp row ran, both-at-once says so."""
    from benchmarks import bench_warp

    order = []
    monkeypatch.setattr(bench_warp.warp, "check_installed", lambda: None)
    monkeypatch.setattr(bench_warp, "c_reference", lambda cfg, s: order.append("C") or dict(pushes_per_s=100.0,
                                                                                           cores=2))

    def rate(cfg, w, mode):
        order.append(mode)
        if mode == "JAX":
            raise RuntimeError("CUDA_ERROR_NOT_SUPPORTED: operation not supported\nmore lines")
        return dict(graph_mode=mode, worlds=w, pushes_per_s=2.0 * w, seconds=1.0, compile_s=0.0, overflowed_worlds=0)

    monkeypatch.setattr(bench_warp, "mode_rate", rate)
    monkeypatch.setattr(bench_warp, "together", lambda cfg, w, mode, s, cores: dict(
        worlds=w, graph_mode=mode, c_cores=cores, warp_pushes_per_s=1.0, c_pushes_per_s=1.0, pushes_per_s=2.0 * w))
    out = bench_warp.run(worlds=[100, 200], graph_modes=["WARP", "JAX"])
    assert order == ["C", "WARP", "WARP", "JAX", "JAX"]
    assert [r.get("failed") for r in out["warp"]] == [None, None, *["RuntimeError: CUDA_ERROR_NOT_SUPPORTED: "
                                                                   "operation not supported"] * 2]
    assert out["best"]["worlds"] == 200 and out["warp_over_c"] == 4.0 and out["together_over_c"] == 4.0
    table = bench_warp.table(out)
    assert table.count("failed: RuntimeError") == 2 and "| 400.0 | 4.00x |" in table

    monkeypatch.setattr(bench_warp, "mode_rate", lambda cfg, w, mode: 1 / 0)
    out = bench_warp.run(worlds=[100], graph_modes=["NONE"])
    assert out["best"] is None and out["together"] == dict(failed="no Warp row ran") and out["warp_over_c"] is None
    assert "| Warp + C at once | - | - | failed: no Warp row ran | - |" in bench_warp.table(out)


def test_a_json_path_that_cannot_take_the_result_is_refused_before_timing(tmp_path, monkeypatch, capsys):
    """--json naming a folder (or without .json) is one line before any timing: it failed after the whole run."""
    monkeypatch.setattr(bench_planner, "run", lambda quick: pytest.fail("timed before checking --json"))
    for bad in (str(tmp_path), str(tmp_path / "result.txt")):
        with pytest.raises(SystemExit) as ended:
            benchmark.main(["planner", "--quick", "--json", bad])
        assert ended.value.code == 2 and "--json" in capsys.readouterr().err


def test_options_the_benchmark_does_not_read_or_unknown_variants_are_refused_before_timing(monkeypatch, capsys):
    """--variants with planner (read by sim only), an unknown scene variant (a KeyError after compiling) and a world
    count of 0 are one line, exit 2, before any timing."""
    from benchmarks import bench_sim

    monkeypatch.setattr(bench_planner, "run", lambda quick: pytest.fail("timed before checking the options"))
    monkeypatch.setattr(bench_sim, "run", lambda *a, **k: pytest.fail("timed before checking the options"))
    for argv, says in ((["planner", "--variants", "fast"], "--variants is read by benchmark sim and all"),
                       (["sim", "--variants", "nope"], "no scene variant 'nope'"),
                       (["sim", "--full-sweep", "fast", "x"], "--full-sweep: no scene variant 'x'"),
                       (["sim", "--worlds", "0"], "--worlds"), (["planner", "--batch", "task"], "--batch")):
        with pytest.raises(SystemExit) as ended:
            benchmark.main(argv)
        err = capsys.readouterr().err
        assert ended.value.code == 2 and says in err and err.count("\n") == 1, err
