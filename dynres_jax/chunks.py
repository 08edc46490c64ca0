"""Batches computed in chunks of a fixed size, so that an episode's result does not depend on how many run beside it.

XLA compiles a batched function per batch shape and may round differently for each (another matrix-product tiling,
another reduction order): the same episode rendered or decided beside 1 or 4 others came out different on a CPU
(2026-11-28: depth pixels, then the planner's costs by 1e-6 relative, which the closed loop amplifies), and on a GPU
evaluate's first 32 of 256 episodes ended up to 0.9 px apart from the same 32 alone. ``in_chunks`` runs a batched
function on ``chunk_size()`` episodes at a time, always the same compiled shape, the last chunk padded with copies of
its first episode: on a CPU one episode at a time (as a run of one decides), on a GPU ``GPU_CHUNK`` at a time.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

GPU_CHUNK = 64  # episodes a batched function runs at once on an accelerator


def chunk_size() -> int:
    """Episodes a chunk holds on this process's default JAX backend: 1 on a CPU, ``GPU_CHUNK`` elsewhere."""
    return 1 if jax.default_backend() == "cpu" else GPU_CHUNK


def in_chunks(fn: Callable, *args, size: int | None = None):
    """fn(*args) for args with a leading episode axis [B] (pytrees; every leaf [B, ...]), computed ``size`` episodes at
    a time (default ``chunk_size()``; the last chunk padded with copies of its first episode, dropped after): fn's
    output, its leaves [B, ...]. fn must treat episodes independently (a vmapped function)."""
    size = chunk_size() if size is None else int(size)
    if size < 1:
        raise ValueError(f"a chunk holds at least one episode, got {size}")
    b = len(jax.tree.leaves(args)[0])
    outs = []
    for start in range(0, b, size):
        n = min(size, b - start)

        def take(x, start=start, n=n):
            part = x[start:start + n]
            if n == size:
                return part
            return jnp.concatenate([part, jnp.repeat(part[:1], size - n, axis=0)])

        outs.append((n, fn(*jax.tree.map(take, args))))
    if len(outs) == 1:
        n, out = outs[0]
        return out if n == size else jax.tree.map(lambda x: x[:n], out)
    return jax.tree.map(lambda *xs: jnp.concatenate([x[:n] for (n, _), x in zip(outs, xs, strict=True)]),
                        *[out for _, out in outs])


__all__ = ["GPU_CHUNK", "chunk_size", "in_chunks"]
