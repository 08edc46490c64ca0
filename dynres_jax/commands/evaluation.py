"""An evaluation's results (``evaluate``): each process's episodes of a method, merged over the job's processes in
episode order, success by the task's rule (``tasks.episode_success``), the summary (means with 95 % intervals,
success shares, every method paired with the reference: Δ final d with a paired-bootstrap interval and McNemar's test
on success) and its printed report.

Sort's episodes (``evaluate --task sort``) keep, beside final d (to the true goals, the mean over both kinds) and the
inside share (the lower kind's share inside its own goal), each kind's share [E, 2] and the mixing [E], by step and at
the end; its success is both kinds at least ``tasks.SORT_INSIDE`` inside and mixing below ``tasks.SORT_MIXING``.
"""

from __future__ import annotations

import jax
import numpy as np

from dynres_jax.commands import methods
from dynres_jax.control import tasks
from dynres_jax.stats import mcnemar, paired_bootstrap, wilson


def sort_records(records: list[dict]) -> list[dict]:
    """Sort's step records (``sort.SortEpisodes``' scores) as an evaluation reads them: distance, d to the true goals
    (``goal_distance``; the loop's own d is against the step's waypoints), and inside, the lower kind's share inside
    its own goal."""
    return [dict(r, distance=r["goal_distance"], inside=np.min(r["kind_inside"], axis=-1)) for r in records]


def episode_results(records: list[dict], episodes, name: str, starts, finals) -> dict:
    """One process's episodes of a method (``run_episodes``' records): per-step arrays [T][B] and the final values
    [B], with the episode indices [B], and where every piece started and ended (starts, finals: State [B]). Sort's
    records (``sort_records``) add kind_inside [T][B][2] and mixing [T][B]; one goal an episode, seen_inside
    [T][B] (the share the camera saw inside the goal before each push)."""
    steps = lambda key: np.stack([x[key] for x in records]).tolist()  # noqa: E731
    xy = lambda states: np.round(np.asarray(states.pos)[..., :2], 5).tolist()  # noqa: E731  (0.01 mm)
    sort = dict(kind_inside=steps("kind_inside"), mixing=steps("mixing")) if "kind_inside" in records[0] else {}
    seen = dict(seen_inside=steps("seen_inside")) if "seen_inside" in records[0] else {}
    return dict(episode=[int(i) for i in episodes], distance=steps("distance"), inside=steps("inside"),
                start_pieces=xy(starts), final_pieces=xy(finals),
                omega=steps("omega"), adam_steps=steps("adam_steps"), broken=records[-1]["broken"].tolist(),
                seconds=float(sum(x["seconds"] for x in records)), dynamics=name,
                device=jax.devices()[0].device_kind, **sort, **seen)


def merge(parts: list[dict]) -> dict:
    """The processes' ``episode_results`` of one method -> the method's results in episode order: final d and inside
    share [E], every step's [T][E] and their means per step [T], ω and Adam steps per step [T][E], broken [E],
    seconds (the slowest process's), and every piece's (x, y) at the start and the end [E][N][2] (m); Sort's adds
    final_kind_inside [E][2], final_mixing [E], mean_mixing [T], kind_inside [T][E][2] and mixing [T][E]; one goal
    an episode, seen_inside [T][E]."""
    order = np.argsort(np.concatenate([p["episode"] for p in parts]))
    cat = lambda key: np.concatenate([np.asarray(p[key]) for p in parts], axis=-1)[..., order]  # noqa: E731
    distance, inside = cat("distance"), cat("inside")
    pieces = lambda key: np.concatenate([np.asarray(p[key]) for p in parts])[order].tolist()  # noqa: E731
    merged = dict(final_distance=distance[-1].tolist(), final_inside=inside[-1].tolist(),
                  distance=distance.tolist(), inside=inside.tolist(),
                  start_pieces=pieces("start_pieces"), final_pieces=pieces("final_pieces"),
                  mean_distance=distance.mean(axis=1).tolist(), mean_inside=inside.mean(axis=1).tolist(),
                  omega=cat("omega").tolist(), broken=cat("broken").tolist(), adam_steps=cat("adam_steps").tolist(),
                  seconds=max(p["seconds"] for p in parts), dynamics=parts[0]["dynamics"], device=parts[0]["device"],
                  processes=len(parts))
    if "seen_inside" in parts[0]:
        merged.update(seen_inside=cat("seen_inside").tolist())
    if "kind_inside" in parts[0]:  # Sort: [T][B][2] per part, episodes on axis 1
        kind = np.concatenate([np.asarray(p["kind_inside"]) for p in parts], axis=1)[:, order]
        mixing = cat("mixing")
        merged.update(final_kind_inside=kind[-1].tolist(), final_mixing=mixing[-1].tolist(),
                      mean_mixing=mixing.mean(axis=1).tolist(), kind_inside=kind.tolist(), mixing=mixing.tolist())
    return merged


