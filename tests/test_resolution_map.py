"""scripts/resolution_map.py: surfaces priced at a budget and the best fixed ω's regret, against sums by hand."""

import json
import os

import numpy as np
import pytest

from dynres_jax.control.budget import TimingTable, reference_table


def _surface(folder, c_star, d0, timing: TimingTable, omegas=(25, 50), steps=(1, 10), samples=4):
    """A tradeoff --surface folder of two scene kinds, splitting the scenes of c_star [ω, N, S] in halves."""
    os.makedirs(folder)
    half = c_star.shape[-1] // 2
    for k, cols in enumerate((slice(0, half), slice(half, None))):
        np.savez(os.path.join(folder, f"surface_{k}.npz"), c_star=c_star[..., cols], d0=d0[cols])
    summary = dict(omegas=list(omegas), steps=list(steps), buckets=[25, 50], samples=samples, device="test",
                   timing=timing.to_json(), kinds={"a": {}, "b": {}})
    with open(os.path.join(folder, "surface.json"), "w") as f:
        json.dump(summary, f)
    return str(folder)


C_STAR = np.array([[[3, 3, 3, 3], [1, 2, 1, 2]],    # ω = 25 at N = 1, 10
                   [[2, 4, 2, 4], [0, 0, 0, 0]]], float)  # ω = 50
D0 = np.full(4, 5.0)
TABLE = TimingTable("test", 4, 1, {25: 0.0, 50: 0.0}, {25: 0.01, 50: 0.02})


def test_each_omega_gets_the_most_steps_its_price_affords(script, tmp_path):
    m = script("resolution_map")
    run = m.load(_surface(tmp_path / "run", C_STAR, D0, TABLE))
    np.testing.assert_array_equal(m.priced(run, 0.05), C_STAR[:, 0])  # 10 steps cost 0.1 and 0.2 s: N = 1 for both
    np.testing.assert_array_equal(m.priced(run, 0.15), [C_STAR[0, 1], C_STAR[1, 0]])  # ω = 25 affords N = 10
    np.testing.assert_array_equal(m.priced(run, 0.005), [D0, D0])  # no step fits: no push
    np.testing.assert_array_equal(m.priced(run, 1.0), C_STAR[:, 1])


def test_the_regret_of_the_best_fixed_omega_by_hand(script, tmp_path):
    """At 0.05 s both ω average 3 px (ω = 25 kept, the first); the per-scene best averages (2 + 3 + 2 + 3) / 4 = 2.5:
    regret 0.5. At 0.15 s ω = 25 is best on every scene: regret 0, as it is when nothing fits."""
    m = script("resolution_map")
    run = m.load(_surface(tmp_path / "run", C_STAR, D0, TABLE))
    rng = np.random.default_rng(0)
    at = {b: m.regret(m.priced(run, b), rng) for b in (0.05, 0.15, 0.005)}
    assert at[0.05]["best"] == 0 and at[0.05]["regret"] == 0.5 and at[0.05]["ci95"][0] >= 0
    assert at[0.15]["best"] == 0 and at[0.15]["regret"] == 0 and at[0.15]["ci95"] == [0, 0]
    assert at[0.005]["regret"] == 0


def test_the_reference_pricing_prices_each_omega_and_the_map_is_written(script, tmp_path):
    """A run priced by the reference's t(ω) (11 and 20 ms at ω = 25, 50): at 0.1 s ω = 25 affords N = 1 (10 steps
    cost 0.11 s); at 0.19 s ω = 25 affords 10 steps and ω = 50 one (10 cost 0.2 s). main writes map.json, map.md
    and map.png."""
    m = script("resolution_map")
    folder = _surface(tmp_path / "ref", C_STAR, D0, reference_table((25, 50), 4, 1))
    run = m.load(folder)
    np.testing.assert_array_equal(m.priced(run, 0.1), C_STAR[:, 0])
    np.testing.assert_array_equal(m.priced(run, 0.19), [C_STAR[0, 1], C_STAR[1, 0]])
    m.main([folder, _surface(tmp_path / "ours", C_STAR, D0, TABLE), "--out", str(tmp_path / "map"),
            "--budgets", "0.05", "0.15"])
    result = json.load(open(tmp_path / "map" / "map.json"))
    assert len(result) == 2 and [r["regret"] for r in result["ours (M = 4, test)"]] == [0.5, 0.0]
    assert (tmp_path / "map" / "map.png").stat().st_size > 0
    assert "| 0.05 | 25 |" in open(tmp_path / "map" / "map.md").read()


