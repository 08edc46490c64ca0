"""The ranking benchmark of the dynamics f(z, u, ω): does a model order the planner's own candidate pushes as the
simulator does?

The closed loop fails where the model ranks the planner's refined plans wrongly (docs/ladder: the simulator choosing
among the same plans succeeds far more often). A ranking set holds S planning states the closed loop visits (the
particles the planner saw and its goal) and, for each, C candidate pushes (the planner's M plans after its Adam steps
and its best), each pushed on a copy of the world in C MuJoCo (``studies.ranking`` builds it). The true outcome of a
candidate is the task objective c of the same particles carried rigidly with their pieces to where the push left
them (``targets.attach_particles``): what a perfect particle model would predict. A model's prediction is c of its
predicted particles. Scores per state (``ranking_scores``): Spearman's and Kendall's rank correlations between
predicted and true c, the top-1 regret (true c of the model's pick minus the best true c, pixels), whether the pick is
among the true top 5, and the one-step error of the predicted particles (mm); ``summarise`` gives their means over
states with bootstrap intervals.
"""

from __future__ import annotations

import functools
import json
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import rankdata

from dynres_jax.config import SimConfig
from dynres_jax.control.decision import goal_cost
from dynres_jax.control.goals import Goal, make_goals
from dynres_jax.errors import InputError
from dynres_jax.io.shards import save_npz
from dynres_jax.sim.camera import Camera
from dynres_jax.stats import bootstrap_mean

TOP = 5  # a pick counts as good when it is among the true TOP best candidates
BOOTSTRAP = 2000  # resamplings of the states for the intervals
SET_FILE = "ranking_set.npz"


class RankingSet(NamedTuple):
    """S planning states with C candidate pushes each (N particle slots, H x W images). group [S] str: what the
    state comes from (e.g. "gather mnm"); positions [S, N, 3] m, mask [S, N], radius [S] m: the particles the planner
    saw; goal_mask [S, H, W] bool; candidates [S, C, 4] m: first pushes; true_positions [S, C, N, 3] m: the particles
    carried with their pieces by each push in the simulator; true_c [S, C]: c of those (pixels); true_d [S, C]: the
    distance d of the simulated frame after each push (pixels); twin_c [S, C]: c of the particles carried by each
    push on a twin of the world whose pieces were moved by about a millimetre (the physics ceiling: how well the
    world itself, known to within a millimetre, ranks the candidates; NaN in a set built without twins);
    sim: the scenes' SimConfig (its camera)."""

    group: np.ndarray
    positions: np.ndarray
    mask: np.ndarray
    radius: np.ndarray
    goal_mask: np.ndarray
    candidates: np.ndarray
    true_positions: np.ndarray
    true_c: np.ndarray
    true_d: np.ndarray
    twin_c: np.ndarray
    sim: SimConfig

    @property
    def has_twins(self) -> bool:
        """Whether the set was built with twins (``twin_c`` finite), so it has a physics ceiling."""
        return bool(np.isfinite(self.twin_c).all())

    @property
    def camera(self) -> Camera:
        return Camera.top_down(self.sim.camera)


def save(path: str, ranking: RankingSet) -> None:
    """Write a set as one .npz (atomically), its SimConfig as JSON inside."""
    arrays = {k: np.asarray(v) for k, v in ranking._asdict().items() if k != "sim"}
    save_npz(path, {**arrays, "sim_config": np.array(ranking.sim.to_json())})


def load(path: str) -> RankingSet:
    """Read a set written by ``save`` (a file, or a folder holding SET_FILE); InputError naming what is missing."""
    if os.path.isdir(path):
        path = os.path.join(path, SET_FILE)
    if not os.path.exists(path):
        raise InputError(f"ranking set {path!r} does not exist (python -m studies.ranking build makes one)")
    with np.load(path) as f:
        missing = [k for k in (*RankingSet._fields[:-1], "sim_config") if k not in f]
        if missing:
            raise InputError(f"{path}: not a ranking set (no {', '.join(missing)})")
        fields = {k: f[k] for k in RankingSet._fields[:-1]}
        sim = SimConfig.from_json(str(f["sim_config"]))
    return RankingSet(**fields, sim=sim)


