"""Tasks (paper Sec. V): the goals of Gather, Redistribute and Sort, sized to the pile so it can fill them, the rule
that says whether an episode succeeded, and the registry every command, study and script reads a task from.

Gather: push the pile into a disc of random centre and radius. Redistribute: push it into a letter (the paper's J,
T, U, or any character OpenCV draws). Both goals cover 1.3-1.8 times the area of the pieces' footprints, so the
pile fills them loosely, and stay inside the bin. An episode succeeds when ``SUCCESS`` of the pieces end inside the
goal (``succeeded``). Sort: two kinds, each pushed into its own disc (``sort_goal``; the A* blob planner that guides
it is ``dynres_jax.control.sort``); an episode succeeds when each kind has at least ``SORT_INSIDE`` of its pieces
inside its own goal and fewer than ``SORT_MIXING`` of all pieces lie in the other kind's goal (``sort_succeeded``).
``episode_success`` applies the task's rule to an evaluation's episodes: the sort command, ``evaluate`` and the docs
read these definitions.

A new single-kind task is one ``Task`` (its goal sampler, its pile's layout, a line for ``--help``) added to ``TASKS``:
the task commands (``commands/task.py``), ``evaluate``, the studies and the scripts take it from there. Sort is the
one task of two kinds (``Task.kinds``): it has its own command (``commands/sort.py``), and ``evaluate --task sort``
plans it with ``sort.SortPolicy``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.config import SceneConfig
from dynres_jax.control.decision import fold
from dynres_jax.control.goals import check_within, disc_goal, sort_goals, text_goal
from dynres_jax.control.objective import inside_share
from dynres_jax.errors import InputError
from dynres_jax.sim.env import PileEnv
from dynres_jax.sim.scene import footprint

FILL = (1.3, 1.8)  # goal area / the pieces' footprint area
GOAL_MARGIN = 0.03  # m: a Gather disc stays this far inside the bin's walls
SUCCESS = 0.9  # an episode succeeds when this share of the pieces ends inside the goal
SORT_INSIDE, SORT_MIXING = 0.8, 0.05  # Sort succeeds: each kind >= 80 % inside its own goal, mixing below 5 %
GOAL_GAP = 0.04  # m: sort goals' rims at least this far apart (room for A*'s snapping of both centres to the grid)
GOAL_EDGE = 0.01  # m: sort goals' rims at least this far from the bin wall
SAMPLE_TRIES = 10_000  # rejection-sampling tries for the sort goals' centres


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


def _pixel_area(env: PileEnv) -> float:
    """m² of table a pixel of the env's top-down camera covers."""
    return (2 * env.config.camera.view_half_width / env.camera.width) ** 2


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


def mask_goal(env: PileEnv, mask) -> tuple[np.ndarray, dict]:
    """A goal drawn by the user: mask [H, W] bool of the env's camera (a goal PNG, ``io.frames.load_goal``) ->
    (mask, description: its area in m² and ``fill``, that area over the pieces' footprint area; the drawn goals'
    fill is ``FILL``). ValueError when a goal pixel lies outside the bin."""
    mask = np.asarray(mask, bool)
    if mask.shape != (env.camera.height, env.camera.width):
        raise ValueError(f"the goal mask is {mask.shape}, the camera's images are "
                         f"{(env.camera.height, env.camera.width)}")
    check_within(mask, env.camera, env.config.scene.bin_half_width)
    area = float(mask.sum()) * _pixel_area(env)
    return mask, dict(shape="mask", area=area, fill=area / float(np.sum(np.pi * env.scene.footprint**2)))


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
    pixel_area = _pixel_area(env)
    height = 0.12
    for _ in range(3):  # a stroke's area grows with the square of the height (stroke width is height / 5)
        mask = text_goal(env.camera, letter, centre, height)
        height *= np.sqrt(target / (mask.sum() * pixel_area))
    mask = text_goal(env.camera, letter, centre, height)
    return mask, dict(shape="text", text=letter, centre=centre.tolist(), height=float(height))


