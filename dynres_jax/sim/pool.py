"""Many worlds at once, with ``PileEnv``'s batched State: ``WorldPool`` steps C MuJoCo worlds in host worker
processes, one world per core, and renders their observations on the JAX device; ``MJXPool`` steps them as one batch
in MJX on the device, ``SizedPool`` in MuJoCo Warp on the GPU (one engine a batch size). All have ``reset(keys)``,
``push(states, actions)``, ``env``, ``camera`` and ``scene``; ``make_pool`` picks one by engine name
(``sim.engines``).

Why: with the default Newton solver, C MuJoCo on every host core outruns MJX on one GPU several times over
(docs/performance.md, "Speed"), so data generation and evaluation at scale push through this pool while perception and
planning stay batched on the accelerator. A worker is a spawned process whose JAX runs on the host (pile layouts and
push sampling are small JAX functions); it builds each scene once, from the SimConfig's JSON.
"""

from __future__ import annotations

import functools
import multiprocessing
import os
import signal
import threading
import time
from typing import Protocol

import jax
import jax.numpy as jnp
import numpy as np

from dynres_jax.chunks import in_chunks
from dynres_jax.config import CameraConfig, SceneConfig, SimConfig
from dynres_jax.sim import engines
from dynres_jax.sim.camera import Camera, Renderer
from dynres_jax.sim.env import PileEnv, State
from dynres_jax.sim.scene import build_scene


def python_scan(step, carry, xs):
    """``jax.lax.scan``'s contract as a Python loop over the leading axis of xs (concrete values: the C engine)."""
    ys = []
    for x in xs:
        carry, y = step(carry, x)
        ys.append(y)
    return carry, jax.tree.map(lambda *v: jnp.stack(v), *ys)


def random_episode(env: PileEnv, key, pushes: int, record, scan=jax.lax.scan):
    """Data generation's episode (``learn.data``): a reset and ``pushes`` random pushes through the pile
    (``PileEnv.sample_push``: always in bounds), the broken flag sticky. record: State -> the arrays kept of a frame;
    scan: ``jax.lax.scan`` where the episode is traced (MJX, vmapped over worlds), ``python_scan`` for the C engine.
    Returns (every frame's record stacked [F = pushes + 1], actions [pushes, 4] m)."""
    k_reset, k_push = jax.random.split(key)
    s0 = env.reset(k_reset)

    def step(s, k):
        action = env.sample_push(k, s.pos)
        s1 = env.simulate(s, *env.plate_trajectory(action))
        return s1._replace(obs=None), (record(s1), action)

    _, (frames, actions) = scan(step, s0._replace(obs=None), jax.random.split(k_push, pushes))
    return jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), record(s0), frames), actions


def _checked(env: PileEnv, actions) -> np.ndarray:
    """actions [B, 4] as float32, each checked like ``PileEnv.push`` (a bad one raises ValueError naming it)."""
    actions = np.asarray(actions, np.float32)
    for a in actions:
        env.check_action(a)
    return actions


def _host_only(parent: int) -> None:
    """Worker initialiser: JAX on the host (never the accelerator the parent holds), one thread per process; Ctrl-C
    is the parent's to report (it ends the pool), not every worker's; the worker ends within a second of its parent
    (process ``parent``), also mid-task when the parent was killed (``_die_with``)."""
    threading.Thread(target=_die_with, args=(parent,), daemon=True).start()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ["XLA_FLAGS"] = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
    jax.config.update("jax_platforms", "cpu")


def _die_with(parent: int) -> None:
    """A worker's watchdog: end this process once ``parent`` is no longer its parent (killed: re-parented)."""
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(1)


def process_pool(workers: int | None = None):
    """``workers`` (default: every host core) spawned processes for ``WorldPool``; use as a context manager. The
    workers start with ``JAX_PLATFORMS=cpu`` in their environment, so a module that makes a JAX array on import
    cannot open the accelerator in every worker before ``_host_only`` runs."""
    saved = {k: os.environ.get(k) for k in ("JAX_PLATFORMS", "XLA_PYTHON_CLIENT_PREALLOCATE")}
    os.environ.update(JAX_PLATFORMS="cpu", XLA_PYTHON_CLIENT_PREALLOCATE="false")
    try:
        return multiprocessing.get_context("spawn").Pool(workers or os.cpu_count(), initializer=_host_only,
                                                           initargs=(os.getpid(),))
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k)
            else:
                os.environ[k] = v