def concatenate(sets: list[RankingSet]) -> RankingSet:
    """Several sets of one camera as one (states appended; particle slots padded to the widest)."""
    if any(s.sim.camera != sets[0].sim.camera for s in sets):
        raise ValueError("ranking sets of different cameras cannot be joined")
    n = max(s.mask.shape[1] for s in sets)

    def pad(x, axis):
        widths = [(0, 0)] * x.ndim
        widths[axis] = (0, n - x.shape[axis])
        return np.pad(x, widths)

    slots = {"positions": 1, "mask": 1, "true_positions": 2}
    fields = {k: np.concatenate([pad(getattr(s, k), slots[k]) if k in slots else getattr(s, k) for s in sets])
              for k in RankingSet._fields[:-1]}
    return RankingSet(**fields, sim=sets[0].sim)


@functools.partial(jax.jit, static_argnames=("dynamics", "camera"))
def _predict(positions, mask, radius, goals, candidates, *, dynamics, camera):
    """Per state and candidate: (c of the predicted particles [S, C], the predicted particles [S, C, N, 3])."""

    def state(pos, m, r, goal, pushes):
        f, cost = dynamics(r), goal_cost(goal, camera)

        def one(push):
            final = f(pos, m, push[None])[-1]
            return cost(final, m), final

        return jax.vmap(one)(pushes)

    return jax.lax.map(lambda x: state(*x), (positions, mask, radius, goals, candidates))


def goals(ranking: RankingSet) -> Goal:
    """The states' goals [S], rebuilt from their masks (``make_goals``)."""
    return make_goals(ranking.goal_mask, ranking.camera)


def predict(ranking: RankingSet, dynamics) -> tuple[np.ndarray, np.ndarray]:
    """A planner dynamics (``registry``: radius -> (positions, mask, actions) -> [T, N, 3]) on every candidate of a
    set: (predicted c [S, C] pixels, predicted particles [S, C, N, 3] m)."""
    c, final = _predict(jnp.asarray(ranking.positions), jnp.asarray(ranking.mask), jnp.asarray(ranking.radius),
                        goals(ranking), jnp.asarray(ranking.candidates), dynamics=dynamics, camera=ranking.camera)
    return np.asarray(c), np.asarray(final)


def _ranks(x):
    """Ranks 0..C-1 of each row of x [S, C] (average ranks on ties)."""
    return rankdata(x, axis=1) - 1.0


def spearman(predicted, true) -> np.ndarray:
    """Spearman's rank correlation of each row of predicted and true [S, C] -> [S] (0 for a constant row)."""
    a, b = _ranks(np.asarray(predicted, np.float64)), _ranks(np.asarray(true, np.float64))
    a, b = a - a.mean(1, keepdims=True), b - b.mean(1, keepdims=True)
    den = np.sqrt(np.sum(a * a, 1) * np.sum(b * b, 1))
    return np.where(den > 0, np.sum(a * b, 1) / np.where(den > 0, den, 1.0), 0.0)


def kendall(predicted, true) -> np.ndarray:
    """Kendall's tau-b of each row of predicted and true [S, C] -> [S] (0 for a constant row)."""
    p, t = np.asarray(predicted, np.float64), np.asarray(true, np.float64)
    dp = np.sign(p[:, :, None] - p[:, None, :])
    dt = np.sign(t[:, :, None] - t[:, None, :])
    upper = np.triu(np.ones((p.shape[1], p.shape[1]), bool), 1)[None]
    concord = np.sum(dp * dt * upper, axis=(1, 2))
    n_p, n_t = np.sum((dp != 0) * upper, axis=(1, 2)), np.sum((dt != 0) * upper, axis=(1, 2))
    den = np.sqrt(n_p * n_t)
    return np.where(den > 0, concord / np.where(den > 0, den, 1.0), 0.0)


