"""The physics behind ``PileEnv``, one module each behind one protocol (``Physics``): ``c`` (C MuJoCo, the
reference), ``mjx`` (MuJoCo XLA) and ``warp`` (MuJoCo Warp through MJX). A new physics is one module with a class of
this protocol and one row in ``sim.engines.ENGINES``: ``PileEnv(backend=its name)``, the pools and every command's
--backend then take it."""

from __future__ import annotations

import contextlib
import io
from typing import ClassVar, NamedTuple, Protocol

import jax

with contextlib.redirect_stdout(io.StringIO()):  # mujoco.mjx prints a notice when the optional Warp is missing: once
    from mujoco import mjx  # noqa: F401  (here, quietly, before any physics module imports it)


class Poses(NamedTuple):
    """A world after a plate trajectory: qpos [nq], qvel [nv] (MuJoCo's state), the pieces' geom poses pos [N, 3]
    (world, metres) and mat [N, 3, 3]; overflow [] int32: capacity bits the physics ran out of (sticky; None where
    it has no capacities)."""

    qpos: jax.Array
    qvel: jax.Array
    pos: jax.Array
    mat: jax.Array
    overflow: jax.Array | None = None


class Physics(Protocol):
    """Steps one world of a scene along a plate trajectory. Built as ``Physics(scene, worlds, contact_jacobian)``
    (``sim.scene.Scene``; worlds: how many worlds a batch steps at once, where capacities depend on it;
    contact_jacobian: "sparse" or "dense", MJX's choice, ignored by the others).

    name: PileEnv's backend; traced: ``run`` is pure JAX (PileEnv jits it, pools vmap it over worlds), else it runs on
    the host, one world a call; workers: a pool steps its worlds in host worker processes, one a core
    (``sim.pool.WorldPool``); per_batch: its capacities are sized by the batch's world count (a pool builds one
    engine per batch size). A physics that can also return frames while the plate moves has ``run_drawn``
    (``c.CPhysics``); one that needs a pip extra (``sim.engines.Engine.extra``) has ``check_installed()``, raising
    InputError naming it (``warp.WarpPhysics``)."""

    name: ClassVar[str]
    traced: ClassVar[bool]
    workers: ClassVar[bool]
    per_batch: ClassVar[bool]

    def run(self, qpos, qvel, plate_pos, plate_quat) -> Poses:
        """The world from qpos [nq], qvel [nv] along plate_pos [K, 3], plate_quat [K, 4] (one row a step)."""

    @staticmethod
    def check_batch(overflow, n_pieces: int) -> None:
        """Raise naming the capacity a batch's worlds ran out of (overflow [B] of ``Poses.overflow``), if any."""
