"""The resolution trade-off: the paper's Fig. 4 from Bayesian-optimisation labels, and the anytime surface.

    python -m experiments.tradeoff --labels runs/labels --out runs/tradeoff
    python -m experiments.tradeoff --surface --out runs/surface [--scenes 128] [--repeats 5]
    python -m experiments.tradeoff --reliability runs/labels_a runs/labels_b --out runs/reliability

Fig. 4 (``--labels``, from experiments.label_resolution): c+(ω) for the same pile with a disc vs a letter goal of the
same centre and area, and for the same central disc goal with a spread pile vs a pile near it, and how often each
claim holds.

The anytime surface (``--surface``): c*, the distribution distance d after one push planned with N Adam steps at
resolution ω and executed in the simulator, for every ω in SURFACE_OMEGAS and N in SURFACE_STEPS, on two kinds of
scene (``SURFACE_SCENES``: a spread pile with a disc goal; a pile already near a letter goal centred on it). Every ω
and N of a scene plans from the same key, so the same starting pushes (common random numbers). Beside it, this
device's timing table (seconds per decision at each bucket, one scene, the task batch), so c* can be read against
seconds. Writes ``surface.json`` (mean c* per scene kind, ω and N with 95 % intervals, the planner's own predicted c,
d before the push, the timing table) and ``surface.png``; each scene kind's raw values are saved as it finishes
(``surface_KIND.npz``; within a kind, each finished plan draw and ω in ``surface_KIND.partial.npz``) and a rerun goes
on where the last stopped. ``--repeats R`` plans every scene, ω and N R times from
independent keys (``mpc.draw_keys``: draw 0 the common key above, as the closed loop's plan draws), kept as
c_star_draws [R, ω, N, S] beside c_star (draw 0): what a cross-fitted oracle over ω needs
(``scripts/crossfit.py``).

Label reliability (``--reliability A B``): two label runs of the same scenes (``label_resolution`` with the same
``--seed`` and another ``--plan-seed``), scene by scene: the rank (Spearman) and Pearson correlations of the two
labels, their mean absolute difference, and what that bounds a regressor g to: its correlation with either run's
labels is at most the square root of the Pearson test-retest correlation, and its mean absolute error at least half
the runs' mean absolute difference (E|A - B| <= E|A - g| + E|g - B|, and A, B are exchangeable).

Claims (paper Sec. V-B): the best ω is higher for a letter than for a disc on the same pile, and higher for a
gathered pile (one blob) than for a spread one with the same goal. Reported: the share of pairs where the label is
higher, lower or equal, with 95 % Wilson intervals, and ``tradeoff.png`` with the GP mean of c+ for example pairs.
"""

from __future__ import annotations

import functools
import json
import os

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.commands import checks
from dynres_jax.commands.models import load_model
from dynres_jax.commands.planner_args import add_reference_planner_args, planner_options, priced, resolve_planner_args
from dynres_jax.commands.task import check_pile
from dynres_jax.config import CameraConfig, PileConfig, PushConfig, SceneConfig, SimConfig
from dynres_jax.control import tasks
from dynres_jax.control.budget import BUCKETS, TimingTable, bucket_for
from dynres_jax.control.decision import decide_batch, episode
from dynres_jax.control.goals import make_goals
from dynres_jax.control.mpc import MPCConfig, draw_keys, measure_timing
from dynres_jax.control.objective import distribution_distance
from dynres_jax.control.planner import planner_config
from dynres_jax.io import files
from dynres_jax.io.shards import complete_shards, read_shard, save_npz
from dynres_jax.models.registry import SHIPPED_DYNAMICS, LoadedDynamics
from dynres_jax.resolution.bo import CANDIDATES
from dynres_jax.sim.pool import WorldPool, process_pool
from dynres_jax.stats import wilson

SURFACE_OMEGAS = (10, 25, 50, 75, 100)
SURFACE_STEPS = (1, 5, 10, 20, 50, 100, 200)
SURFACE_SCENES = ("spread pile, disc goal", "pile near a letter goal")
LETTER_REACH = 0.03  # m: the near-letter scenes' pile and letter centres lie within this of the bin centre


