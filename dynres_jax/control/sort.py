"""Sort (paper Sec. V and Appendix "High-Level Planner for Sort Task"): two piles of different kinds, each pushed to
its own disc without mixing, guided by an A* planner over blob centres.

Paper mapping:
- Each pile is a blob: a circle of fixed radius (``blob_radius``, m) around its centre. A node of the search is the
  pair of blob centres, each on a sparse grid (spacing ``grid_step``, m, on the table plane; the paper's grid is in
  image space, ours in metres, which for the top-down camera is the same up to scale).
- Neighbours move ONE blob ONE grid step, 8-connected (diagonals included), with no collision: the two circles may
  not overlap (centre distance >= 2 ``blob_radius``) and centres stay within ±``bound``. Every step costs 1, so the
  fewest-steps path is preferred (the paper's constant cost per step); among those, the one that switches the moved
  blob least (ours: each blob then moves in long runs, so the waypoint ``lookahead`` steps ahead lies further than one
  grid step from a pile's centre, a target one push can reach).
- Heuristic: the sum over blobs of the Chebyshev grid distance to its goal. With 8-connected unit-cost moves this is
  the exact cost when the blobs do not interfere, hence admissible and consistent (the Euclidean grid distance is
  not admissible here: a diagonal step covers √2 grid units at cost 1).
- Perceived piles can start closer than 2 ``blob_radius`` (touching or mixed piles); such a start may only be left
  by moves that strictly increase the centre distance until the circles are apart. Goals must not overlap.
- A pile has arrived when at least ``ARRIVED`` of its particles lie inside its goal disc (ours): A* starts it at its
  goal. Without this a pile already inside its goal, whose centre sat a centimetre off (pieces fill a disc unevenly),
  was pushed for the rest of the episode while the other pile waited (19 of 30 failures on seeds 30000, docs/sort).
  ``ARRIVED`` is Sort's success share (``tasks.SORT_INSIDE``, 80 %): at 90 % a pile 80-89 % inside, already counted
  a success, kept being pushed while the other waited (9 of 13 failures on fresh seeds, docs/sort).

Closed loop (``SortPolicy``, a chooser on the one MPC loop, ``mpc.run``): each MPC step perceives both
piles (particles of one kind each, segmentation), takes the blob centres as the particle centroids, RE-PLANS the A* path
from them (so a pile disturbed by a push is handled), and plans one push on the particles of the whole scene, each
labelled with its kind (``perception.particle_kinds``), with one goal per kind (``goals.KindGoals``): the blob of
the path's first move is pursued toward a disc of ``goal_radius`` at its waypoint, up to ``lookahead`` grid steps ahead
along its current run of moves; the other blob is held: only a loss against the disc where it rests (its goal when the
path does not move it again) counts (``objective.kind_objective``), so a push through the resting pile costs what it
scatters and the resting pile never draws the push. When both piles are at their goals (centres snapping to them, or
arrived), both kinds are pursued into their own goal discs; when A* finds no path (no room to pass), the pile farther
from its goal is pursued straight to it and the other held at its goal. Each kind's c also counts, weighted by
``MIXING``, how deep its particles lie inside the other kind's true goal (``objective.kind_costs``): without it, 37 of
63 failures on fresh seeds ended with both kinds inside but 5 % or more of the pieces in the wrong goal; with it, 2 of
44 (docs/sort). The paper's reference code has no Sort; these choices are ours. ``SortEpisodes`` runs one policy per
episode of a batch (``evaluate --task sort``).
"""

from __future__ import annotations

import heapq
import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.config import check_omega
from dynres_jax.control.budget import bucket_for
from dynres_jax.control.choosers import Candidate, Chooser, Orders
from dynres_jax.control.decision import batch, episode
from dynres_jax.control.goals import check_objective, disc_goal, make_goal, sort_goals, stack_goals, with_objective
from dynres_jax.control.keep import scorer
from dynres_jax.control.mpc import MPCConfig
from dynres_jax.control.tasks import SORT_INSIDE, sort_scores
from dynres_jax.perception import check_particles, cloud_particles, foreground, pack
from dynres_jax.sim.env import PileEnv

