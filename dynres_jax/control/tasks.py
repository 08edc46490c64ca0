"""Tasks (paper Sec. V): the goals of Gather and Redistribute, sized to the pile so it can fill them, and the registry
every command, study and script reads a task from.

Gather: push the pile into a disc of random centre and radius. Redistribute: push it into a letter (the paper's J,
T, U, or any character OpenCV draws). Both goals cover 1.3-1.8 times the area of the pieces' footprints, so the
pile fills them loosely, and stay inside the bin. An episode succeeds when ``SUCCESS`` of the pieces end inside the
goal. Sort (two kinds to their own regions, with the paper's A* blob planner) is in ``dynres_jax.control.sort``.

A new single-kind task is one ``Task`` (its goal sampler, its pile's layout, a line for ``--help``) added to ``TASKS``:
the task commands (``commands/task.py``), ``evaluate``, the studies and the scripts take it from there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.config import SceneConfig
from dynres_jax.control.goals import disc_goal, text_goal
from dynres_jax.control.mpc import fold
from dynres_jax.errors import InputError
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.scene import footprint

FILL = (1.3, 1.8)  # goal area / the pieces' footprint area
GOAL_MARGIN = 0.03  # m: a Gather disc stays this far inside the bin's walls
SUCCESS = 0.9  # an episode succeeds when this share of the pieces ends inside the goal


def largest_pile(scene: SceneConfig) -> int:
    """The most pieces of this scene's mix (at its mean footprint) whose largest goal disc (FILL[1] times their
    footprint area) still fits the bin with GOAL_MARGIN to spare; from the config alone, before any scene is built."""
    reach = scene.bin_half_width - GOAL_MARGIN
    return int(np.pi * reach**2 / FILL[1] / np.mean(np.pi * footprint(scene) ** 2))


def check_pile_fits(scene: SceneConfig) -> None:
    """InputError naming the largest piece count that fits when the scene's pile is too large for its goals."""
    if sum(scene.pieces) > largest_pile(scene):
        raise InputError(f"{sum(scene.pieces)} {'/'.join(scene.kinds)} pieces need a goal disc wider than the bin "
                         f"allows (half width {scene.bin_half_width} m, {GOAL_MARGIN} m margin): at most "
                         f"{largest_pile(scene)} fit")


def _target_area(rng: np.random.Generator, env: PileEnv) -> float:
    return float(np.sum(np.pi * env.scene.footprint**2)) * rng.uniform(*FILL)


def gather_goal(rng: np.random.Generator, env: PileEnv) -> tuple[np.ndarray, dict]:
    """A random disc holding the pile: (mask [H, W] bool, description). ValueError (``check_pile_fits``) for a pile
    too large for the bin."""
    check_pile_fits(env.config.scene)
    radius = float(np.sqrt(_target_area(rng, env) / np.pi))
    lim = env.config.scene.bin_half_width - radius - GOAL_MARGIN
    centre = rng.uniform(-lim, lim, size=2)
    return disc_goal(env.camera, centre, radius), dict(shape="disc", centre=centre.tolist(), radius=radius)


def disc_and_letter(rng: np.random.Generator, env: PileEnv, letter: str) -> tuple[np.ndarray, np.ndarray, dict]:
    """The paper's Fig. 4 goal pair: a disc and ``letter`` of the same centre (near the bin centre) and area (the
    target area): (disc mask, letter mask [H, W] bool, description)."""
    area = _target_area(rng, env)
    centre = rng.uniform(-0.03, 0.03, size=2)
    radius = float(np.sqrt(area / np.pi))
    letter_mask, info = redistribute_goal(rng, env, letter, centre, area)
    return disc_goal(env.camera, centre, radius), letter_mask, dict(info, radius=radius, area=area)


def redistribute_goal(rng: np.random.Generator, env: PileEnv, letter: str, centre=None,
                      area: float | None = None) -> tuple[np.ndarray, dict]:
    """``letter`` centred near the bin centre (or on ``centre`` [2], m), scaled so its ink covers the target area (or
    ``area``, m²): (mask [H, W] bool, description)."""
    target = _target_area(rng, env) if area is None else float(area)
    centre = rng.uniform(-0.03, 0.03, size=2) if centre is None else np.asarray(centre, np.float64)
    pixel_area = (2 * env.config.camera.view_half_width / env.camera.width) ** 2
    height = 0.12
    for _ in range(3):  # a stroke's area grows with the square of the height (stroke width is height / 5)
        mask = text_goal(env.camera, letter, centre, height)
        height *= np.sqrt(target / (mask.sum() * pixel_area))
    mask = text_goal(env.camera, letter, centre, height)
    return mask, dict(shape="text", text=letter, centre=centre.tolist(), height=float(height))


@dataclass(frozen=True)
class Task:
    """A single-kind task. description: one line for ``--help``; layout: the pile it starts from
    (``PileConfig.layout``); goal(rng, env, letter) -> (mask [H, W] bool, description dict); letter: whether the goal
    is drawn from text (the command takes ``--letter``, ``evaluate`` its ``--letters``)."""

    description: str
    layout: str
    goal: Callable[[np.random.Generator, PileEnv, str | None], tuple[np.ndarray, dict]]
    letter: bool = False


TASKS: dict[str, Task] = {
    "gather": Task("Gather (paper Sec. V): push a spread-out pile into a disc of random centre and radius.", "spread",
                   lambda rng, env, letter: gather_goal(rng, env)),
    "redistribute": Task("Redistribute (paper Sec. V): push a pile into a letter shape.", "blob",
                         redistribute_goal, letter=True),
}


def succeeded(inside) -> np.ndarray:
    """Per episode, whether its final inside share [E] reaches SUCCESS. The shares are float32 ratios of piece counts:
    90 of 100 reads 0.89999998, so the comparison allows float32's rounding (1e-6, far below one piece's share)."""
    return np.asarray(inside, np.float64) >= SUCCESS - 1e-6


def episode_goal(task: str, i: int, seed: int, env: PileEnv, letters: str = "JTU") -> np.ndarray:
    """Episode i's goal mask [H, W] from rng (seed, i): the task's goal, with the letter ``letters[i % len(letters)]``
    where it draws one."""
    return TASKS[task].goal(np.random.default_rng((seed, i)), env, letters[i % len(letters)])[0]


def episode_keys(seed: int, episodes) -> tuple[jax.Array, jax.Array]:
    """Episode i's keys, from (seed, i) alone, so the first E of a run's episodes are a run of E episodes (the `sim`
    ceiling on a subset is paired with its full run): the pile's key (``PileEnv.reset``) and the planner's. episodes
    [E] indices -> ([E] pile keys, [E] planner keys)."""
    piles = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(seed), i))(jnp.asarray(episodes))
    return piles, fold(piles, 1)