def compare(high: np.ndarray, low: np.ndarray) -> dict:
    """Share of pairs whose first label is higher, lower, equal (with a Wilson interval on 'higher')."""
    n = len(high)
    k = int(np.sum(high > low))
    return dict(pairs=n, higher=k / n, lower=float(np.mean(high < low)), equal=float(np.mean(high == low)),
                higher_ci95=wilson(k, n), mean_first=float(high.mean()), mean_second=float(low.mean()))


@checks.guarded("tradeoff")
def main(argv=None):
    parser = checks.parser("tradeoff", __doc__)
    parser.add_argument("--labels", help="label shards of experiments.label_resolution (Fig. 4)")
    parser.add_argument("--out", required=True)
    checks.add_fresh(parser)
    parser.add_argument("--surface", action="store_true", help="measure the anytime surface instead")
    parser.add_argument("--reliability", nargs=2, metavar="LABELS", help="two label runs of the same scenes")
    parser.add_argument("--scenes", type=checks.count(2), default=128, help="surface: scenes of each kind")
    parser.add_argument("--samples", type=checks.samples, default=50, help="surface: pushes optimised at once (M)")
    parser.add_argument("--pieces", type=checks.count(1), default=100, help="surface: pieces in a pile")
    parser.add_argument("--repeats", type=checks.count(1), default=1,
                        help="surface: independent plans of every scene, ω and N (a cross-fitted oracle needs >= 3)")
    parser.add_argument("--ckpt", default=None, help="surface: dynamics checkpoint (default: the shipped one)")
    parser.add_argument("--workers", type=checks.workers(), default=None,
                        help="surface: C engine processes (default: every core)")
    parser.add_argument("--seed", type=checks.seed, default=0)
    parser.add_argument("--quick", action="store_true", help="surface: tiny sizes for a CPU smoke run")
    add_reference_planner_args(parser)
    args = parser.parse_args(argv)
    resolve_planner_args(parser, args)
    if sum(map(bool, (args.labels, args.surface, args.reliability))) != 1:
        parser.error("give exactly one of --labels (Fig. 4), --surface or --reliability")
    if args.surface:
        checks.quick_sets(parser, args, ("scenes", "samples", "pieces"))
        check_pile(parser, SceneConfig.kinds, (args.pieces,))
        model = load_model(parser, "auto", args.ckpt, SceneConfig.plate_half_width)
        checks.claim(args.out, "tradeoff", checks.settings(args), args.fresh,
                     {"--ckpt": args.ckpt or SHIPPED_DYNAMICS})
        return surface(args, model)
    if args.reliability:
        first, second = args.reliability
        if os.path.realpath(first) == os.path.realpath(second):  # a link to the same run too
            parser.error(f"--reliability needs two label runs of the same scenes, got {first} twice")
        for folder in (first, second):
            complete_shards(folder, "--reliability", "labels")
        try:
            check_same_scenes(first, second)
        except ValueError as e:
            parser.error(f"--reliability: {e}")
        checks.claim(args.out, "tradeoff", checks.settings(args), args.fresh, {"--reliability": args.reliability})
        return reliability(first, second, args.out)
    paths = complete_shards(args.labels, "--labels", "labels")
    checks.claim(args.out, "tradeoff", checks.settings(args), args.fresh, {"--labels": args.labels})
    shards = {int(z["shard"]): z for z in map(read_shard, paths)}
    letter_vs_disc, blob_vs_spread, examples = [], [], {}
    for s, z in shards.items():
        letter_vs_disc.append((z["label"][1::2], z["label"][0::2]))  # scenes 2j + 1 (letter) vs 2j (disc)
        examples.setdefault("goal", (z, 0, 1))
        if s % 2 == 0 and s + 1 in shards:  # shard s spread, s + 1 one blob near the goal, same goals: the discs
            blob_vs_spread.append((shards[s + 1]["label"][0::2], z["label"][0::2]))
            examples.setdefault("pile", (z, shards[s + 1]))
    ld = [np.concatenate(x) for x in zip(*letter_vs_disc, strict=True)]
    result = dict(letter_vs_disc=compare(*ld))
    if blob_vs_spread:
        result["gathered_vs_spread"] = compare(*[np.concatenate(x) for x in zip(*blob_vs_spread, strict=True)])
    os.makedirs(args.out, exist_ok=True)
    files.write_json(os.path.join(args.out, "tradeoff.json"), result)
    _plot(examples, os.path.join(args.out, "tradeoff.png"))
    print(json.dumps(result))  # JSON, as every command prints a record
    return result


