"""Ways to sum a gather's gradient that repeat bit for bit, timed in the planner (issue 67; docs/repeat, "Sums without
int32 atomics"). Each variant replaces ``models.propagation.exact_scatter_add`` for one pass; the planner runs the
shipped model on 1,500 candidates (50 pushes x 30 re-samplings) at the buckets 32, 64 and 100, and two plans of the
same inputs are compared bit for bit.

    PYTHONPATH=. python scripts/profile_scatter.py [VARIANT ...] [--steps 100] [--profile] [--slots 32 64 100]

Variants: float (a plain float scatter-add: the speed to beat; does not repeat), int30 (the library's: 30-bit fixed
point summed as int32), int30pad (the same into one more row), int30t (the same with the channels leading),
int30barrier (the same behind an optimization barrier: no transpose folded into its scatter), limb1
(24-bit fixed point as integer-valued float32: float atomics add it exactly), limb2 (two such limbs, 38 bits, one
scatter each), onehot (a one-hot matrix product, bf16 x 3), sorted32 (each row's terms gathered through a sort, at
most 32 a row), compare (every sum a fused [E, n, C] reduction: no atomics), dense (a graph's senders' sum as a dense
[N, N] layout reduced over the receivers, other sums by compare), dense_int30 (the same, other sums int30),
densepair (the planner's pair-table step: its gradient recomputed over all N x N pairs, no gather; other sums by
compare), densepair_int30, forward (the planner's gradient by forward mode: 4T tangents through a model with no
hand-written gradient; no scatter anywhere). ``--profile`` prints the 12 slowest kernels at bucket 64 (through
torch.profiler, on a GPU); ``--dump DIR`` keeps in DIR, for each compiled plan, the HLO of its scatter fusions and
their PTX kernels (from XLA's dump). Prints ms per Adam step, whether two plans are bit-identical, and the variant's
best cost.
"""

import argparse
import glob
import os
import re
import shutil
import sys
import tempfile

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # torch's profiler shares the GPU
XLA_DUMP = tempfile.mkdtemp(prefix="xla_dump_") if "--dump" in sys.argv else None
if XLA_DUMP:  # before jax is imported
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + f" --xla_dump_to={XLA_DUMP} --xla_dump_hlo_as_text"
                               " --xla_dump_hlo_module_re=.*plan.*")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from dynres_jax.models import propagation  # noqa: E402

LIBRARY = propagation.exact_scatter_add


def _rows(index, values):
    values = jnp.asarray(values, jnp.float32)
    return jnp.asarray(index).reshape(-1), values.reshape(-1, values.shape[-1])


def _scaled(flat, bound, bits):
    """Each channel scaled by a power of two so that its total |value| is below 2^bits."""
    total = jnp.sum(jnp.abs(flat), axis=0) if bound is None else jnp.asarray(bound, jnp.float32)
    return total, jnp.ldexp(jnp.ones_like(total), jnp.minimum(bits - jnp.frexp(total)[1], 126))


def plain_float(index, values, n, bound=None):
    index, flat = _rows(index, values)
    return jnp.zeros((n, flat.shape[-1])).at[index].add(flat)


def limb1(index, values, n, bound=None):
    index, flat = _rows(index, values)
    total, scale = _scaled(flat, bound, 23)  # rounded terms sum below 2^24: exact in float32, in any order
    summed = jnp.zeros((n, flat.shape[-1])).at[index].add(jnp.round(flat * scale))
    return jnp.where(jnp.isfinite(total), summed / scale, jnp.nan)


def limb2(index, values, n, bound=None):
    index, flat = _rows(index, values)
    total, scale = _scaled(flat, bound, 23)
    low_bits = 24 - max(flat.shape[0] - 1, 1).bit_length()  # E terms of |low| <= 2^(low_bits - 1) sum below 2^24
    high = jnp.round(flat * scale)
    low = jnp.round((flat * scale - high) * 2.0**low_bits)
    rows = jnp.zeros((n, flat.shape[-1]))
    # the barrier keeps XLA from merging the two scatters into one of high + low x 2^-L (then not exact)
    high, low = jax.lax.optimization_barrier((rows.at[index].add(high), rows.at[index].add(low)))
    return jnp.where(jnp.isfinite(total), (high + low * 2.0**-low_bits) / scale, jnp.nan)


