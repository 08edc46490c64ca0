"""Pictures of an episode: a frame with its goal tinted and the planner's particles drawn (``overlay``), Sort's two
goals tinted (``tint``), and ``Frames``, the closed loop's ``on_step`` callback that collects GIF frames of episode 0;
and of an evaluation: its score and step curves (``evaluation_plots``).
"""

from __future__ import annotations

import os
from collections.abc import Callable

import cv2
import numpy as np

GOAL_TINT = np.array([60.0, 200.0, 60.0])  # RGB tint of the goal (green)
GOAL_TINTS = np.array([[60.0, 110.0, 235.0], [240.0, 150.0, 40.0]])  # Sort: goal 0 blue, goal 1 orange
PUSH_COLOUR = (30, 30, 220)  # RGB of the push's arrow (blue)


def overlay(rgb: np.ndarray, goal_mask: np.ndarray, particles: np.ndarray | None, camera, scale: int = 3,
            label: str = "", push=None):
    """An RGB frame [H, W, 3] uint8 with the goal tinted green, particles [n, 3] (world, m) as red dots, the push
    (x0, y0, x1, y1) m as a blue arrow from its start to its end, and an optional text label in the top-left
    corner."""
    img = rgb.astype(np.float32)
    img[goal_mask] = 0.6 * img[goal_mask] + 0.4 * GOAL_TINT
    img = cv2.resize(img.astype(np.uint8), (rgb.shape[1] * scale, rgb.shape[0] * scale),
                     interpolation=cv2.INTER_NEAREST)
    if particles is not None and len(particles):
        uv, _ = camera.world_to_pixel(np.asarray(particles, np.float64))
        for u, v in np.asarray(uv) * scale:
            cv2.circle(img, (int(u), int(v)), max(2, scale), (220, 30, 30), -1)
    if push is not None:
        push = np.asarray(push, np.float64)
        ends = np.array([[*push[:2], 0.0], [*push[2:4], 0.0]])
        (u0, v0), (u1, v1) = np.asarray(camera.world_to_pixel(ends)[0]) * scale
        cv2.arrowedLine(img, (int(u0), int(v0)), (int(u1), int(v1)), PUSH_COLOUR, max(2, scale), tipLength=0.15)
    if label:
        cv2.putText(img, label.replace("ω", "w"), (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (20, 20, 20), 1, cv2.LINE_AA)
    return img


def tint(rgb, goal_masks, tints=GOAL_TINTS) -> np.ndarray:
    """rgb [H, W, 3] with goal_masks[k] [H, W] tinted by tints[k] (Sort: kind 0's goal blue, kind 1's orange)."""
    img = np.asarray(rgb, np.float32)
    for mask, colour in zip(goal_masks, tints, strict=False):
        img[mask] = 0.6 * img[mask] + 0.4 * colour
    return img.astype(np.uint8)


class Frames:
    """GIF frames of episode 0, as an ``on_step`` callback of ``control.mpc.run``: ``draw(rgb [H, W, 3], particles
    [n, 3] m or None, record) -> frame`` draws each step's frame before its push with the particles the planner saw
    and the step's record (its push: ``record["action"]``), and ``finish(states)`` the final one (particles None, the
    last step's record, whose d and inside share are the final state's)."""

    def __init__(self, draw: Callable):
        self.draw, self.frames, self.last = draw, [], None

    def __call__(self, t: int, states, particles, record: dict) -> None:
        seen = np.asarray(particles.positions[0])[np.asarray(particles.mask[0])]
        self.frames.append(self.draw(np.asarray(states.obs.rgb[0]), seen, record))
        self.last = record

    def finish(self, states) -> list[np.ndarray]:
        """Add the final frame; returns every frame."""
        self.frames.append(self.draw(np.asarray(states.obs.rgb[0]), None, self.last))
        return self.frames


def caption(particles, record) -> str:
    """A frame's caption: the step and its ω before a push; d and the share inside after the last."""
    if record is None:
        return ""
    if particles is None:
        return f"end  d = {float(record['distance'][0]):.2f}  inside {float(record['inside'][0]):.0%}"
    return f"step {record['step'] + 1}  ω = {int(record['omega'][0])}"


def _push(particles, record):
    """The push a step frame draws (record's action of episode 0), none on the final frame nor on a step whose
    episode held (the stop rule: a NaN action)."""
    if particles is None or record is None or not np.all(np.isfinite(np.asarray(record["action"])[0])):
        return None
    return np.asarray(record["action"])[0]


def goal_frames(goal_mask: np.ndarray, camera) -> Frames:
    """Frames of a task with one goal (Gather, Redistribute): the goal tinted green, the particles red, the push
    blue, the step and its ω as the caption (the final frame: d and the share inside)."""
    def draw(rgb, particles, record):
        return overlay(rgb, goal_mask, particles, camera, label=caption(particles, record),
                       push=_push(particles, record))

    return Frames(draw)


def sort_frames(goal_masks, target_mask: Callable[[], np.ndarray], camera) -> Frames:
    """Frames of Sort: kind 0's goal blue, kind 1's orange (``tint``), the current waypoint disc ``target_mask()``
    green (none on the final frame), the particles red, the push blue, captions as ``goal_frames``'."""
    def draw(rgb, particles, record):
        target = np.zeros_like(goal_masks[0]) if particles is None else target_mask()
        return overlay(tint(rgb, goal_masks), target, particles, camera, label=caption(particles, record),
                       push=_push(particles, record))

    return Frames(draw)


def evaluation_plots(results: dict, task: str, out_dir: str, names: dict[str, str]) -> None:
    """An evaluation's ``score.png`` (per method, the share of episodes with final d below τ, against τ) and
    ``steps.png`` (mean d over the MPC steps) in out_dir. results: {method: {final_distance [E], mean_distance [T]}};
    names: each method's name in the legends."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    finals = np.concatenate([r["final_distance"] for r in results.values()])  # d >= 0
    taus = np.linspace(0.0, 1.02 * finals.max(), 200)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for method, r in results.items():
        d = np.array(r["final_distance"])
        ax.plot(taus, [(d < t).mean() for t in taus], label=names[method], lw=2.5 if method == "adaptive" else 1.2,
                ls="--" if method == "cnn" else "-")
    ax.set(xlabel="threshold τ on final d (pixels)", ylabel="task score (share of episodes with d < τ)",
           title=f"{task}, {len(d)} episodes")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "score.png"), dpi=120)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for method, r in results.items():
        ax.plot(np.arange(1, len(r["mean_distance"]) + 1), r["mean_distance"], label=names[method])
    ax.set(xlabel="MPC step", ylabel="mean d", title=task)
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))  # whole steps, not 1.25
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "steps.png"), dpi=120)
    plt.close(fig)