def _plot(examples: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    z, a, b = examples["goal"]
    curves = [(axes[0], z, a, "disc goal"), (axes[0], z, b, "letter goal")]
    if "pile" in examples:
        spread, blob = examples["pile"]
        curves += [(axes[1], spread, 0, "spread pile"), (axes[1], blob, 0, "gathered pile")]
    for ax, shard, i, name in curves:
        (line,) = ax.plot(CANDIDATES, shard["gp_mean"][i], label=f"{name}: best ω = {int(shard['label'][i])}")
        ax.scatter(shard["omega"][i], shard["c_plus"][i], color=line.get_color(), s=12)
    axes[0].set(title="same pile, two goals", xlabel="ω", ylabel="c+(ω) (GP mean, points observed)")
    axes[1].set(title="same goal, two piles", xlabel="ω")
    for ax in axes:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def ranks(x) -> np.ndarray:
    """Ranks of x [n] from 1, ties given their mean rank."""
    x = np.asarray(x)
    order = np.argsort(x, kind="stable")
    r = np.empty(len(x))
    r[order] = np.arange(1, len(x) + 1)
    for value in np.unique(x):
        tied = x == value
        r[tied] = r[tied].mean()
    return r


def _labels_by_scene(folder: str) -> dict:
    """{(shard, index): label} of a label run."""
    out = {}
    for path in complete_shards(folder, "--reliability", "labels"):
        z = read_shard(path, ("shard", "label"))
        out.update({(int(z["shard"]), i): int(v) for i, v in enumerate(z["label"])})
    return out


SCENE_SETTINGS = ("seed", "batch", "kind", "pieces", "mid_episode", "quick")  # what makes label_resolution's scene


def check_same_scenes(first: str, second: str) -> None:
    """ValueError when two label runs' settings that make the scenes (SCENE_SETTINGS) differ: scene (shard, i) of one
    would be another pile than (shard, i) of the other."""
    settings = []
    for folder in (first, second):
        with open(os.path.join(folder, "config.json")) as f:
            config = json.load(f)
        settings.append({k: config.get(k) for k in SCENE_SETTINGS})
    differ = {k: (settings[0][k], settings[1][k]) for k in SCENE_SETTINGS if settings[0][k] != settings[1][k]}
    if differ:
        what = ", ".join(f"{k} {x} vs {y}" for k, (x, y) in differ.items())
        raise ValueError(f"{first} and {second} label different scenes ({what}); relabel with the same --seed and "
                         "another --plan-seed")


def reliability(first: str, second: str, out_dir: str) -> dict:
    """Label reliability of two runs over the same scenes (module docstring; ``check_same_scenes``) -> the summary
    written to reliability.json."""
    check_same_scenes(first, second)
    a, b = _labels_by_scene(first), _labels_by_scene(second)
    scenes = sorted(set(a) & set(b))
    if len(scenes) < 3:
        raise ValueError(f"{first} and {second} share {len(scenes)} scenes; reliability needs at least 3")
    x, y = np.array([a[s] for s in scenes], float), np.array([b[s] for s in scenes], float)
    pearson = float(np.corrcoef(x, y)[0, 1])
    result = dict(scenes=len(scenes), spearman=float(np.corrcoef(ranks(x), ranks(y))[0, 1]), pearson=pearson,
                  mean_abs_difference=float(np.mean(np.abs(x - y))), equal=float(np.mean(x == y)),
                  regressor_correlation_at_most=float(np.sqrt(max(pearson, 0.0))),
                  regressor_mae_at_least=float(np.mean(np.abs(x - y)) / 2),
                  label_mean=float(np.concatenate([x, y]).mean()))
    os.makedirs(out_dir, exist_ok=True)
    files.write_json(os.path.join(out_dir, "reliability.json"), result)
    print(json.dumps(result))  # JSON, as every command prints a record
    return result


def _scenes(kind: int, args, pool):
    """(start states [S], goal masks [S, H, W]) of one surface scene kind, seeded by (seed, kind, scene)."""

    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(args.seed + kind), i))(jnp.arange(args.scenes))
    starts = pool.reset(keys)
    masks = []
    for i in range(args.scenes):
        rng = np.random.default_rng((args.seed, kind, i))
        if kind == 0:
            masks.append(tasks.gather_goal(rng, pool.env)[0])
        else:  # the letter centred on the pile, so the pile is already near its goal
            centre = np.clip(np.asarray(starts.pos[i, :, :2]).mean(0), -LETTER_REACH, LETTER_REACH)
            masks.append(tasks.redistribute_goal(rng, pool.env, "JTU"[i % 3], centre)[0])
    return starts, np.stack(masks)


