"""The ranking benchmark (learn.ranking, studies.ranking): rank statistics against brute-force definitions, a tiny set
built from the closed loop and scored, saved and loaded."""

import itertools

import numpy as np
import pytest

from dynres_jax.io import ckpt
from dynres_jax.learn import ranking
from dynres_jax.models.registry import build_model, load_dynamics


def brute_kendall(p, t):
    """Kendall's tau-b by counting pairs."""
    conc = disc = tie_p = tie_t = 0
    for i, j in itertools.combinations(range(len(p)), 2):
        a, b = np.sign(p[i] - p[j]), np.sign(t[i] - t[j])
        if a == 0 and b == 0:
            continue
        if a == 0:
            tie_p += 1
        elif b == 0:
            tie_t += 1
        elif a == b:
            conc += 1
        else:
            disc += 1
    return (conc - disc) / np.sqrt((conc + disc + tie_p) * (conc + disc + tie_t))


def brute_spearman(p, t):
    """Pearson correlation of average ranks, the ranks counted by hand."""
    def ranks(x):
        return np.array([np.sum(x < v) + (np.sum(x == v) - 1) / 2 for v in x])

    return np.corrcoef(ranks(p), ranks(t))[0, 1]


def test_rank_statistics_equal_their_definitions():
    rng = np.random.default_rng(0)
    p = rng.integers(0, 6, (5, 9)).astype(float)  # ties on purpose
    t = p + rng.normal(0, 2, p.shape)
    t[:, :2] = t[:, 2:4]  # ties in the truth too
    np.testing.assert_allclose(ranking.kendall(p, t), [brute_kendall(a, b) for a, b in zip(p, t, strict=True)])
    np.testing.assert_allclose(ranking.spearman(p, t), [brute_spearman(a, b) for a, b in zip(p, t, strict=True)])


def test_scores_of_a_perfect_a_reversed_and_a_constant_ranking():
    true = np.array([[3.0, 1.0, 2.0, 5.0, 4.0, 9.0, 7.0]])
    perfect = ranking.ranking_scores(true + 10, true)
    assert perfect["spearman"][0] == pytest.approx(1) and perfect["kendall"][0] == pytest.approx(1)
    assert perfect["regret"][0] == 0 and perfect["top5"][0] == 1
    reverse = ranking.ranking_scores(-true, true)
    assert reverse["spearman"][0] == pytest.approx(-1) and reverse["kendall"][0] == pytest.approx(-1)
    assert reverse["regret"][0] == 9.0 - 1.0 and reverse["top5"][0] == 0  # picks the worst
    flat = ranking.ranking_scores(np.zeros_like(true), true)
    assert flat["spearman"][0] == 0 and flat["kendall"][0] == 0 and flat["regret"][0] == 3.0 - 1.0  # the first
    true_pos = np.zeros((1, 7, 4, 3))
    mask = np.array([[True, True, True, False]])
    off = true_pos + np.array([0.003, 0.0, 0.0]) * mask[:, None, :, None]
    off[:, :, 3] = 5.0  # a masked slot's garbage counts for nothing
    assert ranking.ranking_scores(true, true, off, true_pos, mask)["error_mm"][0] == pytest.approx(3.0)
    s = ranking.summarise({"x": np.array([0.0, 1.0, 1.0, 0.0])})
    assert s["x"]["mean"] == 0.5 and 0 <= s["x"]["ci95"][0] < 0.5 < s["x"]["ci95"][1] <= 1


@pytest.fixture(scope="module")
def tiny_set(tmp_path_factory):
    from studies import ranking as study

    out = tmp_path_factory.mktemp("ranking")
    study.main(["build", "--out", str(out), "--episodes", "3", "--samples", "4", "--adam-steps", "2", "--capture",
                "0", "--workers", "2", "--kind", "coffee", "--pieces", "30"])
    return str(out)


@pytest.mark.slow
def test_a_tiny_set_is_built_from_the_closed_loop_and_scored(tiny_set, tmp_path):
    from studies import ranking as study

    s = ranking.load(tiny_set)
    c = 4 + 1  # the planner's samples and its best
    assert len(s.group) == 3 and s.candidates.shape == (3, c, 4) and s.true_c.shape == (3, c)
    assert s.true_positions.shape == (3, c) + s.positions.shape[1:]
    # the true outcome moved the particles the push swept, and kept masked slots at zero
    moved = np.linalg.norm(s.true_positions - s.positions[:, None], axis=-1)
    assert np.any(moved[:, :, s.mask[0]] > 0.005) and np.all(s.true_positions[:, :, ~s.mask[0]] == 0)
    sweep = load_dynamics("sweep", None, s.sim.scene.plate_half_width).dynamics
    c_pred, final = ranking.predict(s, sweep)
    assert c_pred.shape == (3, c) and np.all(np.isfinite(c_pred))
    results = study.main(["score", "--set", tiny_set, "--ckpt", "shipped", "sweep", "--out", str(tmp_path / "t.md")])
    table = (tmp_path / "t.md").read_text()
    assert "| shipped (all) | 3 |" in table and "| sweep (gather coffee) | 3 |" in table
    assert "| physics (twin) (all) | 3 |" in table and "error_mm" not in results["physics (twin)"]["all"]
    assert s.twin_c.shape == s.true_c.shape and np.all(np.isfinite(s.twin_c)) and not np.array_equal(s.twin_c, s.true_c)
    assert -1 <= results["shipped"]["all"]["spearman"]["mean"] <= 1 and results["sweep"]["all"]["error_mm"]["mean"] > 0
    # the truth is c of the carried particles: recomputed from them, it is the saved true c
    import jax

    from dynres_jax.control.goals import make_goal
    from dynres_jax.control.objective import objective

    for i in range(len(s.group)):
        goal = make_goal(s.goal_mask[i], s.camera)
        again = jax.vmap(lambda p, i=i, goal=goal: objective(p, s.mask[i], goal, s.camera))(s.true_positions[i])
        np.testing.assert_allclose(np.asarray(again), s.true_c[i], rtol=1e-5)