def sort_goal(rng: np.random.Generator, env: PileEnv) -> tuple[np.ndarray, float, np.ndarray]:
    """Two random disjoint goal discs of one radius, sized to the kind with the larger footprint area (``FILL``
    times it), rims ``GOAL_GAP`` apart and ``GOAL_EDGE`` from the wall: (centres [2, 2] m, radius m, masks [2, H, W]
    bool, mask k for kind k). ValueError when the pieces are too many for two such discs in the bin."""
    kinds = np.asarray(env.scene.kind)
    if kinds.max() != 1:
        raise ValueError(f"Sort needs a scene of two kinds, got kinds {env.config.scene.kinds}")
    area = max(float(np.sum(np.pi * env.scene.footprint[kinds == k] ** 2)) for k in (0, 1)) * rng.uniform(*FILL)
    radius = float(np.sqrt(area / np.pi))
    lim = env.config.scene.bin_half_width - radius - GOAL_EDGE
    need = 2 * radius + GOAL_GAP
    for _ in range(SAMPLE_TRIES if lim > 0 else 0):
        centres = rng.uniform(-lim, lim, size=(2, 2))
        if np.linalg.norm(centres[0] - centres[1]) >= need:
            return centres, radius, sort_goals(env.camera, centres, radius,
                                               bin_half_width=env.config.scene.bin_half_width)
    raise ValueError(f"two sort goals of radius {radius:.3f} m, {GOAL_GAP} m apart, hardly fit in the bin: too many "
                     f"pieces ({env.config.scene.pieces})")


def _sort_task_goal(rng: np.random.Generator, env: PileEnv, letter=None) -> tuple[np.ndarray, dict]:
    """``sort_goal`` as the registry's goal: (masks [2, H, W] bool, description with the centres and radius)."""
    centres, radius, masks = sort_goal(rng, env)
    return masks, dict(shape="discs", centres=centres.tolist(), radius=radius)


def sort_scores(piece_pos, kinds, goals, camera) -> tuple[list[float], float]:
    """piece_pos [N, 3] m, kinds [N] kind index, goals: the two ``Goal``s -> (inside: share of kind k's pieces
    inside goal k, for k = 0, 1; mixing: share of all pieces inside the other kind's goal)."""
    kinds = np.asarray(kinds)
    inside = [float(inside_share(piece_pos, kinds == k, goals[k], camera)) for k in (0, 1)]
    wrong = sum(float(inside_share(piece_pos, kinds == k, goals[1 - k], camera)) * np.sum(kinds == k) for k in (0, 1))
    return inside, wrong / len(kinds)


def sort_kinds_inside(inside) -> np.ndarray:
    """Whether both kinds' inside shares (inside [..., 2], float32 count ratios) reach SORT_INSIDE, with 1e-6 of
    rounding allowed (as ``succeeded``) -> [...] bool."""
    return np.asarray(inside, np.float64).min(axis=-1) >= SORT_INSIDE - 1e-6


def sort_mixed(mixing) -> np.ndarray:
    """Whether the mixing [...] (a float32 count ratio) reaches SORT_MIXING, with 1e-6 of rounding allowed: 3 of 60
    pieces read 0.0499999989 and are 5 % -> [...] bool."""
    return np.asarray(mixing, np.float64) >= SORT_MIXING - 1e-6


def sort_succeeded(inside, mixing) -> np.ndarray:
    """Whether Sort's episodes meet its target: both kinds' inside shares (inside [..., 2]) at least SORT_INSIDE
    (``sort_kinds_inside``) and mixing [...] below SORT_MIXING (``sort_mixed``). One episode ([2], a scalar) gives a
    bool."""
    ok = sort_kinds_inside(inside) & ~sort_mixed(mixing)
    return bool(ok) if np.ndim(ok) == 0 else ok


