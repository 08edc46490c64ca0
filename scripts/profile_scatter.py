"""Ways to sum a gather's gradient that repeat bit for bit, timed in the planner (issue 67; docs/repeat, "Sums without
int32 atomics"). Each variant replaces ``models.propagation.exact_scatter_add`` for one pass; the planner runs the
shipped model on 1,500 candidates (50 pushes x 30 re-samplings) at the buckets 32, 64 and 100, and two plans of the
same inputs are compared bit for bit.

    PYTHONPATH=. python scripts/profile_scatter.py [VARIANT ...] [--steps 100] [--profile]

Variants: float (a plain float scatter-add: the speed to beat; does not repeat), int30 (the library's: 30-bit fixed
point summed as int32), limb1 (24-bit fixed point as integer-valued float32: float atomics add it exactly), limb2
(two such limbs, 38 bits, one scatter each), onehot (a one-hot matrix product, bf16 x 3), sorted32 (each row's
terms gathered through a sort, at most 32 a row). ``--profile`` prints the 12 slowest kernels at bucket 64 (through
torch.profiler, on a GPU). Prints ms per Adam step, whether two plans are bit-identical, and the variant's best cost.
"""

import argparse
import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # torch's profiler shares the GPU

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


VARIANTS = dict(float=plain_float, int30=LIBRARY, limb1=limb1, limb2=limb2, onehot=onehot, sorted32=sorted32)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--profile", action="store_true")
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
    for name in args.variants:
        propagation.exact_scatter_add = VARIANTS[name]
        jax.clear_caches()
        for slots in (32, 64, 100):
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
    propagation.exact_scatter_add = LIBRARY


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
