"""PropNet's propagation step over a particle graph, with a hand-written gradient (``dynamics.Dynamics``, steps 3-4
of its module docstring): the summed edge effects Σ_j ReLU(c_ij + r_i + s_j) of every receiver i, where c_ij is the
edge's constant term (per edge, or a row of the pair table) and r_i, s_j the receiver and sender terms of the nodes;
and GNS's message-passing step (``GNSStep``) with the MLPs both build (``mlp``).

Repeatable sums. A gather's gradient adds each row's cotangents back into its source row; as a float scatter-add
on a GPU that sum is done by atomics in whatever order they land, so two runs of the same inputs differ in the last
bits, and a planner's argmin, then a whole closed-loop episode, with them (docs/repeat). Every such sum here is
``exact_scatter_add``: in fixed point, where integer addition gives the same bits in any order."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import nnx

FIXED_POINT_BITS = 30  # a channel's total |value| is scaled below 2^30, so no int32 partial sum overflows


def exact_scatter_add(index, values, n: int, bound=None):
    """Σ of values [..., C] into n rows by index [...] (int, in [0, n)) -> [n, C] float32, bit for bit the same
    whatever order the additions run in (GPU atomics included). Each channel is scaled by a power of two so that its
    total |value| (or ``bound`` [C], an upper bound on it known without a pass over the values) is below 2^30,
    rounded to integers, summed as int32 (integer sums do not depend on the order, and none can overflow) and scaled
    back. Each term is rounded to 2^-31 of twice the channel's bound: a row of d terms errs by at most d x 2^-30 x
    bound, about float32's own error where the row's sum is near the bound, more where it is far below (totals under
    2^-96 sum to 0). One int32 word a term: a plan at the evaluation's batch takes 1.4x as long as with a float
    scatter, with two words (60 bits) 2.3x (H100; no cost on a CPU: docs/repeat)."""
    values = jnp.asarray(values, jnp.float32)
    flat, index = values.reshape(-1, values.shape[-1]), jnp.asarray(index).reshape(-1)
    total = jnp.sum(jnp.abs(flat), axis=0) if bound is None else jnp.asarray(bound, jnp.float32)  # [C]
    # total < 2^e (frexp), so total x 2^(30 - e) < 2^30; capped where 2^(30 - e) would overflow float32
    scale = jnp.ldexp(jnp.ones_like(total), jnp.minimum(FIXED_POINT_BITS - jnp.frexp(total)[1], 126))  # [C]
    summed = jnp.zeros((n, flat.shape[-1]), jnp.int32).at[index].add(jnp.round(flat * scale).astype(jnp.int32))
    # a NaN or inf has no fixed point: its channel is NaN, as a float sum would be (never finite garbage)
    return jnp.where(jnp.isfinite(total), summed.astype(jnp.float32) / scale, jnp.nan)


@jax.custom_vjp
def gather_rows(x, index):
    """x [N, C] float32, index [...] int in [0, N) -> x[index] [..., C], whose gradient w.r.t. x sums by
    ``exact_scatter_add`` (repeatable on GPUs) instead of a float scatter-add."""
    return x[index]


def _gather_fwd(x, index):
    return x[index], (index, x.shape[0])


def _gather_bwd(residuals, grad):
    index, n = residuals
    return exact_scatter_add(index, grad, n).astype(grad.dtype), None


gather_rows.defvjp(_gather_fwd, _gather_bwd)


def _edge_input(pair, constant, neighbours, node_terms):
    """The edge propagator's input before its ReLU [N, k, H] in the constant's dtype: c_ij + r_i + s_j, with c_ij
    row j of the pair table's row i when ``pair`` (constant [N, N, H]), else constant [N, k, H] itself; node_terms
    [N, 2H] float32 holds the receiver terms r and the sender terms s side by side (one matrix product makes both).
    The senders are gathered from its [2N, H] view, where row 2j + 1 is s_j: a gather of the sender half would
    first copy it out. The node terms are cast after the broadcast and the gather."""
    n, h = node_terms.shape[0], node_terms.shape[-1] // 2
    c = jnp.take_along_axis(constant, neighbours[..., None], axis=1) if pair else constant
    senders = node_terms.reshape(2 * n, h)[2 * neighbours + 1]  # [N, k, H]
    return c + node_terms[:, None, :h].astype(c.dtype) + senders.astype(c.dtype)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def incoming_effects(pair, constant, neighbours, edge_mask, node_terms):
    """One propagation step's summed edge effects: Σ over i's edges j of ReLU(c_ij + r_i + s_j) -> [N, H] float32
    (neighbours [N, k], edge_mask [N, k]; ``_edge_input`` for the rest).

    The gradient is hand-written. The forward pass also counts each receiver's active edges per channel (int8 for
    k <= 127: a quarter of a float32 count's memory traffic), so the gradient w.r.t. r is the incoming gradient times
    that count, with no pass over the edges. The only per-edge work of the backward pass is the senders' sum: it
    recomputes which edges are active (XLA fuses that into the scatter-add) instead of storing them, and adds the
    per-edge gradients up by sender (``exact_scatter_add``, so GPU runs repeat)."""
    return _incoming_fwd(pair, constant, neighbours, edge_mask, node_terms)[0]


def _incoming_fwd(pair, constant, neighbours, edge_mask, node_terms):
    x = _edge_input(pair, constant, neighbours, node_terms)
    active = edge_mask[..., None] & (x > 0)
    incoming = jnp.sum(jnp.where(active, x, 0.0), axis=1, dtype=jnp.float32)  # Σ ReLU(x) over the real edges
    count_dtype = jnp.int8 if neighbours.shape[1] <= jnp.iinfo(jnp.int8).max else jnp.int32
    count = jnp.sum(active, axis=1, dtype=count_dtype)  # [N, H]: active edges per receiver and channel (<= k)
    # The barrier keeps XLA from merging the backward pass's recomputed flags with these: it would store the flags.
    return incoming, jax.lax.optimization_barrier((constant, neighbours, edge_mask, node_terms, count))


def _incoming_bwd(pair, residuals, grad):
    constant, neighbours, edge_mask, node_terms, count = residuals
    active = edge_mask[..., None] & (_edge_input(pair, constant, neighbours, node_terms) > 0)
    per_edge = jnp.where(active, grad[:, None, :], 0.0)  # [N, k, H] float32
    # |per_edge| <= |grad| of its receiver, so k x Σ|grad| bounds each channel's total without a pass over the edges
    bound = neighbours.shape[1] * jnp.sum(jnp.abs(grad), axis=0)
    grad_senders = exact_scatter_add(neighbours, per_edge, grad.shape[0], bound)
    grad_terms = jnp.concatenate([grad * count.astype(jnp.float32), grad_senders], axis=1)  # [N, 2H]: r | s
    grad_constant = per_edge.astype(constant.dtype)
    if pair:  # each (receiver, sender) pair has one real edge (repeats are masked, adding 0): the same in any order
        rows = jnp.arange(neighbours.shape[0])[:, None]
        grad_constant = jnp.zeros_like(constant).at[rows, neighbours].add(grad_constant)
    return grad_constant, None, None, grad_terms.astype(node_terms.dtype)


incoming_effects.defvjp(_incoming_fwd, _incoming_bwd)


def mlp(sizes, rngs, *, final_relu):
    """Linear layers of the given sizes with ReLU between them (and after the last when final_relu)."""
    layers = []
    for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        layers.append(nnx.Linear(n_in, n_out, rngs=rngs))
        if final_relu or i < len(sizes) - 2:
            layers.append(nnx.relu)
    return nnx.Sequential(*layers)


class GNSStep(nnx.Module):
    """One GNS message-passing step with weights of its own (``dynamics`` module docstring, "Processor")."""

    def __init__(self, h: int, rngs: nnx.Rngs):
        self.edge_in = nnx.Linear(3 * h, h, rngs=rngs)  # [edge, receiver, sender]: split when applied
        self.edge_out = nnx.Linear(h, h, rngs=rngs)
        self.edge_norm = nnx.LayerNorm(h, rngs=rngs)
        self.node_mlp = mlp((2 * h, h, h), rngs, final_relu=False)  # [node, summed messages]
        self.node_norm = nnx.LayerNorm(h, rngs=rngs)

    def __call__(self, nodes, edges, neighbours, valid):
        """nodes [N, H], edges [N, k, H], neighbours [N, k], valid [N, k, 1] -> (nodes, edges) after the step."""
        h = nodes.shape[-1]
        w = self.edge_in.kernel[...]
        terms = nodes @ jnp.concatenate([w[h:2 * h], w[2 * h:]], axis=1)  # [N, 2H]: receiver | sender
        hidden = edges @ w[:h] + terms[:, None, :h] + gather_rows(terms[:, h:], neighbours) + self.edge_in.bias[...]
        message = jnp.where(valid, self.edge_norm(self.edge_out(nnx.relu(hidden))), 0.0)
        summed = jnp.sum(message, axis=1)
        nodes = nodes + self.node_norm(self.node_mlp(jnp.concatenate([nodes, summed], -1)))
        return nodes, edges + message