@functools.lru_cache(maxsize=2)
def _env(sim_json: str, backend: str) -> PileEnv:
    return PileEnv(SimConfig.from_json(sim_json), backend=backend, render=False)


def _arrays(s: State) -> tuple:
    return tuple(np.asarray(x) for x in (s.qpos, s.qvel, s.pos, s.mat, s.broken))


def _reset(job) -> tuple:
    sim_json, backend, key = job
    return _arrays(_env(sim_json, backend).reset(jnp.asarray(key, jnp.uint32)))


def _push(job) -> tuple:
    sim_json, backend, world, action = job
    qpos, qvel, pos, mat, broken = world
    if broken:  # a broken world stays as it was
        return world
    env = _env(sim_json, backend)  # the action was checked in the parent (WorldPool.push)
    return _arrays(env.simulate(State(qpos, qvel, pos, mat, None, broken), *env.plate_trajectory(jnp.asarray(action))))


def _poses(s: State) -> dict:
    return dict(pos=s.pos, mat=s.mat, broken=s.broken)


def _random_episode(job) -> dict:
    """``env.random_episode`` in a host engine: poses and broken flags of every frame, and the pushes."""
    sim_json, backend, key, pushes = job
    frames, actions = random_episode(_env(sim_json, backend), jnp.asarray(key, jnp.uint32), pushes, _poses, python_scan)
    return dict({k: np.asarray(v) for k, v in frames.items()}, action=np.asarray(actions, np.float32))


@functools.lru_cache(maxsize=16)
def _renderer(scene: SceneConfig, camera: CameraConfig):
    """Jitted renderer of poses pos [B, N, 3], mat [B, N, 3, 3] -> batched Observation (one compile per scene)."""
    return jax.jit(jax.vmap(Renderer(build_scene(scene), Camera.top_down(camera)).__call__))


class WorldPool:
    """Worlds of one SimConfig stepped in ``processes`` (``process_pool``; None: in this process, for tests and
    debugging) by a host physics (``backend``, default C MuJoCo). ``reset(keys)`` and ``push(states, actions)`` take
    and return PileEnv States batched on a leading axis, observations rendered here on the JAX device. ``env`` gives
    the scene, camera and action checks."""

    def __init__(self, config: SimConfig, processes=None, backend: str = "mujoco"):
        self.env, self.backend = PileEnv(config, backend=backend, render=False), backend
        self._render = _renderer(config.scene, config.camera)
        self.config, self.camera, self.scene = config, self.env.camera, self.env.scene
        self._json = config.to_json()
        self._processes = processes

    def _map(self, fn, jobs) -> list:
        return list(self._processes.imap(fn, jobs)) if self._processes is not None else [fn(j) for j in jobs]

    def _states(self, rows) -> State:
        qpos, qvel, pos, mat, broken = (np.stack(x) for x in zip(*rows, strict=True))
        pos, mat = jnp.asarray(pos), jnp.asarray(mat)
        return State(jnp.asarray(qpos), jnp.asarray(qvel), pos, mat, in_chunks(self._render, pos, mat),
                     jnp.asarray(broken))

    def reset(self, keys) -> State:
        """New settled piles, one per key: keys [B, 2] -> State [B]."""
        return self._states(self._map(_reset, [(self._json, self.backend, np.asarray(k)) for k in keys]))

    def push(self, states: State, actions) -> State:
        """One push per world: actions [B, 4] (checked like ``PileEnv.push``; a bad one raises ValueError)."""
        actions = _checked(self.env, actions)
        worlds = zip(*(np.asarray(x) for x in (states.qpos, states.qvel, states.pos, states.mat, states.broken)),
                     strict=True)
        jobs = [(self._json, self.backend, w, a) for w, a in zip(worlds, actions, strict=True)]
        return self._states(self._map(_push, jobs))

    def random_episodes(self, keys, pushes: int) -> dict:
        """Data generation: per key a reset and ``pushes`` random pushes. Returns arrays with a leading world axis:
        pos [B, F, N, 3], mat [B, F, N, 3, 3], broken [B, F], action [B, F - 1, 4], depth (float16) and piece
        (int16) [B, F, H, W] (F = pushes + 1)."""
        episodes = self._map(_random_episode, [(self._json, self.backend, np.asarray(k), pushes) for k in keys])
        out = {name: np.stack([e[name] for e in episodes]) for name in episodes[0]}
        flat = lambda x: jnp.asarray(x.reshape((-1,) + x.shape[2:]))  # noqa: E731
        obs = self._render(flat(out["pos"]), flat(out["mat"]))
        frames = out["broken"].shape
        out["depth"] = np.asarray(obs.depth.astype(jnp.float16)).reshape(frames + obs.depth.shape[1:])
        out["piece"] = np.asarray(obs.piece.astype(jnp.int16)).reshape(frames + obs.piece.shape[1:])
        return out


