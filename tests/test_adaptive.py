"""Adaptive resolution end to end on a CPU, tiny sizes: BO labels -> regressor -> evaluation -> Fig. 4 analysis."""

import json
import os
import time

import numpy as np
import pytest

from dynres_jax.commands import evaluate, label_resolution, tradeoff, train_regressor
from dynres_jax.control import mpc
from dynres_jax.control.budget import TimingTable, bucket_for
from dynres_jax.control.choosers import best_of
from dynres_jax.learn import labels as labels_lib
from dynres_jax.learn import regressor as g_training
from dynres_jax.resolution import bo
from dynres_jax.resolution.regressor import FEATURE_SIZE
from dynres_jax.sim import engines
from dynres_jax.sim.physics.c import CPhysics

pytestmark = pytest.mark.slow  # end to end: CI's second tier (python -m pytest -m slow)

QUICK = ["--quick", "--dynamics", "sweep", "--workers", "2"]
# A hand-made timing table: under a 20 ms budget, buckets 16, 32, 64, 100 afford 10, 5, 2 and 1 Adam steps (runs
# spending it plan at its buckets, not the default 16 32 50 75 100)
TABLE = TimingTable("test", 4, 1, fixed_s={16: 0.01, 32: 0.01, 64: 0.01, 100: 0.01},
                    step_s={16: 0.001, 32: 0.002, 64: 0.004, 100: 0.008})
AFFORDED = {16: 4, 32: 4, 64: 2, 100: 1}  # capped by --adam-steps 4 (the quick runs')


@pytest.fixture(scope="module")
def timing(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("timing") / "timing.json")
    TABLE.save(path)
    return ["--time-budget", "0.02", "--timing", path]


