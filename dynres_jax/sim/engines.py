"""The engines that push piles, in one table: every command's ``--backend`` choices and every engine name come from
``ENGINES`` (and "auto"), and what callers need to know of an engine (host workers, one device) is read from its row,
never from its name. An engine on an existing physics (another fast variant) is one row here; a new physics is one
module of ``sim.physics`` and one row here.

An engine is a physics (``sim.physics``: the C engine, MJX, or MuJoCo Warp; ``PileEnv``'s backend is its name) with
the scene's physics parameters as given or as ``SceneConfig.fast``'s. Where the pushes run is ``sim.pool``'s
business, read from the physics: the C engine in worker processes (one world a core), MJX and Warp as one batch on
the JAX devices.
"""

from __future__ import annotations

import dataclasses

import jax

from dynres_jax.config import SimConfig, fast_fields
from dynres_jax.sim.physics import Physics
from dynres_jax.sim.physics.c import CPhysics
from dynres_jax.sim.physics.mjx import MJXPhysics
from dynres_jax.sim.physics.warp import WarpPhysics


@dataclasses.dataclass(frozen=True)
class Engine:
    """One row of the table. physics: its ``sim.physics`` class (its name is ``PileEnv``'s backend); fast: the scene
    runs on ``SceneConfig.fast``'s physics; extra: the pip extra it needs (None: none; its physics' ``check_installed``
    raises InputError naming it when missing); about: one line for --help; one_device: a batch of worlds runs on one
    device (not sharded over several); c_physics: its pushes match the C engine's (so C workers may fill shards of
    one data set beside it)."""
    name: str
    physics: type[Physics]
    fast: bool
    extra: str | None
    about: str
    one_device: bool = False
    c_physics: bool = False

    @property
    def workers(self) -> bool:
        """Its worlds step in host worker processes, one a core (``sim.pool.process_pool``), not on the JAX devices."""
        return self.physics.workers


ENGINES = {e.name: e for e in (
    Engine("mujoco", CPhysics, False, None, "C MuJoCo in worker processes, one world a host core (the reference)",
           c_physics=True),
    Engine("mjx", MJXPhysics, False, None, "MuJoCo XLA, the worlds as one batch on the JAX devices"),
    Engine("mjx-fast", MJXPhysics, True, None, "MJX on the fast scene's physics (SceneConfig.fast; not C's)"),
    Engine("warp", WarpPhysics, False, "warp",
           "MuJoCo Warp on one GPU: C's physics ('pip install \"dynres-jax[warp]\"')", one_device=True, c_physics=True),
)}
AUTO = "auto"  # "mjx-fast" where JAX's default backend is a GPU, else "mujoco"
NAMES = (AUTO, *ENGINES)  # every --backend's choices


def resolve(name: str) -> str:
    """An engine name of ``NAMES`` made concrete: "auto" is "mjx-fast" where JAX's default backend is a GPU, else
    "mujoco". ValueError for a name not in NAMES; InputError naming the extra for an engine whose extra is missing."""
    if name not in NAMES:
        raise ValueError(f"backend must be one of {', '.join(NAMES)}, got {name!r}")
    if name == AUTO:
        return "mjx-fast" if jax.default_backend() == "gpu" else "mujoco"
    if ENGINES[name].extra is not None:
        ENGINES[name].physics.check_installed()
    return name


def sim_config(config: SimConfig, name: str) -> SimConfig:
    """``config`` as the engine ``name`` simulates it: with ``SceneConfig.fast``'s physics for its kinds where the
    engine is fast, else unchanged."""
    if not ENGINES[resolve(name)].fast:
        return config
    return dataclasses.replace(config, scene=dataclasses.replace(config.scene, **fast_fields(config.scene.kinds)))


def beside(config, cpu_workers: int):
    """The config of ``cpu_workers`` C MuJoCo worker processes filling shards beside the engine of ``config`` (any
    config with a ``backend``): ``config`` with backend "mujoco", or None for none. ValueError unless they may: none,
    or any number beside a JAX engine of C's physics (``Engine.c_physics``, not ``workers``: Warp)."""
    engine = ENGINES[resolve(config.backend)]
    if cpu_workers < 0 or (cpu_workers > 0 and (engine.workers or not engine.c_physics)):
        raise ValueError(f"C workers ({cpu_workers}) fill shards beside a JAX engine of C's physics (warp); got "
                         f"backend {config.backend!r}")
    return dataclasses.replace(config, backend="mujoco") if cpu_workers else None


def physics(name: str) -> str:
    """``PileEnv``'s backend for the engine ``name``: its physics' name."""
    return ENGINES[resolve(name)].physics.name


def physics_named(backend: str) -> type[Physics]:
    """The ``sim.physics`` class of a ``PileEnv`` backend (a physics' name); ValueError naming the choices."""
    known = {e.physics.name: e.physics for e in ENGINES.values()}
    if backend not in known:
        raise ValueError(f"backend must be one of {', '.join(map(repr, known))}, got {backend!r}")
    return known[backend]


def uses_workers(name: str) -> bool:
    """Whether the engine ``name`` steps its worlds in host worker processes (a command starts a process pool)."""
    return ENGINES[resolve(name)].workers


def help_text(default: str) -> str:
    """The --backend help: every engine of the table, one line each, and the default."""
    rows = "; ".join(f"{e.name}: {e.about}" for e in ENGINES.values())
    return f"the engine that pushes the piles ({AUTO}: mjx-fast with a GPU, else mujoco; {rows}; default {default})"