def per_world(fn):
    """``fn`` of one world -> the same over a batch (a leading world axis on every argument and on the result), one
    world after another in this process: how C MuJoCo worlds batch where ``jax.vmap`` cannot."""
    def batched(*args):
        worlds = [fn(*(jax.tree.map(lambda x, b=b: x[b], a) for a in args)) for b in range(len(args[-1]))]
        return jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *worlds)

    return batched


class EnvWorlds:
    """One PileEnv's worlds as a batch: ``reset(keys)`` and ``push(states, actions)`` on States with a leading world
    axis. An MJX env's are one jitted, vmapped call each (compiled once per env and batch size); a C MuJoCo env's
    step one world after another in this process."""

    def __init__(self, env: PileEnv):
        self.env, self.config, self.camera, self.scene = env, env.config, env.camera, env.scene
        if env.physics.traced:
            self._reset, self._push = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.push))
        else:
            self._reset, self._push = per_world(env.reset), per_world(env.push)

    def reset(self, keys) -> State:
        """New settled piles, one per key: keys [B, 2] -> State [B]."""
        return self._reset(jnp.asarray(keys))

    def push(self, states: State, actions) -> State:
        """One push per world: actions [B, 4] (checked like ``PileEnv.push``; a bad one raises ValueError)."""
        return self._push(states, jnp.asarray(_checked(self.env, actions)))


class MJXPool(EnvWorlds):
    """Worlds of one SimConfig stepped together by a traced physics (default MJX) on the JAX device (``EnvWorlds``
    of its PileEnv)."""

    def __init__(self, config: SimConfig, backend: str = "mjx"):
        super().__init__(PileEnv(config, backend=backend))


class SizedPool:
    """Worlds of one SimConfig stepped together by a traced physics whose capacities are sized per batch (default
    MuJoCo Warp on the GPU, ``sim.physics.warp``), so each batch size in use gets its own engine (and compile). A
    batch in which a world ran out of capacity raises (Warp: ``CapacityError``); ``env`` is the one-world engine
    (scene, camera, action checks)."""

    def __init__(self, config: SimConfig, backend: str = "warp"):
        self.config, self.backend, self._sizes = config, backend, {}
        self.env = self._worlds(1).env
        self.camera, self.scene = self.env.camera, self.env.scene

    def _worlds(self, n: int) -> EnvWorlds:
        if n not in self._sizes:
            self._sizes[n] = EnvWorlds(PileEnv(self.config, backend=self.backend, worlds=n))
        return self._sizes[n]

    def _checked(self, states: State) -> State:
        self.env.physics.check_batch(states.overflow, self.scene.n_pieces)
        return states

    def reset(self, keys) -> State:
        """New settled piles, one per key: keys [B, 2] -> State [B]."""
        return self._checked(self._worlds(len(keys)).reset(keys))

    def push(self, states: State, actions) -> State:
        """One push per world: actions [B, 4] (checked like ``PileEnv.push``; a bad one raises ValueError)."""
        return self._checked(self._worlds(len(actions)).push(states, actions))


class Worlds(Protocol):
    """What the closed loop pushes (``control.mpc.run``): ``EnvWorlds``, ``MJXPool``, ``SizedPool``, ``WorldPool``."""

    camera: Camera
    scene: object

    def reset(self, keys) -> State: ...

    def push(self, states: State, actions) -> State: ...


def make_pool(config: SimConfig, backend: str, processes=None) -> WorldPool | MJXPool | SizedPool:
    """Worlds of ``config`` in the engine ``backend`` (``engines.NAMES``), as that engine simulates the scene, read
    from its physics (``sim.physics.Physics``): ``WorldPool`` where it runs on the host (C MuJoCo; on ``processes``
    where it steps in worker processes, else in this one), ``SizedPool`` where its capacities depend on the batch
    (MuJoCo Warp), else ``MJXPool`` (MJX, on the fast scene's physics for "mjx-fast")."""
    physics, config = engines.ENGINES[engines.resolve(backend)].physics, engines.sim_config(config, backend)
    if not physics.traced:
        return WorldPool(config, processes if physics.workers else None, physics.name)
    return (SizedPool if physics.per_batch else MJXPool)(config, physics.name)