@dataclass(frozen=True)
class Task:
    """A task. description: one line for ``--help``; layout: the pile it starts from (``PileConfig.layout``);
    goal(rng, env, letter) -> (mask [H, W] bool, description dict; Sort: masks [2, H, W], one per kind); letter:
    whether the goal is drawn from text (the command takes ``--letter``, ``evaluate`` its ``--letters``); kinds: the
    piece kinds of its scene (1; Sort's 2: each kind to its own goal, planned by ``sort.SortPolicy``); mpc_steps: the
    pushes an episode may take (the commands' and ``evaluate``'s default): the paper's 20 for Gather; 90 for
    Redistribute, whose letters 20 pushes leave unfinished; 50 for Sort; stop_share: the default stop rule
    (``MPCConfig.stop_share``; None: every step pushes; Sort 0.9: as many successes, fewer pushes); objective: the
    form of c's SDF term (``goals.with_objective``: "paper", or "hinge" for Redistribute: only pieces outside the goal
    cost); kind_objectives: (kind, objective) pairs for the kinds that plan on another (``objective_for``): M&M, which
    roll, on the hinge (Gather; Sort against M&M's own disc). Chosen on tuning seeds, measured once on fresh ones:
    Redistribute 69 % -> 77 % on unseen characters with the hinge and 90 steps (docs/redistribute), Sort 78 % -> 84 %
    against 30 steps (docs/sort), Gather M&M 81 % -> 91 % with the hinge (the other kinds kept the paper's c: one
    success fewer on coffee and rice; docs/redistribute), Sort almond + M&M 75 % -> 91 % with the hinge on M&M's disc
    (32 paired; docs/sort)."""

    description: str
    layout: str
    goal: Callable[[np.random.Generator, PileEnv, str | None], tuple[np.ndarray, dict]]
    letter: bool = False
    kinds: int = 1
    mpc_steps: int = 20
    stop_share: float | None = None
    objective: str = "paper"
    kind_objectives: tuple[tuple[str, str], ...] = ()

    def objective_for(self, kind: str) -> str:
        """c's SDF term for a kind's pieces (Sort: against its own disc): the kind's own (``kind_objectives``), else
        the task's."""
        return dict(self.kind_objectives).get(kind, self.objective)


TASKS: dict[str, Task] = {
    "gather": Task("Gather (paper Sec. V): push a spread-out pile into a disc of random centre and radius.", "spread",
                   lambda rng, env, letter: gather_goal(rng, env), kind_objectives=(("mnm", "hinge"),)),
    "redistribute": Task("Redistribute (paper Sec. V): push a pile into a letter shape.", "blob",
                         redistribute_goal, letter=True, mpc_steps=90, objective="hinge"),
    "sort": Task("Sort (paper Sec. V): two piles of different kinds, each pushed into its own disc without mixing, "
                 "guided by A* over the piles' centres.", "two_blobs", _sort_task_goal, kinds=2, mpc_steps=50,
                 stop_share=0.9, kind_objectives=(("mnm", "hinge"),)),
}


def succeeded(inside) -> np.ndarray:
    """Per episode, whether its final inside share [E] reaches SUCCESS. The shares are float32 ratios of piece counts:
    90 of 100 reads 0.89999998, so the comparison allows float32's rounding (1e-6, far below one piece's share)."""
    return np.asarray(inside, np.float64) >= SUCCESS - 1e-6


def episode_success(task: str, results: dict) -> np.ndarray:
    """Per episode of an evaluation (``evaluate``'s METHOD.json: final_inside [E]; Sort's final_kind_inside [E, 2]
    and final_mixing [E]), whether it met its task's target: ``sort_succeeded`` for Sort, else ``succeeded``."""
    if TASKS[task].kinds == 2:
        return sort_succeeded(np.reshape(results["final_kind_inside"], (-1, 2)), results["final_mixing"])
    return succeeded(results["final_inside"])


def step_success(task: str, results: dict) -> np.ndarray:
    """Per MPC step and episode of an evaluation (``evaluate``'s METHOD.json: inside [T][E]; Sort's kind_inside
    [T][E][2] and mixing [T][E]), whether the episode met its task's target after that step -> [T, E] bool. An
    episode that met it at some step and not at the end is what a stop rule could have kept."""
    if TASKS[task].kinds == 2:
        return sort_succeeded(results["kind_inside"], results["mixing"])
    return succeeded(results["inside"])


PER_STEP = ("inside", "distance", "seen_inside", "kind_inside", "mixing", "omega", "adam_steps")  # [T][E] records


