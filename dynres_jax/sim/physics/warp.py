"""MuJoCo Warp, the physics behind ``PileEnv(backend="warp")`` (``WarpPhysics``): MJX's ``impl="warp"`` runs the C
engine's own algorithms (collision, Newton solver) as Warp kernels on the GPU, under ``jax.jit`` and ``jax.vmap``.

What this module adds to MJX's two calls (``mjx.put_model(m, impl="warp")``, ``mjx.make_data(m, impl="warp")``):
- capacities: MuJoCo Warp holds every contact of a batch in one buffer of ``naconmax`` rows and every world's
  constraint rows in ``njmax``; ``capacities`` sizes both from the scene's piece count and the batch's world count;
- overflow as an error: a world whose contacts or constraints did not fit was simulated wrongly. The engine keeps
  MuJoCo Warp's per-world overflow bits (``CAPACITY_FLAGS``) and the pool raises ``CapacityError`` naming the
  capacity; the solver's own iteration limits (which C MuJoCo also stops at, silently) are not errors, so the
  kernels' per-step overflow prints are switched off;
- the first call: a CUDA graph cannot be captured while Warp compiles and loads its kernels, which made the first
  call of every fresh process fail (Warp CUDA error 901). ``warm_up`` runs one step uncaptured first.

Install: ``pip install "dynres-jax[warp]"`` (warp-lang, the version mujoco-mjx's own ``warp`` extra pins).
"""

from __future__ import annotations

import functools

import jax
import mujoco
import numpy as np
from mujoco import mjx
from mujoco.mjx import warp as mjx_warp

from dynres_jax.errors import InputError
from dynres_jax.sim.physics import Poses, mjx_step
from dynres_jax.sim.physics.mjx import run_steps

EXTRA = 'pip install "dynres-jax[warp]"'

# Contacts a piece can hold at once (table, neighbours, walls, plate; a box-box pair has up to 8 points), and rows a
# contact adds to the constraint system (pyramidal condim 3: 4). Measured maxima are in docs/warp (a 2x margin).
CONTACTS_PER_PIECE = 16
ROWS_PER_CONTACT = 4

# MuJoCo Warp's OverflowType bits that mean a capacity was too small (NEFC, NJMAX_NNZ, BROADPHASE, NARROWPHASE, CCD,
# NVMAX, EPA_HORIZON); ITERATIONS and LS_ITERATIONS (solver limits) are left out.
CAPACITY_FLAGS = (1 << 0) | (1 << 1) | (1 << 2) | (1 << 3) | (1 << 4) | (1 << 7) | (1 << 8)
_FLAG_NAMES = {1 << 0: "constraint rows (njmax)", 1 << 1: "constraint Jacobian entries (njmax)",
               1 << 2: "broadphase pairs (naconmax)", 1 << 3: "contacts (naconmax)", 1 << 4: "convex collision",
               1 << 7: "island dofs", 1 << 8: "EPA horizon"}


class CapacityError(RuntimeError):
    """MuJoCo Warp ran out of a capacity (contacts or constraint rows) in some worlds of a batch."""


def check_installed() -> None:
    """Raise InputError naming the extra unless MuJoCo Warp (warp-lang) can be imported."""
    if not mjx_warp.WARP_INSTALLED:
        raise InputError(f"the 'warp' engine needs MuJoCo Warp, which needs warp-lang: {EXTRA}")


def capacities(n_pieces: int, worlds: int) -> tuple[int, int]:
    """(naconmax: contacts over the whole batch, njmax: constraint rows per world) for ``worlds`` worlds of
    ``n_pieces`` pieces."""
    if worlds < 1:
        raise ValueError(f"worlds must be at least 1, got {worlds}")
    per_world = CONTACTS_PER_PIECE * max(n_pieces, 1)
    return per_world * worlds, per_world * ROWS_PER_CONTACT + 64