@pytest.mark.slow
def test_concatenate_pads_slots_and_refuses_other_cameras(tiny_set):
    s = ranking.load(tiny_set)
    narrow = s._replace(positions=s.positions[:, :50], mask=s.mask[:, :50], true_positions=s.true_positions[:, :, :50])
    both = ranking.concatenate([s, narrow])
    assert both.positions.shape[1] == s.positions.shape[1] and len(both.group) == 2 * len(s.group)
    np.testing.assert_array_equal(both.mask[len(s.group):, 50:], False)
    from dynres_jax.config import CameraConfig, SimConfig
    with pytest.raises(ValueError, match="different cameras"):
        ranking.concatenate([s, s._replace(sim=SimConfig(camera=CameraConfig(width=64, height=64)))])


def test_listwise_loss_is_listnets_cross_entropy_by_hand():
    from dynres_jax.learn.rank_loss import listwise

    pred, true = np.array([2.0, 1.0, 4.0]), np.array([1.0, 3.0, 2.0])
    p = np.exp(-true) / np.exp(-true).sum()
    q = np.exp(-pred / 2) / np.exp(-pred / 2).sum()
    assert float(listwise(pred, true, 1.0)) != pytest.approx(float(listwise(true, true, 1.0)))
    assert float(listwise(pred, true * 2, 2.0)) == pytest.approx(-np.sum(p * np.log(q)), rel=1e-5)


@pytest.mark.slow
def test_rank_finetuning_lowers_the_listwise_loss_it_trains():
    """Fine-tuning on the ranking alone (no position loss) lowers that loss on the states it trained on (six states
    of the committed M&M set, all their 51 candidates), from a fresh small model (the shipped one is already
    fine-tuned on it)."""
    import os

    import jax
    from flax import nnx

    from dynres_jax.learn.rank_loss import arrays, finetune, state_losses
    from dynres_jax.models.dynamics import DynamicsConfig
    from dynres_jax.models.registry import make_model

    full = ranking.load(os.path.join(os.path.dirname(__file__), "..", "docs", "dynamics_scale", "sets",
                                     "gather_mnm.npz"))
    s = full._replace(**{k: getattr(full, k)[:6] for k in ranking.RankingSet._fields[:-1]})
    model = make_model(DynamicsConfig(hidden=16, propagation_steps=1), seed=3)

    def loss(m):
        graphdef, params = nnx.split(m)
        return float(np.mean(jax.vmap(lambda *x: state_losses(graphdef, params, x, s.camera, 1.0)[0])(*arrays(s))))

    tuned = finetune(model, s, steps=20, batch=6, lr=1e-2, temperature=1.0, rank_weight=1.0, position_weight=0.0,
                     log=lambda *_: None)
    assert loss(tuned) < 0.85 * loss(model)  # measured: 0.78


def test_a_set_without_twins_is_scored_without_the_ceiling(tiny_set, tmp_path):
    from dynres_jax.errors import InputError
    from studies import ranking as study

    s = ranking.load(tiny_set)
    bare = s._replace(twin_c=np.full_like(s.twin_c, np.nan))
    with pytest.raises(InputError, match="no twins"):
        ranking.score_ceiling(bare)
    ranking.save(str(tmp_path / "bare.npz"), bare)
    results = study.main(["score", "--set", str(tmp_path / "bare.npz"), "--ckpt", "sweep", "--out",
                          str(tmp_path / "t.md")])
    assert list(results) == ["sweep"]


@pytest.mark.slow
def test_rank_finetune_saves_a_checkpoint_the_planner_loads(tiny_set, tmp_path):
    """--save writes the fine-tuned model with the source's card: it loads as a planner model, predicts otherwise than
    the source, and a second run refuses to overwrite it."""
    from dynres_jax.models.registry import SHIPPED_DYNAMICS
    from studies import rank_finetune

    out = str(tmp_path / "tuned")
    rank_finetune.main(["--train", tiny_set, "--test", tiny_set, "--out", str(tmp_path / "r"), "--steps", "3",
                        "--batch", "2", "--lr", "1e-3", "--save", out])
    s = ranking.load(tiny_set)
    tuned = ranking.predict(s, load_dynamics("learned", out, s.sim.scene.plate_half_width).dynamics)[1]
    source = ranking.predict(s, load_dynamics("learned", SHIPPED_DYNAMICS, s.sim.scene.plate_half_width).dynamics)[1]
    assert np.abs(tuned - source).max() > 1e-5
    meta = ckpt.load_module(out, build_model)[1]
    assert meta["step"] == 3 and meta["rank_finetune"]["steps"] == 3  # the folder's step, not the source's
    with pytest.raises(SystemExit):
        rank_finetune.main(["--train", tiny_set, "--test", tiny_set, "--out", str(tmp_path / "r"), "--save", out])
