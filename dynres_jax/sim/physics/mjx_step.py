"""MJX's ``step`` with the contact Jacobian built only where it can be non-zero.

MJX (JAX backend) builds each contact's Jacobian row over every degree of freedom of the world: for every contact it
scans the body tree for a mask and takes a cross product at every dof, then multiplies by the contact frame. With
100 pieces that is [contacts, nv, 3] of work per step, a third of a CG step on the GPU. A contact between two
bodies can only move their own dofs and their ancestors', a set fixed by the model: here at most three a piece.
``make_constraint`` computes those few entries and writes the dense row once; everything else (which rows exist,
their order, impedances, reference accelerations) is MJX's own, so ``step`` matches ``mujoco.mjx.step`` to float
rounding (tested).

``step(m, d, dofs)`` supports what the pile scenes use: dof friction loss, contacts of dimension 1 or 3 (pyramidal or
elliptic), the Euler integrator, no equality constraints, limits, tendons, actuators or sensors.
``check_supported`` names whatever else a model has. ``traced_template``: a Data template (MJX's or MuJoCo Warp's)
whose zero arrays are built inside the trace, not captured in the program.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco.mjx._src import collision_driver, smooth, solver
from mujoco.mjx._src import constraint as mjx_constraint
from mujoco.mjx._src import forward as mjx_forward
from mujoco.mjx._src.types import ConeType

TESTED_MUJOCO = "3.17.0"  # the MuJoCo (and MuJoCo MJX) release whose internals ``step`` is written against


def check_version(installed: str = mujoco.__version__) -> None:
    """Raise RuntimeError unless the installed MuJoCo is the one ``step`` was tested on: it calls MJX's private
    modules (``mujoco.mjx._src``), which change between releases without notice."""
    if installed != TESTED_MUJOCO:
        raise RuntimeError(f"mjx_step.step is written against MuJoCo MJX {TESTED_MUJOCO}'s internals, but MuJoCo "
                           f"{installed} is installed: install mujoco=={TESTED_MUJOCO} mujoco-mjx=={TESTED_MUJOCO}, "
                           "or step with the public mujoco.mjx.step (PileEnv(..., contact_jacobian='dense'))")


def check_supported(model: mujoco.MjModel) -> None:
    """Raise ValueError naming every feature of ``model`` that ``step`` does not handle."""
    problems = [what for what, n in [("equality constraints", model.neq), ("tendons", model.ntendon),
                                     ("actuators", model.nu), ("sensors", model.nsensor),
                                     ("limited joints", int(model.jnt_limited.sum()))] if n]
    if model.opt.integrator != mujoco.mjtIntegrator.mjINT_EULER:
        problems.append(f"integrator {mujoco.mjtIntegrator(model.opt.integrator).name} (Euler only)")
    dims = set(collision_driver.make_condim(model).tolist())
    if dims - {1, 3}:
        problems.append(f"contact dimensions {sorted(dims - {1, 3})} (1 and 3 only)")
    if problems:
        raise ValueError("mjx_step.step does not support " + ", ".join(problems) + "; use mujoco.mjx.step")


def chain_dofs(model: mujoco.MjModel) -> np.ndarray:
    """[nbody, K] the dofs that move each body (its own and its ancestors'), padded with -1."""
    chains = []
    for b in range(model.nbody):
        dofs, a = [], b
        while a > 0:
            dofs = [k for k in range(model.nv) if model.dof_bodyid[k] == a] + dofs
            a = model.body_parentid[a]
        chains.append(dofs)
    out = -np.ones((model.nbody, max(1, max(map(len, chains)))), np.int32)
    for b, dofs in enumerate(chains):
        out[b, : len(dofs)] = dofs
    return out


def _contact_jacobian(m, d, contact, dim: int, dofs: np.ndarray) -> jax.Array:
    """[C * rows, nv] constraint Jacobian rows of C contacts of dimension ``dim``, in MJX's order (contact-major;
    pyramidal: ±friction edges per tangent direction; elliptic: normal then tangents), inactive contacts zero."""
    body = jnp.asarray(m.geom_bodyid)[contact.geom]  # [C, 2]
    dof = jnp.asarray(dofs)[body]  # [C, 2, K]
    offset = contact.pos[:, None] - d.subtree_com[jnp.asarray(m.body_rootid)[body]]  # [C, 2, 3]
    cdof = d.cdof[jnp.maximum(dof, 0)]  # [C, 2, K, 6]
    jacp = cdof[..., 3:] + jnp.cross(cdof[..., :3], offset[:, :, None])  # [C, 2, K, 3]
    jacp = jacp * ((dof >= 0) * jnp.array([-1.0, 1.0])[:, None])[..., None]  # body2 minus body1
    diff = jnp.einsum("cij,cbkj->cibk", contact.frame[:, :dim], jacp)  # [C, dim, 2, K]
    if dim == 1 or m.opt.cone == ConeType.ELLIPTIC:
        rows = diff
    else:  # pyramidal: edges d0 + mu_i d_i and d0 - mu_i d_i for each tangent direction i
        mu = jnp.repeat(contact.friction[:, : dim - 1], 2, axis=1) * jnp.tile(jnp.array([1.0, -1.0]), dim - 1)
        rows = diff[:, :1] + jnp.repeat(diff[:, 1:], 2, axis=1) * mu[:, :, None, None]
    active = (contact.dist - contact.includemargin < 0)[:, None, None, None]
    rows = rows * active  # [C, R, 2, K]
    onehot = dof[:, None, :, :, None] == jnp.arange(m.nv)  # [C, 1, 2, K, nv]
    jac = jnp.sum(jnp.where(onehot, rows[..., None], 0.0), axis=(2, 3))  # [C, R, nv]
    return jac.reshape(-1, m.nv)


def make_constraint(m, d, dofs: np.ndarray):
    """``mjx._src.constraint.make_constraint`` for the supported models, contact rows from ``_contact_jacobian``."""
    efcs = [mjx_constraint._efc_friction(m, d)]
    contact_fn = (mjx_constraint._efc_contact_elliptic if m.opt.cone == ConeType.ELLIPTIC
                  else mjx_constraint._efc_contact_pyramidal)
    for dim in (1, 3):
        con_id = np.nonzero(d._impl.contact.dim == dim)[0]
        if con_id.size == 0:
            continue
        # MJX's rows for everything but J; XLA drops the dense Jacobian those functions compute, as nothing reads it.
        efc = mjx_constraint._efc_contact_frictionless(m, d) if dim == 1 else contact_fn(m, d, dim)
        contact = jax.tree.map(lambda x, con_id=con_id: x[con_id], d._impl.contact)
        efcs.append(efc.replace(J=_contact_jacobian(m, d, contact, dim, dofs)))
    efc = jax.tree.map(lambda *x: jnp.concatenate(x), *[e for e in efcs if e is not None])

    @jax.vmap
    def fn(efc):
        k, b, imp = mjx_constraint._kbi(m, efc.solref, efc.solimp, efc.pos_imp)
        r = jnp.maximum(efc.invweight * (1 - imp) / imp, mujoco.mjMINVAL)
        aref = -b * (efc.J @ d.qvel) - k * imp * efc.pos_aref
        return aref, r, efc.pos_aref + efc.margin, efc.margin, efc.frictionloss

    aref, r, pos, margin, frictionloss = fn(efc)
    return d.tree_replace({"_impl.efc_J": efc.J, "_impl.efc_D": 1 / r, "_impl.efc_aref": aref,
                           "_impl.efc_pos": pos, "_impl.efc_margin": margin,
                           "_impl.efc_frictionloss": frictionloss})


def step(m, d, dofs: np.ndarray):
    """One simulator step, as ``mujoco.mjx.step(m, d)``; ``dofs = chain_dofs(model)``."""
    d = smooth.kinematics(m, d)
    d = smooth.com_pos(m, d)
    d = smooth.camlight(m, d)
    d = smooth.crb(m, d)
    d = smooth.factor_m(m, d)
    d = collision_driver.collision(m, d)
    d = make_constraint(m, d, dofs)
    d = mjx_forward.fwd_velocity(m, d)
    d = mjx_forward.fwd_actuation(m, d)
    d = mjx_forward.fwd_acceleration(m, d)
    d = solver.solve(m, d)
    return mjx_forward.euler(m, d)


def traced_template(data0):
    """A function returning ``data0`` (an MJX Data, or any pytree of arrays) with each all-zero array rebuilt by
    ``jnp.zeros`` where it is called: inside ``jax.jit`` those are ops, not constants captured in the program
    (MuJoCo Warp's contact buffers grow with the batch: 2 GB of constants at 8,192 worlds). Equal values."""
    zero = jax.tree.map(lambda x: not bool(jnp.any(x)), data0)

    def template():
        return jax.tree.map(lambda x, z: jnp.zeros(x.shape, x.dtype) if z else x, data0, zero)

    return template