def test_samples_or_steps_pairs_equal_work_by_hand(script, tmp_path):
    """Surfaces at M = 2 and 4 with N = 1 and 2: only the work 4 is reached twice, by 2 x 2 and 4 x 1; the difference
    is c*(4 x 1) - c*(2 x 2) per scene, by hand."""
    m = script("samples_or_steps")
    small = C_STAR  # M = 2: [ω, N, S]
    large = C_STAR[:, ::-1] + 1.0  # M = 4: c*(N = 1) is small's c*(N = 2) + 1
    runs = {2: m.load(_surface(tmp_path / "m2", small, D0, TABLE, steps=(1, 2), samples=2)),
            4: m.load(_surface(tmp_path / "m4", large, D0, TABLE, steps=(1, 2), samples=4))}
    assert m.pairs_by_work(runs) == {4: [(2, 1), (4, 0)]}
    rows = m.compare(runs, np.random.default_rng(0))
    assert [(r["omega"], r["work"]) for r in rows] == [(25, 4), (50, 4)]
    for r, omega in zip(rows, range(2), strict=True):
        assert r["samples_minus_steps"] == 1.0 and r["ci95"] == [1.0, 1.0]
        assert r["means"] == {"2x2": small[omega, 1].mean(), "4x1": small[omega, 1].mean() + 1.0}


def _loop_cross_fitted(c):
    """The cross-fitted oracle as loops: per scene and held-out draw, the ω of the others' lowest mean."""
    r, w, s = c.shape
    out, pick = np.zeros(s), np.zeros((r, s), int)
    for scene in range(s):
        for held in range(r):
            means = [np.mean([c[d, o, scene] for d in range(r) if d != held]) for o in range(w)]
            pick[held, scene] = int(np.argmin(means))
            out[scene] += c[held, pick[held, scene], scene] / r
    return out, pick


def test_the_cross_fitted_oracle_equals_its_loops_and_removes_the_winners_curse(script):
    """On random c* the vectorised choice equals the loops. On c* where ω does not matter (every ω the same
    distribution, plan noise only) the cross-fitted oracle is no better than one plan at a fixed ω, while the
    single-plan oracle (min over ω of one draw) looks better: the winner's curse it removes. Where one ω is truly
    better on half the scenes, the cross-fitted oracle finds it: a positive gap."""
    m = script("crossfit")
    rng = np.random.default_rng(1)
    c = rng.normal(10, 1, size=(5, 3, 40))
    mine, pick = m.cross_fitted(c)
    loops = _loop_cross_fitted(c)
    np.testing.assert_allclose(mine, loops[0])
    np.testing.assert_array_equal(pick, loops[1])
    tune = np.arange(400) % 2 == 0
    noise = rng.normal(10, 1, size=(5, 3, 400))
    flat = m.compare(noise, tune, (25, 50, 100), rng)
    assert abs(flat["gap"]) < 0.15 and flat["gap_ci95"][0] < 0 < flat["gap_ci95"][1]
    assert flat["single_oracle"] < flat["fixed"] - 0.5 and flat["best_of_r"] < flat["fixed"] - 0.5
    assert abs(flat["label_spearman"]) < 0.2
    real = noise.copy()
    real[:, 2, 1::4] -= 3.0  # ω = 100 better by 3 px on half the test scenes
    found = m.compare(real, tune, (25, 50, 100), rng)
    assert found["gap"] > 1.0 and found["gap_ci95"][0] > 0.5 and found["label_spearman"] > 0.5
    with np.testing.assert_raises(ValueError):
        m.cross_fitted(c[:1])