def _surface_scenes(pool, starts, goals, keys, dynamics, cfg, omegas, steps, scene_name: str, repeats: int = 1,
                    partial: str | None = None) -> dict:
    """c* and the predicted c [ω, N, S] and d before the push [S] of the scenes ``starts`` [S] with ``goals`` [S], each
    planned from its own key in ``keys`` [S] at every ω and N (common random numbers); with repeats R > 1 also
    c_star_draws [R, ω, N, S], draw r planned from ``mpc.draw_keys(keys, r)``. partial: a file the finished (draw, ω)
    are saved to as they finish (atomically) and read back from, so a killed run goes on where it stopped (the
    caller's run.json vouches for the same settings)."""
    camera = pool.camera
    measure = jax.jit(jax.vmap(lambda obs, goal: distribution_distance(obs, goal, camera)))
    draws = np.zeros((repeats, len(omegas), len(steps), len(keys)))
    predicted, done = np.zeros(draws.shape[1:]), np.zeros((repeats, len(omegas)), bool)
    if partial and os.path.exists(partial):
        with np.load(partial) as saved:
            draws, predicted, done = saved["draws"], saved["predicted"], saved["done"]
        print(f"  {scene_name}: {int(done.sum())} of {done.size} (plan draw, ω) kept from {partial}", flush=True)
    init = jnp.zeros((len(keys), cfg.planner.horizon, 4), jnp.float32)  # no warm start
    for r in range(repeats):
        drawn = draw_keys(keys, r)
        for i, omega in enumerate(omegas):
            if done[r, i]:
                continue
            for j, n in enumerate(steps):
                result = decide_batch(starts.obs, goals, drawn, init, False, np.full(len(keys), omega),
                                      np.full(len(keys), n), spec=cfg.spec(bucket_for(omega, cfg.buckets)),
                                      dynamics=dynamics, camera=camera)[2]
                after = pool.push(starts, result.best[:, 0])
                draws[r, i, j] = measure(after.obs, goals)
                if r == 0:
                    predicted[i, j] = result.best_cost
            done[r, i] = True
            if partial:
                save_npz(partial, dict(draws=draws, predicted=predicted, done=done))
            print(f"  {scene_name}{f', plan draw {r}' if repeats > 1 else ''}: ω = {omega:3d}: mean c* over N = "
                  f"{steps}: {np.round(draws[r, i].mean(axis=1), 2).tolist()}", flush=True)
    out = dict(c_star=draws[0], predicted=predicted, d0=np.asarray(measure(starts.obs, goals)))
    return dict(out, c_star_draws=draws) if repeats > 1 else out