def summarise(results: dict, task: str) -> dict:
    """Per method: means with 95 % intervals, the success share (by ``task``'s rule) and the share that met the rule
    at some step (``reached_share``: at most what a stop rule could keep); Sort's adds the mean final share of each
    kind inside its goal and the mixing. Beside them, ``paired``: each other method against the
    reference (adaptive when evaluated, else the first method) on the same episodes: the mean of its final d minus
    the reference's with a paired-bootstrap 95 % interval, and McNemar's test on success."""
    out, success = {}, {method: tasks.episode_success(task, r) for method, r in results.items()}
    for method, r in results.items():
        d, inside = np.array(r["final_distance"]), np.array(r["final_inside"])
        n, k = len(d), int(np.sum(success[method]))
        reached = int(np.sum(tasks.step_success(task, r).any(axis=0)))  # met the rule at some step
        out[method] = dict(episodes=n, final_distance=float(d.mean()),
                           final_distance_ci95=float(1.96 * d.std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0,
                           final_inside=float(inside.mean()), success_share=k / n, success_ci95=wilson(k, n),
                           reached_share=reached / n,
                           mean_omega=float(np.mean(r["omega"])), broken=int(np.sum(r["broken"])),
                           dynamics=r.get("dynamics"))
        if "final_kind_inside" in r:
            out[method].update(final_kind_inside=np.mean(r["final_kind_inside"], axis=0).tolist(),
                               final_mixing=float(np.mean(r["final_mixing"])))
    reference = "adaptive" if "adaptive" in results else next(iter(results))
    paired = {}
    for method, r in results.items():
        if method == reference or len(r["final_distance"]) < 2:
            continue
        paired[method] = dict(delta_d=paired_bootstrap(r["final_distance"], results[reference]["final_distance"]),
                              success=mcnemar(success[method], success[reference]))
    summary = dict(methods=out, reference=reference, paired=paired)
    fixed = [m for m in results if m.isdigit()]
    if fixed and "oracle" in results and "adaptive" in results:  # how much of the oracle's gain adaptive recovers
        best = min(fixed, key=lambda m: out[m]["final_distance"])
        gain = out[best]["final_distance"] - out["oracle"]["final_distance"]
        summary["oracle_gap"] = dict(best_fixed=best, oracle_gain=gain,
                                     adaptive_gain=out[best]["final_distance"] - out["adaptive"]["final_distance"],
                                     recovered=((out[best]["final_distance"] - out["adaptive"]["final_distance"]) / gain
                                                if gain > 0 else None))
    return summary


def label(name: str, r: dict) -> str:
    """A method's name in the plots (``methods.METHODS``' label): "ω = 50", "adaptive", "CNN, ω = 50", "best of 5,
    ω = 50"."""
    return methods.method(name).label(name, r["omega"])


def report(summary: dict) -> None:
    """Each method's line and each paired comparison's."""
    rule = tasks.success_rule(summary["task"])
    for method, s in summary["methods"].items():
        sort = (f"  kinds inside {' / '.join(f'{x:.1%}' for x in s['final_kind_inside'])}, mixing "
                f"{s['final_mixing']:.1%}") if "final_kind_inside" in s else ""
        print(f"{method:>8}: final d {s['final_distance']:8.2f} ± {s['final_distance_ci95']:.2f}  inside "
              f"{s['final_inside']:.1%}{sort}  {rule} in {s['success_share']:.0%} of episodes "
              f"({s['reached_share']:.0%} at some step)  mean ω {s['mean_omega']:.1f}")
    for method, p in summary["paired"].items():
        lo, hi = p["delta_d"]["ci95"]
        m = p["success"]
        print(f"{method:>8} - {summary['reference']}: Δd {p['delta_d']['mean']:+.2f} [{lo:+.2f}, {hi:+.2f}]  "
              f"successes only here {m['first_only']}, only there {m['second_only']} (McNemar p = {m['p']:.3f})")