def first_steps(results: dict, steps: int) -> dict:
    """An evaluation's results as if its episodes had ended after their first ``steps`` MPC steps: the per-step
    records [T][E] cut to [steps][E], the finals and means per episode taken from them (the final pieces dropped)."""
    total = len(results["inside"])
    if not 1 <= steps <= total:
        raise ValueError(f"steps must be in 1..{total} (the run's MPC steps), got {steps}")
    out = {k: v for k, v in results.items() if k != "final_pieces"}
    out.update({k: np.asarray(results[k])[:steps].tolist() for k in PER_STEP if k in results})
    for key in ("inside", "distance", "kind_inside", "mixing"):
        if key in results:
            values = np.asarray(out[key])
            out[f"final_{key}"] = values[-1].tolist()
            if key != "kind_inside":
                out[f"mean_{key}"] = values.mean(0).tolist()
    return out


def stopped(results: dict, share: float) -> dict:
    """An evaluation's results (``evaluate``'s METHOD.json: inside, distance and seen_inside [T][E]; Sort's also
    kind_inside [T][E][2] and mixing [T][E]) made without the stop rule, as ``MPCConfig.stop_share = share`` would
    have left them: an episode holds from the first step t* whose frame met the rule, so its scores after every step
    from t* on are those after push t* - 1 (a run with the rule is the same run up to t* at a fixed ω: tests/test_mpc;
    with ω chosen per episode a held episode may change its batch's bucket). Returns a copy with those scores, their
    finals and their means per step so replaced, and stopped_at [E] (t*; T: never). ValueError for an episode whose
    first frame met it (its start is not recorded)."""
    seen = np.asarray(results["seen_inside"], np.float64)
    met = seen >= share
    first = np.where(met.any(axis=0), np.argmax(met, axis=0), len(seen))
    if np.any(first == 0):
        raise ValueError(f"episodes {np.flatnonzero(first == 0).tolist()} met a stop share of {share} before their "
                         "first push: their start's scores are not recorded")
    steps = np.arange(len(seen))[:, None]
    source = np.minimum(steps, first[None] - 1)  # [T, E]: the step whose scores stand
    out = dict(results, stopped_at=first.tolist())
    for key in ("inside", "distance", "kind_inside", "mixing"):
        if key in results:
            values = np.asarray(results[key])
            values = np.take_along_axis(values, source.reshape(source.shape + (1,) * (values.ndim - 2)), axis=0)
            out.update({key: values.tolist(), f"final_{key}": values[-1].tolist()})
            if key != "kind_inside":
                out[f"mean_{key}"] = values.mean(1).tolist()
    return out


def success_rule(task: str) -> str:
    """The task's success rule in words (what ``evaluate`` prints beside its success shares)."""
    if TASKS[task].kinds == 2:
        return f"each kind ≥{SORT_INSIDE:.0%} inside its goal, mixing <{SORT_MIXING:.0%}"
    return f"≥{SUCCESS:.0%} inside"


def draw_goal(task: str, i: int, seed: int, env: PileEnv, letters: str = "JTU") -> tuple[np.ndarray, dict]:
    """Episode i's goal from rng (seed, i): the task's (mask, description), with the letter
    ``letters[i % len(letters)]`` where it draws one."""
    return TASKS[task].goal(np.random.default_rng((seed, i)), env, letters[i % len(letters)])


def episode_goal(task: str, i: int, seed: int, env: PileEnv, letters: str = "JTU") -> np.ndarray:
    """Episode i's goal mask [H, W] (Sort: [2, H, W]) from rng (seed, i) (``draw_goal``)."""
    return draw_goal(task, i, seed, env, letters)[0]


def episode_keys(seed: int, episodes) -> tuple[jax.Array, jax.Array]:
    """Episode i's keys, from (seed, i) alone, so the first E of a run's episodes are a run of E episodes (the `sim`
    ceiling on a subset is paired with its full run): the pile's key (``PileEnv.reset``) and the planner's. episodes
    [E] indices -> ([E] pile keys, [E] planner keys)."""
    piles = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(seed), i))(jnp.asarray(episodes))
    return piles, fold(piles, 1)