WAYPOINT_EDGE = 0.005  # m: A*'s bound keeps waypoint discs of goal_radius this far inside the bin
MOVES = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0)]  # 8-connected grid steps
ARRIVED = SORT_INSIDE  # share of a pile's particles inside its goal disc at which it counts as there: success's
MIXING = 10.0  # weight of a kind's depth inside the other kind's goal in its c (chosen on tuning seeds, docs/sort)


def astar_blobs(starts, goals, blob_radius: float, grid_step: float, bound) -> list[np.ndarray]:
    """A* over pairs of blob centres. starts, goals [2, 2] (m, row b = blob b's (x, y)); blob_radius, grid_step (m);
    bound: m, centres stay within ±bound (a scalar, or (x, y) half-widths of a rectangle). Starts are snapped to the
    nearest grid point inside the bound, goals to the nearest grid point. Returns the path as a list of [2, 2]
    centre pairs (m) from the snapped start to the snapped goals, consecutive pairs differing in one blob by one
    grid step (a one-element list when the start snaps to the goals): of the fewest steps, and of those the fewest
    switches of the moved blob. ValueError for bad arguments, goals outside
    the bound or overlapping, and when no collision-free path exists."""
    starts, goals = np.asarray(starts, np.float64), np.asarray(goals, np.float64)
    if starts.shape != (2, 2) or goals.shape != (2, 2):
        raise ValueError(f"starts and goals must be [2, 2] (one (x, y) per blob), got {starts.shape}, {goals.shape}")
    if not (np.all(np.isfinite(starts)) and np.all(np.isfinite(goals))):
        raise ValueError("starts and goals must be finite")
    if not (blob_radius > 0 and grid_step > 0):
        raise ValueError(f"blob_radius and grid_step must be positive, got {blob_radius}, {grid_step}")
    half = np.broadcast_to(np.asarray(bound, np.float64), (2,))
    if np.any(half < 0):
        raise ValueError(f"bound must be non-negative, got {bound}")
    if np.any(np.abs(goals) > half + 1e-9):
        raise ValueError(f"goals {goals.tolist()} lie outside the bound ±{half.tolist()} m")
    n = np.floor(half / grid_step + 1e-9).astype(int)  # grid indices -n..n per axis
    start = tuple(int(i) for i in np.clip(np.rint(starts / grid_step), -n, n).astype(int).ravel())
    goal = tuple(int(i) for i in np.clip(np.rint(goals / grid_step), -n, n).astype(int).ravel())
    apart = (2 * blob_radius / grid_step) ** 2 - 1e-9  # squared centre distance (grid units) of touching circles

    def gap2(node):
        return (node[0] - node[2]) ** 2 + (node[1] - node[3]) ** 2

    if gap2(goal) < apart:
        raise ValueError(f"goals overlap: snapped to the grid their centres are {np.sqrt(gap2(goal)) * grid_step:.4f}"
                         f" m apart, blobs of radius {blob_radius} m need {2 * blob_radius} m")

    def heuristic(node):
        return sum(max(abs(node[2 * b] - goal[2 * b]), abs(node[2 * b + 1] - goal[2 * b + 1])) for b in (0, 1))

    # A search state is (node, the blob moved last: -1 at the start); its cost (steps, switches) is compared
    # lexicographically, so the fewest steps come first and switches only break ties (the heuristic counts steps).
    begin = (start, -1)
    cost, parent = {begin: (0, 0)}, {begin: None}
    frontier = [(heuristic(start), 0, 0, begin)]
    while frontier:
        _, switches, neg_g, state = heapq.heappop(frontier)
        node, last = state
        if node == goal:
            path = []
            while state is not None:
                path.append(np.asarray(state[0], np.float64).reshape(2, 2) * grid_step)
                state = parent[state]
            return path[::-1]
        if (-neg_g, switches) > cost[state]:
            continue  # a stale entry: the state was reached more cheaply since
        d2 = gap2(node)
        for b in (0, 1):
            g = (-neg_g + 1, switches + (last not in (-1, b)))
            for di, dj in MOVES:
                nxt = list(node)
                nxt[2 * b] += di
                nxt[2 * b + 1] += dj
                nxt = tuple(nxt)
                if abs(nxt[2 * b]) > n[0] or abs(nxt[2 * b + 1]) > n[1]:
                    continue
                if gap2(nxt) < apart and not (d2 < apart and gap2(nxt) > d2):  # collision, unless escaping one
                    continue
                if g < cost.get((nxt, b), (np.inf, np.inf)):
                    cost[(nxt, b)], parent[(nxt, b)] = g, state
                    heapq.heappush(frontier, (g[0] + heuristic(nxt), g[1], -g[0], (nxt, b)))  # ties: deeper first
    raise ValueError(f"no collision-free path for blobs of radius {blob_radius} m from {starts.tolist()} to "
                     f"{goals.tolist()} within ±{half.tolist()} m on a {grid_step} m grid (too little room to pass)")


