"""How well can any model predict a push? The physics noise floor of the dynamics target (issue 4).

A pushed pile is chaotic: two worlds whose pieces differ by far less than a camera pixel end a push in visibly
different places. This measures that spread and turns it into a lower bound on the one-step error that any
predictor working from the observation can reach, next to the sweep heuristic and a trained model on the same pushes.

For scenes drawn as the training data's (``DataConfig`` defaults, C MuJoCo), each world is reset and pushed
``--pushes`` times along random pushes (``PileEnv.sample_push``). Before each push, particles are sampled from the
observation at every ω (perception h) and attached to their pieces; then, besides the push itself, K twins of
the world are pushed the same way, each with every piece's centre moved by independent Gaussian noise of standard
deviation σ in x and y (``--sigmas``, millimetres; sub-pixel: a pixel is about 3 mm). A twin is scored by each
particle's displacement from its own start (the particle carried with its moved piece), so the moves that make the
twins differ are not counted as error: at σ well below a millimetre the twins differ only where physics does
(contact order, friction's stick or slip). Reported per ω, over all particles, in mm:

- the sweep heuristic's and the model's error against the unperturbed outcome (as ``eval_dynamics`` measures it);
- the twins' distance E|D1 - D2| between the same particle's displacements in two twins;
- the floor E|D1 - D2| / 2. For displacements D1, D2 drawn independently given the observation and any prediction
  p made from it, |D1 - D2| <= |D1 - p| + |D2 - p|, so E|D - p| >= E|D1 - D2| / 2: no predictor beats the floor on
  worlds known only to within σ;
- with ``--twins K`` (K >= 3) the achievable floor: the error of the other twins' median displacement (per
  coordinate) against a held-out twin's, each twin held out in turn. A predictor that simulates K - 1 worlds known
  to within σ reaches it, so the best predictor lies between the floor and the achievable floor.

Every quantity is also split by where the particle starts relative to the push (``graph.SWEEP_REGIONS``: swept,
band edge, off the path), the error lying mostly where the plate passes.

Each scene's sums are written atomically to ``OUT/scenes/``; a killed run resumes where it stopped. At the end:
``OUT/floor.json``, ``floor.md`` (the tables) and ``floor.png`` (the floor against σ, as a share of the heuristic).

    python -m studies.noise_floor --out runs/noise_floor --scenes 48 --worlds 8
    python -m studies.noise_floor --out runs/achievable --twins 5 --sigmas 0.01 0.1 1 --omegas 50 100
"""

from __future__ import annotations

import argparse
import glob
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from tqdm import tqdm

from dynres_jax.io import ckpt, files
from dynres_jax.learn import data, targets
from dynres_jax.models.dynamics import predict, resolution_code
from dynres_jax.models.graph import SWEEP_REGIONS, sweep_region, sweep_rollout
from dynres_jax.models.registry import SHIPPED_DYNAMICS, build_model
from dynres_jax.perception import sample_particles
from dynres_jax.sim.env import State
from dynres_jax.sim.pool import WorldPool, process_pool


def perturb(states: State, qpos_adr, sigma: float, key) -> tuple[State, jax.Array]:
    """Batched states [B] with every piece's centre moved by N(0, σ²) in x and y: qpos_adr [N] (each piece's first
    qpos), sigma in metres -> (the states, the moves [B, N, 2] m). Velocities and poses are kept (poses are
    recomputed by the next push)."""
    adr = jnp.asarray(qpos_adr)
    noise = sigma * jax.random.normal(key, (states.qpos.shape[0], len(adr), 2))
    qpos = states.qpos.at[:, adr].add(noise[..., 0]).at[:, adr + 1].add(noise[..., 1])
    return states._replace(qpos=qpos), noise


def distance_sum(a, b, valid) -> float:
    """Sum over valid entries of |a - b| (metres): a, b [..., 3], valid [...] bool (broadcast to a's leading axes)."""
    d = np.linalg.norm(np.asarray(a, np.float64) - np.asarray(b, np.float64), axis=-1)
    return float(d[np.broadcast_to(np.asarray(valid, bool), d.shape)].sum())