def surface(args, model: LoadedDynamics) -> dict:
    """The anytime surface (module docstring) of ``model`` -> the summary written to surface.json."""
    near_centre_blob = PileConfig(layout="blob", centre_margin=SceneConfig.bin_half_width - LETTER_REACH)
    omegas, steps = SURFACE_OMEGAS, SURFACE_STEPS
    if args.quick:
        args.scenes, args.samples, args.pieces, omegas, steps = 2, 4, 12, (10, 25), (1, 3)
    dynamics, _, name = model
    raw, timing = {}, None
    with process_pool(args.workers) as processes:
        for kind, scene_name in enumerate(SURFACE_SCENES):
            push = PushConfig(max_length=0.1, settle_time=0.04) if args.quick else PushConfig()
            sim = SimConfig(scene=SceneConfig(pieces=(args.pieces,)), push=push,
                            pile=PileConfig(layout="spread") if kind == 0 else near_centre_blob,
                            camera=CameraConfig(width=64, height=64) if args.quick else CameraConfig())
            pool = WorldPool(sim, processes)
            planner = planner_config(pool.env, samples=args.samples, adam_steps=max(steps),
                                     **planner_options(args, pool.env))
            cfg = MPCConfig(mpc_steps=1, max_points=1024 if args.quick else 4096, planner=planner,
                            buckets=args.buckets)
            path = os.path.join(args.out, f"surface_{kind}.npz")
            starts, masks = _scenes(kind, args, pool)
            goals = make_goals(masks, pool.camera)
            if timing is None:
                timing = priced(args, cfg, functools.partial(measure_timing, episode(starts.obs), episode(goals),
                                                             dynamics, cfg, pool.camera))
            if os.path.exists(path):
                raw[kind] = dict(np.load(path))
                continue
            keys = jax.random.split(jax.random.PRNGKey(args.seed + 100 + kind), args.scenes)  # per scene, every ω, N
            partial = os.path.join(args.out, f"surface_{kind}.partial.npz")
            raw[kind] = _surface_scenes(pool, starts, goals, keys, dynamics, cfg, omegas, steps, scene_name,
                                        args.repeats, partial)
            save_npz(path, raw[kind])
            os.remove(partial)
    summary = dict(dynamics=name, device=timing.device, scenes=args.scenes, samples=args.samples,
                   repeats=args.repeats, omegas=omegas, steps=steps, buckets=list(cfg.buckets),
                   timing=timing.to_json(), kinds={})
    for kind, scene_name in enumerate(SURFACE_SCENES):
        r = raw[kind]
        n = r["c_star"].shape[-1]
        summary["kinds"][scene_name] = dict(
            d0=float(r["d0"].mean()), c_star=r["c_star"].mean(-1).tolist(),
            c_star_ci95=(1.96 * r["c_star"].std(-1, ddof=1) / np.sqrt(n)).tolist(),
            predicted=r["predicted"].mean(-1).tolist(),
            best_omega_by_steps={int(s): int(omegas[np.argmin(r["c_star"].mean(-1)[:, j])])
                                 for j, s in enumerate(steps)})
    files.write_json(os.path.join(args.out, "surface.json"), summary)
    _plot_surface(summary, os.path.join(args.out, "surface.png"))
    return summary


def _plot_surface(summary: dict, path: str) -> None:
    """c* against Adam steps (top) and against this device's seconds per decision (bottom), a line per ω."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = summary["kinds"]
    fig, axes = plt.subplots(2, len(kinds), figsize=(5 * len(kinds), 7), squeeze=False)
    timing = TimingTable(**summary["timing"])
    for col, (scene_name, k) in enumerate(kinds.items()):
        for i, omega in enumerate(summary["omegas"]):
            mean, ci = np.array(k["c_star"][i]), np.array(k["c_star_ci95"][i])
            steps = np.array(summary["steps"])
            key = timing.key(omega, summary.get("buckets", BUCKETS))
            seconds = np.array([timing.seconds(key, int(n)) for n in steps])
            for row, x in enumerate((steps, seconds)):
                ax = axes[row, col]
                ax.errorbar(x, mean, yerr=ci, label=f"ω = {omega}", marker="o", ms=3, capsize=2)
        for row, xlabel in enumerate(("Adam steps N", f"seconds per decision ({summary['device']})")):
            ax = axes[row, col]
            ax.axhline(k["d0"], color="grey", ls=":", label="d before the push")
            ax.set(xscale="log", xlabel=xlabel, ylabel="c*: d after the push (px)", title=scene_name)
            ax.legend(fontsize=7)
    fig.suptitle(f"anytime surface: {summary['scenes']} scenes per kind, M = {summary['samples']}")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
