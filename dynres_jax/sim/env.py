"""PileEnv: pure ``reset(key) -> State`` and ``push(state, action) -> State`` over one MJCF, any physics of
``sim.physics`` (the backend names one; ``make_env`` builds one of an engine of ``sim.engines``):

backend "mjx": MuJoCo XLA; ``reset`` and ``push`` are pure JAX, so ``jax.jit`` and ``jax.vmap`` over worlds work.
backend "warp": MuJoCo Warp through MJX (``sim.physics.warp``): the C engine's algorithms on the GPU, jit and vmap as
"mjx". backend "mujoco": the C engine, one world, fast on CPU; same MJCF, same State, same plate trajectory.

An action is ``(x_start, y_start, x_end, y_end)`` in metres: the plate (perpendicular to the push) lowers at the
start, moves to the end at ``PushConfig.speed``, lifts, and is parked out of view while the pile settles. Pushes end
within ``action_bound`` and start there or outside a wall, at ±``reach`` (``sim.pushes``: the action space).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from dynres_jax.config import SimConfig
from dynres_jax.sim import engines, pushes
from dynres_jax.sim.camera import Camera, Observation, Renderer
from dynres_jax.sim.scene import build_scene

PARK = (0.0, 0.0, 3.0)  # plate parking spot, above the camera (out of view, touches nothing)
SINK_LIMIT = 0.005  # a piece whose centre is this far below its rest height went through the table
ESCAPE_MARGIN = 0.02  # a piece this far outside the bin's walls escaped


class State(NamedTuple):
    """One world. qpos [nq], qvel [nv]: MuJoCo state; pos [N, 3], mat [N, 3, 3]: piece geom poses (world, metres);
    obs: the top-down Observation (None when the env renders nothing); broken []: True once a step produced NaN,
    a piece went through the table, or a piece left the bin, or the engine ran out of capacity. Sticky: it stays
    True. overflow [] (int32; a physics with capacities, "warp", else None): the bits it ran out of, sticky."""

    qpos: jax.Array
    qvel: jax.Array
    pos: jax.Array
    mat: jax.Array
    obs: Observation | None
    broken: jax.Array
    overflow: jax.Array | None = None


def _yaw_quat(yaw):
    return jnp.stack([jnp.cos(yaw / 2), jnp.zeros_like(yaw), jnp.zeros_like(yaw), jnp.sin(yaw / 2)], -1)


class PileEnv:
    """Object piles pushed by a flat plate. ``PileEnv(SimConfig(), backend="mjx" | "warp" | "mujoco", render=True)``.
    worlds (backend "warp"): how many worlds a batch (``jax.vmap``) steps at once; capacities are sized for it.
    physics: the ``sim.physics`` object that steps it.

    contact_jacobian (MJX only): "sparse" steps with ``sim.physics.mjx_step.step`` (contact Jacobians built on the
    few dofs a contact can move; MJX's results to float rounding; it reaches into MJX's internals, so it runs only
    on the tested MuJoCo version), "dense" with the public ``mujoco.mjx.step``; "auto" (default): sparse for
    frictionless contacts (``SceneConfig.fast``, where it makes a step about a third faster), dense otherwise (the
    default scene, where it bought 6 %: docs/performance.md).
    """

    def __init__(self, config: SimConfig | None = None, backend: str = "mjx", render: bool = True,
                 contact_jacobian: str = "auto", worlds: int = 1):
        physics = engines.physics_named(backend)
        if contact_jacobian not in ("auto", "sparse", "dense"):
            raise ValueError(f"contact_jacobian must be 'auto', 'sparse' or 'dense', got {contact_jacobian!r}")
        if contact_jacobian == "auto":
            contact_jacobian = "sparse" if (config or SimConfig()).scene.condim == 1 else "dense"
        self.config = config = config or SimConfig()
        self.backend = backend
        self.scene = build_scene(config.scene)
        self.camera = Camera.top_down(config.camera)
        self.renderer = Renderer(self.scene, self.camera) if render else None
        dt, p = config.scene.timestep, config.push
        self.n_lower = max(1, round(p.lower_time / dt))
        self.n_move = max(1, math.ceil(p.max_length / p.speed / dt))
        self.n_lift = max(1, round(p.lift_time / dt))
        self.n_settle = max(1, round(p.settle_time / dt))
        self.n_reset = max(1, round(config.pile.settle_time / dt))
        sc = config.scene
        self.plate_z = p.clearance + (sc.plate_thickness / 2 if sc.plate_geom == "capsule" else sc.plate_half_height)
        # Pushes end this far inside the walls, so the plate never squeezes a piece against a wall; they may start
        # at ±reach, the plate wholly outside a wall (it passes through walls), to sweep pieces off the walls.
        self.action_bound = sc.bin_half_width - sc.plate_thickness / 2 - 2 * float(self.scene.footprint.max())
        self.reach = pushes.wall_reach(sc.bin_half_width, sc.plate_thickness)
        pushes.check_reach(self.action_bound, self.reach, p.min_length, p.max_length)
        self._sites = self._layout_sites()
        self._layout = jax.jit(self._initial_qpos)
        self.physics = physics(self.scene, worlds, contact_jacobian)
        if physics.traced:
            self._simulate = jax.jit(self._simulate_traced)
        else:
            self._simulate, self._finish_jit = self._simulate_host, jax.jit(self._finish)

    @property
    def steps_per_push(self) -> int:
        return self.n_lower + self.n_move + self.n_lift + self.n_settle

    # ----------------------------------------------------------------------------------------------------------
    # Initial piles
    # ----------------------------------------------------------------------------------------------------------
    def _layout_sites(self) -> np.ndarray:
        """[S, 2] grid of candidate piece centres, spaced so pieces on distinct sites never overlap."""
        foot = float(self.scene.footprint.max())
        self._spacing = 2 * foot * 1.08
        edge = self.config.scene.bin_half_width - foot - 0.002
        ticks = np.arange(-edge, edge + 1e-9, self._spacing)
        sites = np.stack(np.meshgrid(ticks, ticks), -1).reshape(-1, 2)
        n = self.scene.n_pieces
        if len(sites) < n:
            raise ValueError(f"{n} pieces do not fit in a bin of half-width {self.config.scene.bin_half_width} m "
                             f"(room for {len(sites)}); use fewer pieces or a larger bin")
        return sites

    def _initial_qpos(self, key):
        """Pieces on distinct grid sites chosen by the pile layout, jittered, with random yaw -> qpos [nq]."""
        cfg, scene, sites = self.config, self.scene, jnp.asarray(self._sites)
        k_centre, k_rough, k_jit, k_yaw = jax.random.split(key, 4)
        lim = cfg.scene.bin_half_width - cfg.pile.centre_margin
        centres = jax.random.uniform(k_centre, (2, 2), minval=-lim, maxval=lim)
        dist = jnp.linalg.norm(sites[None] - centres[:, None], axis=-1)  # [2, S]
        rough = cfg.pile.jitter * self._spacing * jax.random.uniform(k_rough, (len(cfg.scene.kinds), len(sites)))
        taken = jnp.zeros(len(sites), bool)
        chosen = []
        for i, n in enumerate(cfg.scene.pieces):
            if cfg.pile.layout == "spread":
                score = jax.random.uniform(jax.random.fold_in(k_rough, i), (len(sites),))
            elif cfg.pile.layout == "blob":
                score = dist[0] + rough[i]
            elif len(cfg.scene.kinds) > 1:
                score = dist[i % 2] + rough[i]
            else:
                score = dist.min(0) + rough[i]
            _, idx = jax.lax.top_k(-jnp.where(taken, jnp.inf, score), n)
            taken = taken.at[idx].set(True)
            chosen.append(idx)
        xy = sites[jnp.concatenate(chosen)]
        room = jnp.asarray(self._spacing / 2 - scene.footprint * 1.02)
        xy = xy + jax.random.uniform(k_jit, xy.shape, minval=-1, maxval=1) * room[:, None]
        yaw = jax.random.uniform(k_yaw, (scene.n_pieces,), minval=-jnp.pi, maxval=jnp.pi)
        return self._qpos_from(xy, yaw)

    def _qpos_from(self, xy, yaw):
        """Piece centres xy [N, 2] (metres) and yaw [N] (radians), lying at rest on the table -> qpos [nq]."""
        scene = self.scene
        adr = scene.qpos_adr
        qpos = jnp.asarray(scene.model.qpos0, jnp.float32)
        if self.config.scene.joints == "planar":
            yawed = scene.has_yaw
            return qpos.at[adr].set(xy[:, 0]).at[adr + 1].set(xy[:, 1]).at[adr[yawed] + 2].set(yaw[yawed])
        z = jnp.asarray(scene.rest_height) + 0.0005
        qpos = qpos.at[adr].set(xy[:, 0]).at[adr + 1].set(xy[:, 1]).at[adr + 2].set(z)
        quat = _yaw_quat(yaw)
        for j in range(4):
            qpos = qpos.at[adr + 3 + j].set(quat[:, j])
        return qpos

    # ----------------------------------------------------------------------------------------------------------
    # Plate trajectory, shared by both backends
    # ----------------------------------------------------------------------------------------------------------
    def plate_trajectory(self, action):
        """action [4] -> plate (pos [K, 3], quat [K, 4]) for each of the K = steps_per_push simulator steps."""
        p, dt = self.config.push, self.config.scene.timestep
        start, end = action[:2], action[2:]
        delta = end - start
        length = jnp.linalg.norm(delta)
        direction = delta / jnp.maximum(length, 1e-9)
        z_up = self.plate_z + p.lift_height
        k_low = (jnp.arange(self.n_lower) + 1) / self.n_lower
        k_lift = (jnp.arange(self.n_lift) + 1) / self.n_lift
        travel = jnp.minimum((jnp.arange(self.n_move) + 1) * p.speed * dt, length)
        xy = jnp.concatenate([jnp.broadcast_to(start, (self.n_lower, 2)), start + travel[:, None] * direction,
                              jnp.broadcast_to(end, (self.n_lift, 2))])
        z = jnp.concatenate([z_up + (self.plate_z - z_up) * k_low, jnp.full(self.n_move, self.plate_z),
                             self.plate_z + (z_up - self.plate_z) * k_lift])
        pos = jnp.concatenate([xy, z[:, None]], axis=1)
        pos = jnp.concatenate([pos, jnp.broadcast_to(jnp.asarray(PARK), (self.n_settle, 3))])
        quat = jnp.broadcast_to(_yaw_quat(jnp.arctan2(direction[1], direction[0])), (self.steps_per_push, 4))
        return pos.astype(jnp.float32), quat.astype(jnp.float32)

    def sample_push(self, key, pos):
        """A random push through the pile (``pushes.sample_actions``): it passes a random piece of ``pos`` [N, 3] at
        a random angle, or, a share ``pushes.WALL_SHARE`` of the time, comes in from outside the wall nearest to a
        piece near a wall; length at least 3 cm. Returns action [4]; pure JAX (vmap it over worlds)."""
        p = self.config.push
        k_piece, k_wall, k_push = jax.random.split(key, 3)
        valid = jnp.ones(pos.shape[0], bool)
        target = pushes.pile_points(k_piece, pos, valid, (1, 1))
        wall = pushes.pile_points(k_wall, pos, valid, (1, 1), self.reach)
        return pushes.sample_actions(k_push, 1, 1, self.action_bound, max(p.min_length, 0.03), p.max_length, target,
                                     0.0, self.reach, wall)[0, 0]

    def _parked(self, n):
        return (jnp.broadcast_to(jnp.asarray(PARK, jnp.float32), (n, 3)),
                jnp.broadcast_to(jnp.array([1.0, 0, 0, 0], jnp.float32), (n, 4)))

    # ----------------------------------------------------------------------------------------------------------
    # Actions
    # ----------------------------------------------------------------------------------------------------------
    def check_action(self, action) -> np.ndarray:
        """Raise ValueError naming the problem with a concrete action; returns it as float32 [4]."""
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (4,):
            raise ValueError(f"an action is (x_start, y_start, x_end, y_end), shape (4,); got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action has NaN or infinite entries: {a}")
        b, r, p = self.action_bound, self.reach, self.config.push
        if np.any(np.abs(a[2:]) > b + 1e-6):
            raise ValueError(f"action {a} ends outside the workspace: the end's coordinates must lie within "
                             f"+-{b:.4f} m (the bin less the plate and two piece widths, PileEnv.action_bound)")
        start = np.abs(a[:2])
        if np.any((start > b + 1e-6) & (np.abs(start - r) > 1e-6)):
            raise ValueError(f"action {a} starts between the workspace and the walls: a start coordinate lies within "
                             f"+-{b:.4f} m (PileEnv.action_bound) or at +-{r:.4f} m, outside a wall (PileEnv.reach)")
        length = float(np.hypot(a[2] - a[0], a[3] - a[1]))
        if not p.min_length - 1e-6 <= length <= p.max_length + 1e-6:  # float32 plans sit on the bounds
            raise ValueError(f"push length {length:.4f} m is outside [{p.min_length}, {p.max_length}] m "
                             "(PushConfig.min_length / max_length)")
        return a.astype(np.float32)

    def _sanitise(self, action):
        """Traced actions cannot raise: NaN makes the push a no-op and flags the world broken; the rest is
        ``pushes.project``ed into the action space."""
        bad = ~jnp.all(jnp.isfinite(action))
        p = self.config.push
        a = jnp.where(bad, jnp.array([0.0, 0.0, p.min_length, 0.0]), action)
        return pushes.project(a, self.action_bound, p.min_length, p.max_length, self.reach), bad

    # ----------------------------------------------------------------------------------------------------------
    # Public API
    # ----------------------------------------------------------------------------------------------------------
    def reset(self, key) -> State:
        """A new settled pile drawn from ``key``."""
        zero = jnp.zeros(self.scene.model.nv, jnp.float32)
        return self.simulate(State(self._layout(key), zero, None, None, None, jnp.array(False)),
                             *self._parked(self.n_reset))

    def place(self, xy, yaw=None) -> State:
        """A settled world with pieces placed by hand: xy [N, 2] centres (metres), yaw [N] (radians, default 0)."""
        xy = jnp.asarray(xy, jnp.float32)
        if xy.shape != (self.scene.n_pieces, 2):
            raise ValueError(f"place needs xy of shape ({self.scene.n_pieces}, 2), got {xy.shape}")
        yaw = jnp.zeros(len(xy)) if yaw is None else jnp.asarray(yaw, jnp.float32)
        if not isinstance(xy, jax.core.Tracer) and not (np.all(np.isfinite(xy)) and np.all(np.isfinite(yaw))):
            raise ValueError("place needs finite xy and yaw (MuJoCo resets a world with NaN to its default pose)")
        if not isinstance(xy, jax.core.Tracer) and (far := float(np.abs(np.asarray(xy)).max())) > (
                wall := self.config.scene.bin_half_width):
            raise ValueError(f"place: a piece centre lies {far:g} m from the bin's centre in x or y, outside the bin "
                             f"(±{wall:g} m)")
        zero = jnp.zeros(self.scene.model.nv, jnp.float32)
        settled = State(self._qpos_from(xy, yaw), zero, None, None, None, jnp.array(False))
        return self.simulate(settled, *self._parked(self.n_reset))

    def push(self, state: State, action) -> State:
        """Execute one push. Concrete actions are checked (ValueError naming the problem); traced ones (inside
        jit / vmap) are sanitised and a NaN action flags the world broken."""
        if isinstance(action, jax.core.Tracer):
            action, bad = self._sanitise(action)
            state = state._replace(broken=state.broken | bad)
        else:
            action = jnp.asarray(self.check_action(action))
        return self._simulate(state, *self.plate_trajectory(action))

    def simulate(self, state: State, plate_pos, plate_quat) -> State:
        """Step the world along any plate trajectory: plate_pos [K, 3], plate_quat [K, 4], one row per step."""
        return self._simulate(state, plate_pos, plate_quat)

    def observe(self, state: State, plate=None) -> Observation:
        """Render a state's pieces, and the plate if given as (centre [3], quat [4])."""
        if self.renderer is None:
            raise ValueError("this PileEnv was built with render=False")
        if plate is not None:
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, np.asarray(plate[1], np.float64))
            cfg = self.config.scene
            plate = (jnp.asarray(plate[0], jnp.float32), jnp.asarray(rot.reshape(3, 3), jnp.float32),
                     jnp.array([cfg.plate_thickness / 2, cfg.plate_half_width, self.plate_z - cfg.plate_thickness / 2]))
        return self._render_jit(state.pos, state.mat, plate)

    @functools.cached_property
    def _render_jit(self):
        return jax.jit(self.renderer.__call__)

    def _finish(self, qpos, qvel, pos, mat, broken) -> State:
        """Piece poses -> State with observation and the broken flag."""
        b = self.config.scene.bin_half_width + ESCAPE_MARGIN
        sunk = jnp.any(pos[:, 2] < jnp.asarray(self.scene.rest_height) - SINK_LIMIT)
        escaped = jnp.any(jnp.abs(pos[:, :2]) > b)
        nan = ~(jnp.all(jnp.isfinite(qpos)) & jnp.all(jnp.isfinite(qvel)))
        obs = self.renderer(pos, mat) if self.renderer is not None else None
        return State(qpos, qvel, pos, mat, obs, broken | sunk | escaped | nan)

    def _simulate_traced(self, state: State, plate_pos, plate_quat) -> State:
        poses = self.physics.run(state.qpos, state.qvel, plate_pos, plate_quat)
        out = self._finish(*poses[:4], state.broken)
        if poses.overflow is None:
            return out
        flags = poses.overflow | (0 if state.overflow is None else state.overflow)
        return out._replace(broken=out.broken | (flags != 0), overflow=flags)

    def _simulate_host(self, state: State, plate_pos, plate_quat) -> State:
        return self._finish_jit(*self.physics.run(state.qpos, state.qvel, plate_pos, plate_quat)[:4], state.broken)

    @property
    def draws_pushes(self) -> bool:
        """Whether ``push_frames`` can draw a push as it moves (the C engine; MJX pushes run as one compiled scan)."""
        return hasattr(self.physics, "run_drawn")

    def push_frames(self, state: State, action, n_frames: int = 12) -> tuple[State, list[Observation]]:
        """Like ``push`` (``draws_pushes`` only) but also renders ``n_frames`` frames with the plate drawn."""
        if not self.draws_pushes:
            raise ValueError("push_frames needs backend='mujoco' (MJX pushes run as one compiled scan)")
        action = jnp.asarray(self.check_action(action))
        every = max(1, (self.steps_per_push - self.n_settle) // n_frames)
        poses, frames = self.physics.run_drawn(state.qpos, state.qvel, *self.plate_trajectory(action),
                                               frames_at=range(0, self.steps_per_push, every))
        frames = [self.observe(State(None, None, jnp.asarray(p, jnp.float32), jnp.asarray(r, jnp.float32), None,
                                     None), plate=(pp, pq) if pp[2] < PARK[2] else None)
                  for p, r, pp, pq in frames]
        return self._finish_jit(*poses[:4], state.broken), frames


def make_env(config: SimConfig, name: str, **kwargs) -> PileEnv:
    """One ``PileEnv`` of ``config`` in the engine ``name`` (``sim.engines``; kwargs: PileEnv's, e.g. render,
    worlds)."""
    return PileEnv(engines.sim_config(config, name), backend=engines.physics(name), **kwargs)