def test_crossfit_reads_draws_priced_and_refuses_a_run_of_one_plan(script, tmp_path, capsys):
    """main on a surface folder with c_star_draws: the table is written; a folder without draws is refused."""
    import pytest

    m = script("crossfit")
    folder = _surface(tmp_path / "one", C_STAR, D0, TABLE)
    with pytest.raises(SystemExit):
        m.main([folder, "--out", str(tmp_path / "x")])
    assert "--repeats 3" in capsys.readouterr().err
    draws = np.stack([C_STAR + d for d in (0.0, 0.5, 1.0)])  # [R, ω, N, S]
    rich = tmp_path / "rich"
    os.makedirs(rich)
    for k, cols in enumerate((slice(0, 2), slice(2, None))):
        np.savez(rich / f"surface_{k}.npz", c_star=C_STAR[..., cols], d0=D0[cols], c_star_draws=draws[..., cols])
    with open(rich / "surface.json", "w") as f:
        json.dump(dict(omegas=[25, 50], steps=[1, 10], buckets=[25, 50], samples=4, device="test", scenes=2,
                       timing=TABLE.to_json(), kinds={"a": {}, "b": {}}), f)
    m.main([str(rich), "--out", str(tmp_path / "cf"), "--budgets", "1.0"])
    rows = json.load(open(tmp_path / "cf" / "crossfit.json"))["rich (M = 4, test)"]
    assert [r["scenes_of"] for r in rows] == ["all", *m.SURFACE_SCENES] and [r["scenes"] for r in rows] == [2, 1, 1]
    row = rows[0]
    # at 1 s both ω afford 10 steps: ω = 50 is 0 on every scene (plus the draw's offset), best fixed and chosen
    assert row["best_fixed"] == 50 and row["gap"] == 0 and row["moved"] == 0 and row["scenes"] == 2


@pytest.mark.slow
def test_a_killed_surface_goes_on_from_its_last_plan_draw_and_omega(tmp_path, monkeypatch):
    """``tradeoff --surface --repeats 2`` stopped after its third decision (a kill mid-kind) and run again: the rerun
    does not plan again the (draw, ω) saved in surface_0.partial.npz, and ends with the raw values an uninterrupted
    run writes, byte for byte; the partial file is gone."""
    from dynres_jax.commands import tradeoff

    monkeypatch.setattr(tradeoff, "SURFACE_SCENES", tradeoff.SURFACE_SCENES[:1])  # one scene kind: half the work
    argv = ["--surface", "--quick", "--repeats", "2", "--workers", "1"]
    whole = tmp_path / "whole"
    tradeoff.main(argv + ["--out", str(whole)])
    decide, calls = tradeoff.decide_batch, []

    def stops_at_the_third(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("killed")
        return decide(*args, **kwargs)

    monkeypatch.setattr(tradeoff, "decide_batch", stops_at_the_third)
    resumed = tmp_path / "resumed"
    with pytest.raises(RuntimeError, match="killed"):
        tradeoff.main(argv + ["--out", str(resumed)])
    with np.load(resumed / "surface_0.partial.npz") as partial:
        assert partial["done"].tolist() == [[True, False], [False, False]]  # ω = 10 of draw 0: its two N
    calls.clear()
    monkeypatch.setattr(tradeoff, "decide_batch", lambda *a, **k: (calls.append(1), decide(*a, **k))[1])
    tradeoff.main(argv + ["--out", str(resumed)])
    assert len(calls) == 2 * 2 * 2 - 2  # draws x ω x N, less the two kept
    assert (resumed / "surface_0.npz").read_bytes() == (whole / "surface_0.npz").read_bytes()
    assert not (resumed / "surface_0.partial.npz").exists()