def held_out_median(twins) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-out medians: twins [K, ...3] positions (K >= 3) -> (medians, held) [K, ...3], medians[j] the
    per-coordinate median of every twin but j, held[j] twin j."""
    twins = np.asarray(twins, np.float64)
    k = len(twins)
    medians = np.stack([np.median(np.delete(twins, j, axis=0), axis=0) for j in range(k)])
    return medians, twins


def _tracks(worlds: WorldPool, n_max: int, max_points):
    """Jitted (obs [B], pos [B, N, 3], mat [B, N, 3, 3], omega, keys [B]) -> (particles [B, n_max, 3], mask, piece
    index, local offsets, radius [B]): perception h at ω, each particle attached to its piece."""
    piece_mask = jnp.ones(worlds.scene.n_pieces, bool)

    def one(obs, pos, mat, omega, key):
        p = sample_particles(obs, worlds.camera, omega, key, n_max, max_points=max_points)
        index, local = targets.attach_particles(p.positions, p.mask, pos, mat, obs.piece, worlds.camera, piece_mask)
        return p.positions, p.mask & (p.error == 0), index, local, p.radius

    return jax.jit(jax.vmap(one, in_axes=(0, 0, 0, None, 0)))


@jax.jit
@jax.vmap
def _lifted(moves, index):
    """Each particle's share of its piece's move: moves [B, N, 2] m, index [B, n] -> [B, n, 3] (z 0)."""
    return jnp.pad(moves[index], ((0, 0), (0, 1)))


_regions = jax.jit(jax.vmap(sweep_region, in_axes=(0, 0, None)))


# One push predicted per world, compiled once per model structure (not per scene: shapes are [B, n_max]).
_step = jax.jit(jax.vmap(predict, in_axes=(None, None, 0, 0, 0, 0)), static_argnums=0)
_sweep = jax.jit(jax.vmap(lambda x, m, a, w: sweep_rollout(x, m, a[None], w)[0], in_axes=(0, 0, 0, None)))


@jax.jit
@jax.vmap
def trajectories(index, local, pos, mat):
    """Particles carried with their pieces to one new pose: index [B, n], local [B, n, 3], pos [B, N, 3], mat [B, N, 3,
    3] -> [B, n, 3] (``targets.particle_trajectory`` per world)."""
    return targets.particle_trajectory(index, local, pos[None], mat[None])[0]


def measure_scene(config: data.DataConfig, scene: int, args, models: dict, pool) -> dict:
    """One scene's sums: {ω: {quantity: metres summed over particles, "particles": count}}; models: {name: (graphdef,
    params)}, each scored as "model NAME" on the same pushes and particles."""
    sim = data.shard_sim_config(config, scene)
    worlds = WorldPool(sim, pool)
    n_max, max_points, plate_half_width = args.model_settings
    tracks = _tracks(worlds, n_max, max_points)
    key = jax.random.fold_in(jax.random.PRNGKey(args.seed), scene)
    k_reset, key = jax.random.split(key)
    states = worlds.reset(jax.random.split(k_reset, args.worlds))
    sums = {str(o): {} for o in args.omegas}
    for _ in range(args.pushes):
        k_push, k_twin, k_h, key = jax.random.split(key, 4)
        actions = np.array(jax.vmap(worlds.env.sample_push)(jax.random.split(k_push, args.worlds), states.pos))
        # A push clipped at the bin's wall may come out shorter than the simulator takes (data generation makes it a
        # no-op): such a world is pushed the shortest allowed way towards the bin's centre instead and left out of
        # this push's sums.
        short = np.hypot(*(actions[:, 2:] - actions[:, :2]).T) < sim.push.min_length
        actions[short, 2:] = actions[short, :2]
        actions[short, 2] -= np.where(actions[short, 0] > 0, 1, -1) * sim.push.min_length
        outcome = worlds.push(states, actions)
        twins = {}  # σ -> [(the twin pushed, its pieces' moves [B, N, 2])] * K
        for i, sigma in enumerate(args.sigmas):
            keys = jax.random.split(jax.random.fold_in(k_twin, i), args.twins)
            starts = [perturb(states, worlds.scene.qpos_adr, sigma / 1000, k) for k in keys]
            twins[sigma] = [(worlds.push(start, actions), moves) for start, moves in starts]
        broken = [outcome.broken] + [t.broken for pair in twins.values() for t, _ in pair]
        ok = ~short & ~np.any(np.asarray(broken), 0)
        for omega in args.omegas:
            x, mask, index, local, radius = tracks(states.obs, states.pos, states.mat, omega,
                                                   jax.random.split(k_h, args.worlds))
            valid = np.asarray(mask) & ok[:, None]
            truth = trajectories(index, local, outcome.pos, outcome.mat)
            start = trajectories(index, local, states.pos, states.mat)
            pairs = [("sweep heuristic", _sweep(x, mask, actions, plate_half_width), truth)]
            pairs += [(f"model {name}", _step(g, p, x, mask, actions, resolution_code(radius)), truth)
                      for name, (g, p) in models.items()]
            for sigma, ts in twins.items():  # each twin's displacement from its own start (its pieces moved)
                ends = [trajectories(index, local, t.pos, t.mat) - start - _lifted(moves, index) for t, moves in ts]
                pairs.append((f"twins {sigma:g} mm", ends[0], ends[1]))
                if len(ends) >= 3:
                    medians, held = held_out_median(ends)
                    k = len(ends)  # each held-out twin counts 1/K, so the sums stay per particle
                    pairs.append((f"achievable {sigma:g} mm", medians / k, held / k))
            region = np.asarray(_regions(x, actions, plate_half_width))
            row = sums[str(omega)]
            subsets = [("", valid)] + [(f" | {r}", valid & (region == i)) for i, r in enumerate(SWEEP_REGIONS)]
            for part, where in subsets:
                for name, a, b in pairs:
                    row[name + part] = row.get(name + part, 0.0) + distance_sum(a, b, where)
                row["particles" + part] = row.get("particles" + part, 0) + int(where.sum())
        states = outcome
    return {"scene": scene, "kinds": list(sim.scene.kinds), "pieces": list(sim.scene.pieces), "sums": sums}


def _means(rows: list[dict], sigmas, part: str = "") -> dict:
    """Sums of one subset of particles (part: "" for all, " | REGION" for one) -> {quantity: mm, "particles": n},
    each σ's floor half the twins' distance."""
    n = max(sum(r.get("particles" + part, 0) for r in rows), 1)
    names = [k for k in rows[0] if " | " not in k and k != "particles"]
    mean = {k: sum(r.get(k + part, 0.0) for r in rows) / n * 1000 for k in names}
    for sigma in sigmas:
        mean[f"floor {sigma:g} mm"] = mean[f"twins {sigma:g} mm"] / 2
    return dict(mean, particles=sum(r.get("particles" + part, 0) for r in rows))


def summarise(results: list[dict], omegas, sigmas) -> dict:
    """Scene sums -> {ω: {quantity: mean over particles in mm, "particles": n, "regions": {region: the same over the
    particles starting there}}}, each σ's floor half the twins' distance."""
    out = {}
    for omega in omegas:
        rows = [r["sums"][str(omega)] for r in results]
        regions = {r: _means(rows, sigmas, f" | {r}") for r in SWEEP_REGIONS}
        out[str(omega)] = dict(_means(rows, sigmas), regions=regions)
    return out


def _columns(m: dict, sigmas, names) -> list[str]:
    """The quantities a table shows, in order: heuristic, models, per σ the twins, the floor and (when measured) the
    achievable floor."""
    per_sigma = [f"{q} {s:g} mm" for s in sigmas for q in ("twins", "floor", "achievable") if f"{q} {s:g} mm" in m]
    return ["sweep heuristic", *[f"model {n}" for n in names], *per_sigma]


def table(summary: dict, sigmas, names) -> str:
    """Markdown: per ω the heuristic, each model, and per σ the twins' distance, the floor and the achievable floor
    (mm), with ratios: model / heuristic, floor / heuristic at the first σ, model / achievable at each σ."""
    models = [f"model {n}" for n in names]
    first = next(iter(summary.values()))
    head = _columns(first, sigmas, names)
    achievable = [f"achievable {s:g} mm" for s in sigmas if f"achievable {s:g} mm" in first]
    ratios = ([(m, "sweep heuristic") for m in models] + [(f"floor {sigmas[0]:g} mm", "sweep heuristic")]
              + [(m, a) for a in achievable for m in models])
    labels = [f"{a} / {b}".replace("sweep heuristic", "heuristic") for a, b in ratios]
    lines = [f"| ω | {' | '.join(head + labels)} |", "|---:|" + "---:|" * (len(head) + len(labels))]
    for omega, m in summary.items():
        values = [m[k] for k in head] + [m[a] / m[b] for a, b in ratios]
        lines.append(f"| {omega} | " + " | ".join(f"{v:.2f}" for v in values) + " |")
    return "\n".join(lines)


def region_table(summary: dict, sigmas, names) -> str:
    """Markdown: the same quantities per ω and per region of the push (``SWEEP_REGIONS``), with each region's share
    of the particles."""
    head = _columns(next(iter(summary.values())), sigmas, names)
    lines = [f"| ω | region | particles | {' | '.join(head)} |", "|---:|---|---:|" + "---:|" * len(head)]
    for omega, m in summary.items():
        for region, r in m["regions"].items():
            share = f"{r['particles'] / max(m['particles'], 1):.0%}"
            lines.append(f"| {omega} | {region} | {share} | " + " | ".join(f"{r[k]:.2f}" for k in head) + " |")
    return "\n".join(lines)


def plot(summary: dict, sigmas, names, path: str) -> None:
    """Floor against σ (log axis) per ω, beside the heuristic, the model and the issue's target (half the
    heuristic), all as a share of the heuristic's error."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 3.8))
    ax = fig.subplots()
    for i, (omega, m) in enumerate(summary.items()):
        colour = f"C{i}"
        ax.plot(sigmas, [m[f"floor {s:g} mm"] / m["sweep heuristic"] for s in sigmas], "o-", color=colour,
                label=f"floor, ω = {omega}")
        if all(f"achievable {s:g} mm" in m for s in sigmas):
            ax.plot(sigmas, [m[f"achievable {s:g} mm"] / m["sweep heuristic"] for s in sigmas], "s--",
                    color=colour, label=f"achievable (median of twins), ω = {omega}")
        for name in names:
            ax.axhline(m[f"model {name}"] / m["sweep heuristic"], color=colour, ls=":", lw=1)
    ax.axhline(0.5, color="k", ls="--", lw=1, label="target: half the heuristic")
    ax.plot([], [], "k:", lw=1, label="model (dotted, per ω)")
    ax.set(xscale="log", xlabel="σ of the twins' piece moves (mm)", ylabel="one-step error / sweep heuristic's",
           ylim=(0, 1), title="The floor no predictor beats")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def model_name(path: str) -> str:
    """A checkpoint's name in the table: "shipped", or the run folder's (runs/NAME/ckpt: NAME)."""
    path = os.path.abspath(path)
    if path == os.path.abspath(SHIPPED_DYNAMICS):
        return "shipped"
    return os.path.basename(os.path.dirname(path) if os.path.basename(path) == "ckpt" else path)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m studies.noise_floor", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--ckpt", nargs="+", default=[SHIPPED_DYNAMICS],
                        help="dynamics checkpoint(s), each scored on the same pushes (default: the shipped one); "
                             "named by the folder above ckpt/ (runs/NAME/ckpt: NAME), or 'shipped'")
    parser.add_argument("--scenes", type=int, default=48, help="scenes, drawn as the training data's shards")
    parser.add_argument("--worlds", type=int, default=8, help="worlds per scene")
    parser.add_argument("--pushes", type=int, default=2, help="pushes per world")
    parser.add_argument("--twins", type=int, default=2,
                        help="twins per σ; 3 or more also measure the achievable floor (median of the others)")
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.01, 1.0],
                        help="twins' perturbation, standard deviation per axis (mm)")
    parser.add_argument("--omegas", type=int, nargs="+", default=[10, 25, 50, 100])
    parser.add_argument("--seed", type=int, default=1, help="scene seed (training data uses 0)")
    parser.add_argument("--workers", type=int, default=None, help="C MuJoCo processes (default: every core)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    for name in ("scenes", "worlds", "pushes"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be at least 1")
    if args.twins < 2:
        parser.error(f"--twins must be at least 2 (the floor compares two), got {args.twins}")
    if any(s < 0 for s in args.sigmas):
        parser.error(f"--sigmas must be non-negative, got {args.sigmas}")
    models, settings_of = {}, set()
    for path in args.ckpt:
        module, meta, _ = ckpt.load_module(path, build_model)
        models[model_name(path)] = nnx.split(module)
        settings_of.add((meta["train"]["n_max"], meta["train"]["max_points"], meta["dynamics"]["plate_half_width"]))
    if len(models) < len(args.ckpt) or len(settings_of) > 1:
        parser.error("--ckpt: the models need distinct names and the same n_max, max_points and plate width")
    args.model_settings = settings_of.pop()
    n_max = args.model_settings[0]
    if max(args.omegas) > n_max or min(args.omegas) < 1:
        parser.error(f"--omegas must lie in [1, the model's n_max = {n_max}]")
    config = data.DataConfig(seed=args.seed, backend="mujoco")
    folder = os.path.join(args.out, "scenes")
    os.makedirs(folder, exist_ok=True)
    settings = {k: getattr(args, k) for k in ("ckpt", "worlds", "pushes", "twins", "sigmas", "omegas", "seed")}
    settings_path = os.path.join(args.out, "settings.json")
    if os.path.exists(settings_path) and json.load(open(settings_path)) != settings:
        parser.error(f"{args.out} holds a run with other settings ({settings_path}); use another --out")
    files.write_json(settings_path, settings)
    with process_pool(args.workers) as pool:
        for scene in tqdm(range(args.scenes), desc="scenes", disable=args.no_progress):
            path = os.path.join(folder, f"scene_{scene:05d}.json")
            if not os.path.exists(path):
                files.write_json(path, measure_scene(config, scene, args, models, pool))
    results = [json.load(open(p)) for p in sorted(glob.glob(os.path.join(folder, "scene_*.json")))[:args.scenes]]
    summary = {"scenes": len(results), "settings": settings,
               "omegas": summarise(results, args.omegas, args.sigmas)}
    files.write_json(os.path.join(args.out, "floor.json"), summary)
    plot(summary["omegas"], args.sigmas, list(models), os.path.join(args.out, "floor.png"))
    text = (table(summary["omegas"], args.sigmas, list(models))
            + "\n\nBy where each particle starts relative to the push:\n\n"
            + region_table(summary["omegas"], args.sigmas, list(models)))
    files.write_text(os.path.join(args.out, "floor.md"), text)
    print(text)
    return summary


if __name__ == "__main__":
    main()