def onehot(index, values, n, bound=None):
    index, flat = _rows(index, values)
    hot = (index[:, None] == jnp.arange(n)).astype(jnp.bfloat16)  # [E, n], exact in bfloat16
    parts, rest = [], flat
    for _ in range(3):  # three bfloat16 parts hold a float32's 24 bits
        parts.append(rest.astype(jnp.bfloat16))
        rest = rest - parts[-1].astype(jnp.float32)
    out = jax.lax.dot_general(hot, jnp.concatenate(parts, -1), (((0,), (0,)), ((), ())),
                              preferred_element_type=jnp.float32)
    c = flat.shape[-1]
    return (out[:, :c] + out[:, c:2 * c]) + out[:, 2 * c:]


def sorted32(index, values, n, bound=None, cap=32):
    index, flat = _rows(index, values)
    order = jnp.argsort(index, stable=True)
    start = jnp.searchsorted(index[order], jnp.arange(n), side="left")
    end = jnp.searchsorted(index[order], jnp.arange(n), side="right")
    slot = start[:, None] + jnp.arange(cap)
    rows = jnp.where(slot < end[:, None], order[jnp.minimum(slot, len(index) - 1)], len(index))  # [n, cap]
    return jnp.sum(jnp.concatenate([flat, jnp.zeros_like(flat[:1])])[rows], axis=1)


def int30pad(index, values, n, bound=None):
    """The library's sum into n + 1 rows, the last dropped (at bucket 64 the rows equal the 64 channels)."""
    return LIBRARY(index, values, n + 1, bound)[:n]


def int30barrier(index, values, n, bound=None):
    """The library's sum with its int32 scatter behind an optimization barrier, so that XLA cannot fold a later
    transpose into it (at bucket 64 it did: each update a strided column of the [n, C] sum, docs/repeat)."""
    index, flat = _rows(index, values)
    total, scale = _scaled(flat, bound, propagation.FIXED_POINT_BITS)
    terms = jnp.round(flat * scale).astype(jnp.int32)
    summed = jax.lax.optimization_barrier(jnp.zeros((n, flat.shape[-1]), jnp.int32).at[index].add(terms))
    return jnp.where(jnp.isfinite(total), summed.astype(jnp.float32) / scale, jnp.nan)


def int30t(index, values, n, bound=None):
    """The library's sum with the channels leading: each channel's rows summed as a [C, n] scatter."""
    index, flat = _rows(index, values)
    total = jnp.sum(jnp.abs(flat), axis=0) if bound is None else jnp.asarray(bound, jnp.float32)
    scale = jnp.ldexp(jnp.ones_like(total), jnp.minimum(propagation.FIXED_POINT_BITS - jnp.frexp(total)[1], 126))
    terms = jnp.round(flat * scale).astype(jnp.int32).T  # [C, E]
    summed = jnp.zeros((flat.shape[-1], n), jnp.int32).at[:, index].add(terms).T
    return jnp.where(jnp.isfinite(total), summed.astype(jnp.float32) / scale, jnp.nan)


def compare(index, values, n, bound=None):
    """Each output row sums the terms whose index matches it: a fused [E, n, C] reduction over E (no atomics)."""
    index, flat = _rows(index, values)
    return jnp.sum(jnp.where((index[:, None] == jnp.arange(n))[..., None], flat[:, None, :], 0.0), axis=0)


def senders_dense(neighbours, per_edge, n):
    """The senders' sum of a graph as ``graph.build_edges`` makes it (in row i every entry is i itself, a non-edge,
    or a sender j != i that no other entry of the row repeats): each row's edges laid out densely, [i, j] -> the
    entry of row i whose sender is j (or zero), then summed over the receivers i. A gather and a reduction."""
    k = neighbours.shape[1]
    rows = jnp.arange(n)
    own = neighbours == rows[:, None]  # [N, k]: self entries
    hit = (neighbours[:, :, None] == rows) & ~own[..., None]  # [N(i), k, N(j)]
    slot = jnp.sum(jnp.where(hit, jnp.arange(k)[:, None], 0), axis=1) + k * ~jnp.any(hit, axis=1)  # [N, N]
    padded = jnp.concatenate([per_edge, jnp.zeros_like(per_edge[:, :1])], axis=1)  # [N, k + 1, C]
    dense = jnp.take_along_axis(padded, slot[..., None], axis=1)  # [N(i), N(j), C]
    return jnp.sum(dense, axis=0) + jnp.sum(jnp.where(own[..., None], per_edge, 0.0), axis=1)