def ranking_scores(predicted_c, true_c, predicted_positions=None, true_positions=None, mask=None) -> dict:
    """Per-state scores [S] of a model's predicted c [S, C] against the true c [S, C]: spearman, kendall, regret (true
    c of the model's pick minus the lowest true c, pixels), top5 (1.0 when the pick is among the true TOP lowest) and,
    given the predicted and true particles [S, C, N, 3] with mask [S, N], error_mm: the mean distance between them
    over the valid particles and candidates (mm)."""
    predicted_c, true_c = np.asarray(predicted_c, np.float64), np.asarray(true_c, np.float64)
    pick = np.argmin(predicted_c, axis=1)
    rows = np.arange(len(pick))
    true_rank = _ranks(true_c)[rows, pick]
    scores = dict(spearman=spearman(predicted_c, true_c), kendall=kendall(predicted_c, true_c),
                  regret=true_c[rows, pick] - true_c.min(1), top5=(true_rank < TOP).astype(np.float64))
    if predicted_positions is not None:
        err = np.linalg.norm(np.asarray(predicted_positions) - np.asarray(true_positions), axis=-1)  # [S, C, N]
        w = np.broadcast_to(np.asarray(mask, np.float64)[:, None, :], err.shape)
        scores["error_mm"] = 1000 * np.sum(err * w, axis=(1, 2)) / np.maximum(np.sum(w, axis=(1, 2)), 1)
    return scores


def summarise(scores: dict, seed: int = 0) -> dict:
    """Per score: the mean over states and its 95 % percentile-bootstrap interval (states resampled)."""
    rng = np.random.default_rng(seed)  # one stream over the scores, in their order
    out = {}
    for name, values in scores.items():
        one = bootstrap_mean(values, rng, BOOTSTRAP)
        out[name] = dict(mean=one["mean"], ci95=list(one["ci95"]))
    return out


def by_group(ranking: RankingSet, per_state: dict) -> dict:
    """Per-state scores [S] -> {"all": summary, group: summary, ...} (``summarise``), with the states each covers."""
    out = {"all": dict(states=len(ranking.group), **summarise(per_state))}
    for group in sorted(set(ranking.group.tolist())):
        rows = ranking.group == group
        out[str(group)] = dict(states=int(rows.sum()), **summarise({k: v[rows] for k, v in per_state.items()}))
    return out


def score_model(ranking: RankingSet, dynamics) -> dict:
    """A model on a set (``by_group`` of ``ranking_scores``)."""
    c, final = predict(ranking, dynamics)
    return by_group(ranking, ranking_scores(c, ranking.true_c, final, ranking.true_positions, ranking.mask))


def score_ceiling(ranking: RankingSet) -> dict:
    """The physics ceiling in ``score_model``'s form: the twin's c ranking the candidates (no particle error).
    InputError for a set built without twins (its twin_c NaN)."""
    if not ranking.has_twins:
        raise InputError("this ranking set has no twins (built with --twin-sigma 0): no physics ceiling")
    return by_group(ranking, ranking_scores(ranking.twin_c, ranking.true_c))


def headline(scores: dict) -> str:
    """One line of a ``score_model`` (or ``score_ceiling``) result's "all" row: Spearman, top-5, regret, one-step."""
    a = scores["all"]
    line = f"Spearman {a['spearman']['mean']:.3f}, top-5 {a['top5']['mean']:.2f}, regret {a['regret']['mean']:.2f} px"
    return line + (f", one-step {a['error_mm']['mean']:.2f} mm" if "error_mm" in a else "")


def write_table(results: dict, path: str) -> None:
    """results {model name: ``score_model``} -> a Markdown table (one row per model and group; a score a row lacks is
    left blank) and the JSON beside it."""
    with open(os.path.splitext(path)[0] + ".json", "w") as f:
        json.dump(results, f, indent=1)
    lines = ["| model | states | Spearman | Kendall | top-1 regret (px) | pick in true top 5 | one-step error (mm) |",
             "|---|---|---|---|---|---|---|"]
    for name, groups in results.items():
        for group, s in groups.items():
            def cell(k, fmt="{:.3f}", s=s):
                if k not in s:
                    return ""
                return f"{fmt.format(s[k]['mean'])} [{fmt.format(s[k]['ci95'][0])}, {fmt.format(s[k]['ci95'][1])}]"

            lines.append(f"| {name} ({group}) | {s['states']} | {cell('spearman')} | {cell('kendall')} | "
                         f"{cell('regret')} | {cell('top5', '{:.2f}')} | {cell('error_mm', '{:.2f}')} |")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