@pytest.fixture(scope="module")
def labels(tmp_path_factory, timing):
    """The quick labels, and the planner keys of every c*(ω) evaluation (``mpc.act``'s calls, in order)."""
    out, keys = str(tmp_path_factory.mktemp("labels")), []
    act = mpc.act

    def recording(pool, now, *args, **kwargs):
        keys.append(np.asarray(now.keys))
        return act(pool, now, *args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(mpc, "act", recording)
        summary = label_resolution.main(["--out", out, *QUICK, *timing])
    return out, summary, keys


@pytest.fixture(scope="module")
def regressor(labels, tmp_path_factory):
    out = str(tmp_path_factory.mktemp("regressor"))
    return out, train_regressor.main(["--labels", labels[0], "--out", out, "--steps", "5", "--batch", "4",
                                      "--width", "4"])


def test_labels_follow_the_bo_recipe_and_resume(labels, timing, capsys):
    out, summary, keys = labels
    assert summary["scenes"] == 8 and summary["shards_written"] == 2
    for shard in ("shard_00000.npz", "shard_00001.npz"):
        z = np.load(os.path.join(out, shard))
        first = len(labels_lib.FIRST)
        assert np.all(z["omega"][:, :first] == np.array(labels_lib.FIRST))
        for row in z["omega"]:
            assert len(set(row.tolist())) == len(row)  # EI never repeats an ω
        np.testing.assert_allclose(z["c_plus"], z["c_star"] + bo.W_R * z["d0"][:, None] * z["omega"],
                                   rtol=1e-5)
        assert np.all(z["label"] == bo.CANDIDATES[np.argmin(z["gp_mean"], axis=1)])
        assert z["inputs"].shape == (4, FEATURE_SIZE, FEATURE_SIZE, 6)
        assert np.all(z["pile"] == [0, 0, 1, 1]) and np.all(z["goal_shape"] == [0, 1, 0, 1])
        expect = np.vectorize(lambda w: AFFORDED[bucket_for(int(w), TABLE.buckets)])(z["omega"])  # the table's
        assert np.array_equal(z["adam_steps"], expect)  # every ω planned with its bucket's share of the budget
        assert z["repeat_var"].shape == z["omega"].shape and np.all(z["repeat_var"] == 0)  # one repeat: no spread
    assert TimingTable.load(os.path.join(out, "timing.json")).to_json() == TABLE.to_json()  # saved with the labels
    again = label_resolution.main(["--out", out, *QUICK, *timing])
    assert again["shards_written"] == 0 and again["scenes"] == 8
    with pytest.raises(SystemExit):  # other settings are refused, naming what differs, never mixed into the set
        label_resolution.main(["--out", out, *QUICK, *timing, "--seed", "5"])
    assert "--seed 0 there, 5 here" in capsys.readouterr().err


class CHere(CPhysics):
    """C MuJoCo stepped in this process, world after world (a stand-in for an engine of C's physics without host
    workers: Warp)."""

    name, workers = "c-here", False


def test_c_workers_label_shards_beside_an_engine_of_c_physics(labels, timing, tmp_path, monkeypatch, capsys):
    """``--cpu-workers``: C workers label shards from the same list as a JAX engine of C's physics (Warp; here a
    stand-in row: C MuJoCo in this process). Each engine labels one of the two shards and records it, and every shard
    equals the one-engine run's (the same physics, scenes and keys). Beside an engine of another physics: refused."""
    row = engines.Engine("c-here", CHere, False, None, "C MuJoCo in this process, for Warp", c_physics=True)
    monkeypatch.setitem(engines.ENGINES, row.name, row)
    monkeypatch.setattr(engines, "NAMES", (*engines.NAMES, row.name))
    label_shard = labels_lib.label_shard

    def slow(*args, **kwargs):  # a shard takes a second more, so each producer takes one before the other ends
        time.sleep(1.0)
        return label_shard(*args, **kwargs)

    monkeypatch.setattr(label_resolution, "label_shard", slow)
    out = str(tmp_path / "mixed")
    in_process = [a for a in QUICK if a not in ("--workers", "2")]  # the row runs no worker processes
    label_resolution.main(["--out", out, *in_process, *timing, "--backend", "c-here", "--cpu-workers", "1"])
    made_by = set()
    for shard in ("shard_00000.npz", "shard_00001.npz"):
        made, alone = np.load(os.path.join(out, shard)), np.load(os.path.join(labels[0], shard))
        made_by.add(str(made["engine"]))
        assert set(made.files) == set(alone.files)
        for name in alone.files:
            if name != "engine":
                np.testing.assert_array_equal(made[name], alone[name], err_msg=name)
    assert made_by == {"c-here", "mujoco"}
    with pytest.raises(SystemExit):
        label_resolution.main(["--out", str(tmp_path / "c"), *QUICK, *timing, "--cpu-workers", "1"])
    assert "C's physics" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()  # refused before any work


def test_every_omega_of_a_scene_is_planned_from_the_same_keys(labels):
    """Common random numbers: a shard's evaluations (5 at FIRST, then EI's) reuse one key per scene and repeat, so
    c*(ω) - c*(ω') is the resolution's effect; scenes' keys differ, and so do the two shards'."""
    _, summary, keys = labels
    evals = len(keys) // summary["shards_written"]
    assert evals > len(labels_lib.FIRST)
    shards = [keys[i * evals:(i + 1) * evals] for i in range(summary["shards_written"])]
    for shard in shards:
        assert all(np.array_equal(k, shard[0]) for k in shard)
        assert len({k.tobytes() for k in shard[0]}) == len(shard[0])  # every scene its own key
    assert not np.array_equal(shards[0][0], shards[1][0])


def test_mid_episode_labels_start_from_pushed_piles(labels, timing, tmp_path):
    """--mid-episode 1: the same scenes, each first pushed once towards its goal by the closed loop, then labelled;
    every pile has moved (d before the labelled push differs from the fresh scene's)."""
    summary = label_resolution.main(["--out", str(tmp_path), *QUICK, *timing, "--mid-episode", "1"])
    assert summary["scenes"] == 8
    for shard in ("shard_00000.npz", "shard_00001.npz"):
        fresh, mid = np.load(os.path.join(labels[0], shard)), np.load(tmp_path / shard)
        assert int(mid["mid_episode"]) == 1 and int(fresh["mid_episode"]) == 0
        assert np.all(np.abs(mid["d0"] - fresh["d0"]) > 1e-6)


def test_regressor_checkpoint_and_metrics(regressor):
    out, metrics = regressor
    assert metrics["train"] + metrics["validation"] + metrics["held_out"] == 8 and np.isfinite(metrics["mae"])
    assert min(metrics["train"], metrics["validation"], metrics["held_out"]) > 0 and 0 <= metrics["best_step"] <= 5
    with open(os.path.join(out, "metrics.json")) as f:
        assert json.load(f)["params"] == metrics["params"]


def test_evaluation_fixed_and_adaptive(regressor, timing, tmp_path):
    # 60 pieces: enough foreground points at 64 x 64 for any ω up to 100 (the regressor may pick any)
    summary = evaluate.main(["--quick", "--episodes", "2", "--mpc-steps", "2", "--pieces", "60", "--samples", "4",
                             "--adam-steps", "4", *timing, "--methods", "10", "75", "adaptive", "--regressor",
                             os.path.join(regressor[0], "ckpt"), "--dynamics", "sweep", "--workers", "2",
                             "--out", str(tmp_path)])
    assert set(summary["methods"]) == {"10", "75", "adaptive"} and summary["time_budget"] == 0.02
    runs = {}
    for method in summary["methods"]:
        with open(tmp_path / f"{method}.json") as f:
            runs[method] = json.load(f)
        omega, steps = np.array(runs[method]["omega"]), np.array(runs[method]["adam_steps"])
        assert np.array_equal(steps, np.vectorize(lambda w: AFFORDED[bucket_for(int(w), TABLE.buckets)])(omega))
    assert np.all(np.array(runs["10"]["omega"]) == 10) and len(runs["10"]["final_distance"]) == 2
    assert np.all(np.array(runs["75"]["adam_steps"]) == 1)  # a fine ω affords fewer steps under the same budget
    assert summary["reference"] == "adaptive" and set(summary["paired"]) == {"10", "75"}
    delta = summary["paired"]["10"]["delta_d"]
    assert delta["mean"] == pytest.approx(np.mean(np.array(runs["10"]["final_distance"])
                                                  - np.array(runs["adaptive"]["final_distance"])))
    adaptive = runs["adaptive"]
    assert np.all((np.array(adaptive["omega"]) >= 2) & (np.array(adaptive["omega"]) <= 100))
    assert (tmp_path / "score.png").read_bytes()[:4] == b"\x89PNG"
    for bad in (["--methods", "7000"], ["--methods", "best0"], ["--methods", "best5", "--best-omega", "1"]):
        with pytest.raises(SystemExit):
            evaluate.main([*bad, "--out", str(tmp_path)])
    assert best_of("best5") == 5 and best_of("best") == best_of("50") == 0


def test_tradeoff_pairs(labels, tmp_path):
    result = tradeoff.main(["--labels", labels[0], "--out", str(tmp_path)])
    assert result["letter_vs_disc"]["pairs"] == 4 and result["gathered_vs_spread"]["pairs"] == 2  # discs only
    r = result["letter_vs_disc"]
    assert abs(r["higher"] + r["lower"] + r["equal"] - 1) < 1e-9


def test_dihedral_augmentation_is_the_eight_symmetries_of_the_grid():
    """Each (turns, flip) equals NumPy's rot90 then a left-right mirror, sample by sample; the 8 are distinct."""
    images = np.random.default_rng(0).normal(size=(8, 5, 5, 2)).astype(np.float32)
    images[:] = images[0]
    turns, flip = np.arange(8) % 4, np.arange(8) // 4
    out = np.asarray(g_training.dihedral(images, turns, flip))
    for i in range(8):
        expect = np.rot90(images[i], turns[i], axes=(0, 1))
        np.testing.assert_array_equal(out[i], expect[:, ::-1] if flip[i] else expect)
    assert len({o.tobytes() for o in out}) == 8


def test_label_reliability_by_hand(tmp_path):
    """Two label runs of the same scenes matched scene by scene; Spearman by hand on a case with ties."""
    a, b = tmp_path / "a", tmp_path / "b"
    for folder, labels in ((a, [[10, 20], [30, 30]]), (b, [[12, 25], [50, 20]])):
        folder.mkdir()
        (folder / "config.json").write_text(json.dumps({"scenes": 4, "batch": 2}))
        for shard, label in enumerate(labels):
            np.savez(folder / f"shard_{shard:05d}.npz", shard=np.int64(shard), label=np.array(label))
    result = tradeoff.reliability(str(a), str(b), str(tmp_path / "out"))
    # a = 10, 20, 30, 30 -> ranks 1, 2, 3.5, 3.5; b = 12, 25, 50, 20 -> ranks 1, 3, 4, 2
    ra, rb = np.array([1, 2, 3.5, 3.5]), np.array([1, 3, 4, 2])
    assert result["scenes"] == 4 and result["spearman"] == pytest.approx(np.corrcoef(ra, rb)[0, 1])
    assert result["mean_abs_difference"] == pytest.approx((2 + 5 + 20 + 10) / 4)
    assert result["regressor_mae_at_least"] == pytest.approx(37 / 8)
    assert result["regressor_correlation_at_most"] == pytest.approx(np.sqrt(result["pearson"]))
    c = tmp_path / "c"
    c.mkdir()
    (c / "config.json").write_text(json.dumps({"scenes": 2, "batch": 2}))
    np.savez(c / "shard_00000.npz", shard=np.int64(7), label=np.array([10, 20]))
    with pytest.raises(ValueError, match="share 0 scenes"):
        tradeoff.reliability(str(a), str(c), str(tmp_path / "out"))
    os.remove(b / "shard_00001.npz")
    with pytest.raises(ValueError, match="1 of its 2 shards are missing"):
        tradeoff.reliability(str(a), str(b), str(tmp_path / "out"))
    (b / "config.json").write_text(json.dumps({"scenes": 4, "batch": 2, "seed": 5}))  # other piles behind (shard, i)
    with pytest.raises(ValueError, match="label different scenes .seed None vs 5"):
        tradeoff.reliability(str(a), str(b), str(tmp_path / "out"))


def test_label_folders_pool_with_distinct_shard_numbers(labels):
    """Two folders that both hold shard 0 and 1: pooled, their piles keep distinct names (shard, pile)."""
    one = g_training.load_labels([labels[0]])
    both = g_training.load_labels([labels[0], labels[0]])
    n = len(one["label"])
    assert len(both["label"]) == 2 * n and np.array_equal(both["label"][n:], one["label"])
    assert np.array_equal(both["shard"], np.concatenate([one["shard"], one["shard"] + 2]))
    with pytest.raises(ValueError, match="no config.json, so no data or label set"):
        g_training.load_labels([labels[0], os.path.dirname(labels[0])])