def _graph_or(other):
    """A sum that takes a graph's senders' sum (index [N, k] into N rows) to ``senders_dense``, others to other."""
    def add(index, values, n, bound=None):
        if index.ndim == 2 and index.shape[0] == n and values.ndim == 3:
            return senders_dense(index, jnp.asarray(values, jnp.float32), n)
        return other(index, values, n, bound)
    return add


def _dense_pair_bwd(pair, residuals, grad):
    """The propagation step's gradient with the pair table's edges recomputed densely over all N x N pairs: the
    senders' sum is a reduction over the receivers (no scatter, no gather); other graphs as the library's."""
    if not pair:
        return LIBRARY_BWD(pair, residuals, grad)
    constant, neighbours, edge_mask, node_terms, count = residuals
    n, h = node_terms.shape[0], node_terms.shape[-1] // 2
    adjacent = jnp.any((neighbours[:, :, None] == jnp.arange(n)) & edge_mask[..., None], axis=1)  # [N(i), N(j)]
    x = constant + node_terms[:, None, :h].astype(constant.dtype) + node_terms[None, :, h:].astype(constant.dtype)
    active = adjacent[..., None] & (x > 0)  # [N, N, H]
    grad_senders = jnp.sum(jnp.where(active, grad[:, None, :], 0.0), axis=0)
    grad_terms = jnp.concatenate([grad * count.astype(jnp.float32), grad_senders], axis=1)
    grad_constant = jnp.where(active, grad[:, None, :], 0.0).astype(constant.dtype)
    return grad_constant, None, None, grad_terms.astype(node_terms.dtype)


def _forward_value_and_grad(f, **_):
    """value_and_grad by forward mode: f's linearisation applied to each basis vector of its input (the planner's
    push sequence [T, 4]: 4T tangents, batched), so no gradient is ever summed by a scatter."""
    def value_and_grad(x):
        y, linear = jax.linearize(f, x)
        basis = jnp.eye(x.size, dtype=x.dtype).reshape((x.size,) + x.shape)
        return y, jax.vmap(linear)(basis).reshape(x.shape)
    return value_and_grad


def _plain_incoming(pair, constant, neighbours, edge_mask, node_terms):
    """``propagation.incoming_effects`` without its hand-written gradient (forward mode differentiates it)."""
    x = propagation._edge_input(pair, constant, neighbours, node_terms)
    return jnp.sum(jnp.where(edge_mask[..., None] & (x > 0), x, 0.0), axis=1, dtype=jnp.float32)


FORWARD = dict(incoming_effects=_plain_incoming, gather_rows=lambda x, index: x[index])


LIBRARY_BWD = propagation._incoming_bwd
VARIANTS = dict(float=plain_float, int30=LIBRARY, limb1=limb1, limb2=limb2, onehot=onehot, sorted32=sorted32,
                compare=compare, dense=_graph_or(compare), dense_int30=_graph_or(LIBRARY), densepair=compare,
                densepair_int30=LIBRARY, forward=LIBRARY, int30pad=int30pad,
                int30t=int30t, int30barrier=int30barrier)