def put(model: mujoco.MjModel, n_pieces: int, worlds: int, device=None, graph_mode=None):
    """(mx, data0): ``model`` on ``device`` as MuJoCo Warp runs it, overflow prints off, and a Data template sized
    by ``capacities`` for ``worlds`` worlds. graph_mode: a ``warp.JaxCallableGraphMode``; default NONE, no CUDA
    graphs (docs/warp: on an H200 faster than Warp's own graphs, and a graph captured while a new scene's kernels
    load fails with Warp CUDA error 904)."""
    check_installed()
    if graph_mode is None:
        from warp import JaxCallableGraphMode  # only once installed

        graph_mode = JaxCallableGraphMode.NONE
    device = device or jax.local_devices()[0]
    naconmax, njmax = capacities(n_pieces, worlds)
    mx = mjx.put_model(model, device=device, impl="warp", graph_mode=graph_mode)
    mx = mx.replace(opt=mx.opt.replace(_impl=mx.opt._impl.replace(warn_overflow=0)))
    return mx, mjx.make_data(model, device=device, impl="warp", naconmax=naconmax, njmax=njmax)


def overflow(d) -> jax.Array:
    """A Data's capacity overflow bits (int32 per world; MuJoCo Warp ORs them step by step until a reset)."""
    return d._impl.overflow.reshape(()) & CAPACITY_FLAGS


def check_overflow(flags, n_pieces: int) -> None:
    """Raise CapacityError naming the capacities that overflowed, in how many of the batch's worlds: flags [B] (or
    [B, ...], one batch), ``overflow``'s bits of a batch of worlds of ``n_pieces`` pieces."""
    flags = np.asarray(flags).reshape(len(flags), -1)
    hit = [f"{name}: {int(np.sum((flags & bit).any(1)))} worlds" for bit, name in _FLAG_NAMES.items()
           if np.any(flags & bit)]
    if not hit:
        return
    naconmax, njmax = capacities(n_pieces, len(flags))
    raise CapacityError(f"MuJoCo Warp ran out of capacity in a batch of {len(flags)} worlds of {n_pieces} pieces "
                        f"({'; '.join(hit)}; naconmax {naconmax}, njmax {njmax}): those worlds were simulated wrongly. "
                        f"Raise dynres_jax.sim.physics.warp.CONTACTS_PER_PIECE (now {CONTACTS_PER_PIECE})")


@functools.lru_cache(maxsize=8)
def _warmed(key) -> bool:
    model, n_pieces = key
    mx, d = put(model, n_pieces, 1)  # no graph captured
    jax.block_until_ready(jax.jit(mjx.step)(mx, d).qpos)
    return True


def warm_up(model: mujoco.MjModel, n_pieces: int) -> None:
    """Compile and load MuJoCo Warp's kernels for ``model`` with one step outside CUDA graph capture (once per
    model and process): a graph captured while kernels load fails (the benchmark's WARP mode; ``put``'s default
    captures none, and kernels a larger batch adds still load on its first call)."""
    if jax.default_backend() == "gpu":
        _warmed((model, n_pieces))


class WarpPhysics:
    """MuJoCo Warp on the first local JAX device (a GPU), its capacities sized for ``worlds`` worlds a batch
    (contact_jacobian: the protocol's, unused). ``run`` is pure JAX, as MJX's; its Poses carry the overflow bits."""

    name, traced, workers, per_batch = "warp", True, False, True

    def __init__(self, scene, worlds: int = 1, contact_jacobian: str = "dense"):
        self.mx, data0 = put(scene.model, scene.n_pieces, worlds)
        self.data0, self.gid = mjx_step.traced_template(data0), scene.geom_id
        warm_up(scene.model, scene.n_pieces)

    def run(self, qpos, qvel, plate_pos, plate_quat) -> Poses:
        d, pos, mat = run_steps(self.mx, self.data0, mjx.step, self.gid, qpos, qvel, plate_pos, plate_quat)
        return Poses(d.qpos, d.qvel, pos, mat, overflow(d))

    check_batch = staticmethod(check_overflow)
    check_installed = staticmethod(check_installed)