def _kind_centres(obs, camera, omega: int, max_points: int | None, buckets, key, goals_xy,
                  goal_radius: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The two piles' centres (m) [2, 2]: the mean of each kind's particles (ω = min(omega, that kind's foreground
    points), so a small pile still samples, in the smallest bucket holding ω); each kind's share of particles inside
    its goal disc [2] (goals_xy [2, 2] m, goal_radius m); and the points of the whole cloud. The foreground is
    computed once for both kinds and the whole cloud."""
    points, valid = foreground(obs, camera)
    pieces = jnp.asarray(obs.kind).reshape(-1)
    centres, inside = [], []
    for k in (0, 1):
        mine = valid & (pieces == k)
        cloud = pack(jnp.where(mine[:, None], points, 0.0), mine, max_points)
        w = max(min(omega, int(np.sum(np.asarray(cloud[1])))), 1)
        capacity = bucket_for(w, buckets)
        p = cloud_particles(*cloud, obs.depth, w, jax.random.fold_in(key, k), capacity)
        check_particles(p, w, capacity, f"Sort's kind {k}")
        xy = np.asarray(p.positions)[np.asarray(p.mask), :2]
        centres.append(xy.mean(0))
        inside.append(np.mean(np.linalg.norm(xy - goals_xy[k], axis=1) <= goal_radius))
    return np.stack(centres), np.asarray(inside), int(np.sum(np.asarray(pack(points, valid, max_points)[1])))


def _next_waypoint(path: list[np.ndarray], goals_xy: np.ndarray, lookahead: int) -> tuple[int, np.ndarray]:
    """The blob of the path's first move and its target (m): its centre after up to ``lookahead`` of its own
    consecutive moves, or its true (unsnapped) goal when it does not move again after those."""
    blob = int(np.argmax(np.any(path[1] != path[0], axis=1)))
    j = 1
    while j < lookahead and j + 1 < len(path) and not np.any(path[j + 1][1 - blob] != path[j][1 - blob]):
        j += 1
    if all(np.array_equal(p[blob], path[j][blob]) for p in path[j:]):
        return blob, goals_xy[blob]
    return blob, path[j][blob]


def _hold_point(path: list[np.ndarray] | None, goals_xy: np.ndarray, blob: int) -> np.ndarray:
    """Where the resting blob should stay (m): its true goal when the path (None: no path) does not move it again,
    else its current (snapped) centre."""
    if path is None or all(np.array_equal(p[blob], path[0][blob]) for p in path):
        return goals_xy[blob]
    return path[0][blob]


class SortPolicy(Chooser):
    """Sort's A* waypoints as a chooser on the one MPC loop (``mpc.run``), for one episode: every step it perceives
    both piles, re-plans the A* path from their centres and plans one push on both kinds' particles at once at ω
    (``goals.KindGoals``): the moved blob's kind pursued towards a disc of ``goal_radius`` at its waypoint, the
    other kind held at a disc where it rests (``_hold_point``; module docstring). ``target_mask`` is the current
    waypoint's disc (what a frame draws). Its record fields: phase ("path": following A*, "final": both at their
    goals, both pursued, "direct": A* found no path, the farther pile heads straight to its goal), kind moved (-1 in
    "final": both), waypoint [2] m (the moved kind's target centre), centres [2, 2] m (perceived), perceived_inside
    [2] (each kind's share of particles inside its goal; ``arrived`` (default ``ARRIVED``) or more: the pile starts
    A* at its goal), astar_steps left, astar_s; its scores (``sort_step_scores``): kind_inside [2] (kind k's share
    inside goal k), mixing (the share inside the other kind's goal) and goal_distance (d to the true goals).
    mixing: the weight in each kind's c of its particles' intrusion into the other kind's true goal
    (``objective.kind_costs``; default ``MIXING``; 0: none, each kind scored against its target disc alone);
    objective: the form of c's SDF term against each target disc (``goals.with_objective``), one for both or a pair,
    kind k's against its own disc."""

    def __init__(self, env: PileEnv, cfg: MPCConfig, omega: int, key, goals_xy, goal_radius: float, log=print, *,
                 blob_radius: float | None = None, grid_step: float = 0.02, lookahead: int = 3,
                 arrived: float = ARRIVED, mixing: float = MIXING, objective: str | Sequence[str] = "paper"):
        if lookahead < 1:
            raise ValueError(f"lookahead must be at least 1, got {lookahead}")
        if not 0 < arrived <= 1:
            raise ValueError(f"arrived must be a share in (0, 1], got {arrived}")
        if not (np.isfinite(mixing) and mixing >= 0):
            raise ValueError(f"mixing must be a finite weight >= 0, got {mixing}")
        objectives = (objective,) * 2 if isinstance(objective, str) else tuple(objective)
        if len(objectives) != 2:
            raise ValueError(f"objective must be one name or one per kind (2), got {objective!r}")
        self.arrived, self.mixing, self.objectives = arrived, mixing, tuple(check_objective(o) for o in objectives)
        self.omega, self.max_points, self.buckets = check_omega(omega), cfg.max_points, cfg.buckets
        self.piece_kinds, self.key, self.log = env.scene.kind, key, log
        self.camera, self.bin_half = env.camera, env.config.scene.bin_half_width
        self.goals_xy = np.asarray(goals_xy, np.float64)
        self.goal_radius, self.grid_step, self.lookahead = goal_radius, grid_step, lookahead
        self.goal_masks = sort_goals(self.camera, self.goals_xy, goal_radius, bin_half_width=self.bin_half)
        self.goals = [make_goal(m, self.camera) for m in self.goal_masks]
        self.kind_goals = stack_goals(self.goals)  # both kinds' true goals, both pursued: what d is scored against
        self.blob_radius = goal_radius if blob_radius is None else blob_radius
        self.bound = self.bin_half - goal_radius - WAYPOINT_EDGE
        self.phase, self.target_mask = None, np.zeros_like(self.goal_masks[0])

    def __call__(self, t: int, obs) -> Orders:
        obs = episode(obs)
        centres, inside, points = _kind_centres(obs, self.camera, self.omega, self.max_points, self.buckets,
                                                jax.random.fold_in(self.key, t), self.goals_xy, self.goal_radius)
        arrived = inside >= self.arrived
        t0 = time.perf_counter()
        try:
            starts = np.where(arrived[:, None], self.goals_xy, centres)  # an arrived pile starts at its goal
            path = astar_blobs(starts, self.goals_xy, self.blob_radius, self.grid_step, self.bound)
        except ValueError as error:
            path = None
            if self.phase != "direct":
                self.log(f"A*: {error}; heading straight to the goals")
        astar_s = time.perf_counter() - t0
        targets, hold = self.goals_xy.copy(), np.ones(2, bool)  # kind k's target centre (m); held kinds
        if path is None:
            self.phase, steps_left = "direct", -1
            kind = int(np.argmax(np.linalg.norm(centres - self.goals_xy, axis=1)))
        elif len(path) == 1:
            self.phase, steps_left, kind, hold[:] = "final", 0, -1, False
        else:
            self.phase, steps_left = "path", len(path) - 1
            kind, targets[kind] = _next_waypoint(path, self.goals_xy, self.lookahead)
            targets[1 - kind] = _hold_point(path, self.goals_xy, 1 - kind)
        if kind >= 0:
            hold[kind] = False
        masks = [disc_goal(self.camera, c, self.goal_radius, bin_half_width=self.bin_half) for c in targets]
        self.target_mask = masks[kind] if kind >= 0 else np.zeros_like(masks[0])
        record = dict(phase=[self.phase], kind=[kind], waypoint=[targets[max(kind, 0)]], centres=[centres],
                      perceived_inside=[inside], astar_steps=[steps_left], astar_s=[astar_s])
        goals = stack_goals([with_objective(make_goal(m, self.camera), o) for m, o in zip(masks, self.objectives,
                                                                                            strict=True)], hold,
                            self.goals, self.mixing)
        return Orders(batch(goals), (Candidate(np.array([max(min(self.omega, points), 1)])),), None, record)

    def score(self, states) -> dict:
        return sort_step_scores(states, [self], batch(self.kind_goals))


class SortEpisodes(Chooser):
    """Sort on a batch of episodes (``evaluate --task sort``): policy b (a ``SortPolicy``: its own goals, key, A*
    path and phase) decides for episode b of the frames, and their orders are joined into one batch, so each episode
    is ordered as it would be alone and all plan in one compiled decision. Record fields and scores: each policy's,
    stacked [B, ...]."""

    def __init__(self, policies: Sequence[SortPolicy]):
        if not policies:
            raise ValueError("SortEpisodes needs a policy per episode, got none")
        self.policies = list(policies)
        self.goals = jax.tree.map(lambda *x: jnp.stack(x), *[p.kind_goals for p in self.policies])  # [B, 2, ...]

    def __call__(self, t: int, obs) -> Orders:
        if len(obs.depth) != len(self.policies):
            raise ValueError(f"{len(obs.depth)} frames for {len(self.policies)} Sort episodes")
        orders = [p(t, batch(episode(obs, b))) for b, p in enumerate(self.policies)]
        goals = jax.tree.map(lambda *x: jnp.concatenate([jnp.asarray(v) for v in x]), *[o.goals for o in orders])
        omega = np.concatenate([o.candidates[0].omega for o in orders])
        record = {k: np.concatenate([np.asarray(o.record[k]) for o in orders]) for k in orders[0].record}
        return Orders(goals, (Candidate(omega),), None, record)

    def score(self, states) -> dict:
        return sort_step_scores(states, self.policies, self.goals)


def sort_step_scores(states, policies: Sequence[SortPolicy], goals) -> dict:
    """Sort's scores of states [B] on the true state, episode b scored by policies[b]'s goals (goals: theirs as
    KindGoals [B], both pursued): kind_inside [B, 2] and mixing [B] (``tasks.sort_scores``), and goal_distance [B],
    the mean over both kinds of d of a kind's foreground to its own goal (``keep.scorer``; the loop's own d scores a
    step against its waypoint discs)."""
    scores = [sort_scores(states.pos[b], p.piece_kinds, p.goals, p.camera) for b, p in enumerate(policies)]
    kinds = tuple(np.asarray(policies[0].piece_kinds).tolist())
    distance = scorer(policies[0].camera, kinds)(states, goals)["distance"]
    return dict(kind_inside=[s[0] for s in scores], mixing=[s[1] for s in scores],
                goal_distance=np.asarray(distance))