PAIR_BWD = dict(densepair=_dense_pair_bwd, densepair_int30=_dense_pair_bwd)  # variants with their own gradient


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--dump", metavar="DIR", default=None)
    parser.add_argument("--slots", type=int, nargs="+", default=[32, 64, 100],
                        help="particle slots of the plans (the buckets; any size: 60 tells whether 64's layout is "
                             "the size's)")
    args = parser.parse_args()
    from benchmarks.bench_planner import PARTICLE_RADIUS, _camera_and_goal, _piles
    from benchmarks.bench_resolution import _ms_per_step
    from dynres_jax.control.decision import goal_cost
    from dynres_jax.control.planner import PlannerConfig, plan
    from dynres_jax.models.registry import SHIPPED_DYNAMICS, load_dynamics

    camera, goal = _camera_and_goal()
    dynamics = load_dynamics("auto", SHIPPED_DYNAMICS, 0.04)[0](PARTICLE_RADIUS)
    config = PlannerConfig(samples=50, resamples=30, adam_steps=args.steps)
    print(jax.devices()[0].device_kind, flush=True)
    from dynres_jax.control import objective
    from dynres_jax.models import dynamics as dynamics_module

    library = dict(gather_rows=propagation.gather_rows, incoming_effects=propagation.incoming_effects,
                   value_and_grad=jax.value_and_grad)
    for name in args.variants:
        forward = name == "forward"
        dynamics_module.incoming_effects = FORWARD["incoming_effects"] if forward else library["incoming_effects"]
        dynamics_module.gather_rows = objective.gather_rows = (FORWARD if forward else library)["gather_rows"]
        jax.value_and_grad = _forward_value_and_grad if forward else library["value_and_grad"]
        propagation.exact_scatter_add = VARIANTS[name]
        propagation.incoming_effects.defvjp(propagation._incoming_fwd, PAIR_BWD.get(name, LIBRARY_BWD))
        jax.clear_caches()
        for slots in args.slots:
            positions, mask = _piles(slots, 30, seed=slots), np.ones((30, slots), bool)
            cost = goal_cost(goal, camera, slots)
            ms = _ms_per_step(dynamics, cost, positions, mask, config, args.steps, 5)
            def run(cost=cost, positions=positions, mask=mask):
                return jax.block_until_ready(plan(dynamics, cost, positions, mask, jax.random.PRNGKey(3), config))

            a, b = run(), run()
            same = all(np.array_equal(x, y, equal_nan=True)
                       for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))
            print(f"{name:8s} bucket {slots:3d}: {ms:6.3f} ms per Adam step, two plans bit-identical: {same}, "
                  f"best c {float(a.best_cost):.4f}", flush=True)
            if args.profile and slots == 64:
                _profile(run, args.steps)
        if args.dump:
            _keep_scatters(args.dump, name)
    propagation.exact_scatter_add = LIBRARY
    dynamics_module.incoming_effects = library["incoming_effects"]
    dynamics_module.gather_rows = objective.gather_rows = library["gather_rows"]
    jax.value_and_grad = library["value_and_grad"]
    propagation.incoming_effects.defvjp(propagation._incoming_fwd, LIBRARY_BWD)


def _keep_scatters(out, variant):
    """From XLA's dump of the plans compiled since the last call: each module's scatter fusions (HLO) and their PTX
    kernels, as out/VARIANT.txt; the dump's files are then deleted."""
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, f"{variant}.txt"), "a") as f:
        for hlo in sorted(glob.glob(os.path.join(XLA_DUMP, "*after_optimizations.txt"))):
            text = open(hlo).read()
            f.write(f"==== {os.path.basename(hlo)}\n")
            for block in re.split(r"\n(?=\S)", text):  # computations, one a block
                if "scatter" in block.split("\n", 1)[0] or re.search(r"= \S+ scatter\(", block):
                    f.write(block + "\n")
            for line in text.splitlines():  # the calls of the fusions, with their shapes
                if "scatter" in line and "calls=" in line:
                    f.write("CALL " + line.strip() + "\n")
        for ptx in sorted(glob.glob(os.path.join(XLA_DUMP, "*.ptx"))):
            f.write(f"==== {os.path.basename(ptx)}\n")
            for entry in re.findall(r"\.entry [^(]*scatter[^(]*\(.*?\n}", open(ptx).read(), re.S):
                f.write(entry + "\n")
    shutil.rmtree(XLA_DUMP)
    os.makedirs(XLA_DUMP)


def _profile(run, steps):
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CUDA]) as trace:
        run()
    rows = sorted(((e.key, e.device_time_total / steps, e.count / steps) for e in trace.key_averages()),
                  key=lambda r: -r[1])
    for key, us, count in rows[:12]:
        print(f"    {us:8.1f} µs {count:4.0f}x  {key[:100]}")


if __name__ == "__main__":
    main()
