"""The particle graph of f(z, u, ω): the sweep heuristic (action -> guessed displacement) and radius + kNN edges.

Shapes are static: particles [N, 3] with a mask [N]; edges as neighbour indices [N, k] with an edge mask. Masked
particles are inert: they get no displacement, have no edges and are no one's neighbour, whatever their positions.
Units are metres; an action is (x_start, y_start, x_end, y_end) of the plate's centre line.

The k nearest neighbours come from the [N, N] distance matrix (``k_smallest``), except on CUDA GPUs for N <= 128,
where a Pallas (Triton) kernel computes a tile of the matrix in registers and picks from it (``knn_kernel``: the same
edges, 2.2x faster at the planner's batch); tests run the kernel in Pallas' interpreter, and ``no_gpu_kernels``
leaves it out of traces meant for other machines (``jax.export``).
"""

from __future__ import annotations

import contextlib
import functools

import jax
import jax.numpy as jnp

R_EDGE = 0.032  # m: the reference's 0.08 of its 1-unit bin, on our 0.4 m bin
K_NEIGHBOURS = 10  # the reference's k
SWEEP_END_OFFSET = 0.01  # m past the end line: the plate's half-thickness (5 mm) plus a typical piece radius
SWEEP_FALLOFF = 0.01  # m over which the sweep's effect fades to zero outside the band (about a piece's width)


def _smoothstep(x):
    """0 for x <= 0, 1 for x >= 1, 3x^2 - 2x^3 between: continuous with a continuous derivative."""
    x = jnp.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def push_geometry(action):
    """action [4] (x_start, y_start, x_end, y_end) m -> (start [2] m, unit direction [2], length [] m) as the model
    sees a push (float32; a zero-length push gets a finite, arbitrary direction): the sweep heuristic's and the
    dynamics model's push frame."""
    action = jnp.asarray(action, jnp.float32)
    start, delta = action[:2], action[2:] - action[:2]
    length = jnp.sqrt(jnp.sum(jnp.square(delta)) + 1e-12)
    return start, delta / length, length


def _sweep(particles, action, plate_half_width, end_offset, falloff):
    """The sweep's geometry: (gate [N] in [0, 1], distance left to the end line [N] (m, >= 0), unit direction [2])."""
    particles = jnp.asarray(particles, jnp.float32)
    start, along, length = push_geometry(action)
    side = jnp.stack([-along[1], along[0]])
    rel = particles[:, :2] - start
    s, t = rel @ along, rel @ side
    gate = _smoothstep((plate_half_width + falloff - jnp.abs(t)) / falloff) * _smoothstep((s + falloff) / falloff)
    return gate, jnp.maximum(length + end_offset - s, 0.0), along


def sweep_displacement(particles, mask, action, plate_half_width, *, end_offset=SWEEP_END_OFFSET,
                       falloff=SWEEP_FALLOFF):
    """Guessed displacement of each particle under a push. particles [N, 3] m, mask [N] bool, action [4]
    (x_start, y_start, x_end, y_end) m, plate_half_width m -> [N, 3] m (z component 0).

    With s the distance along the push from the start and t the signed sideways distance from the push line, a
    particle with s <= L + end_offset (L the push length) is moved along the push to s = L + end_offset, just past
    the plate at the end line, scaled by a sideways gate (1 for |t| <= plate_half_width, a smoothstep fall-off to 0 at
    |t| = plate_half_width + falloff) and a behind-the-start gate (1 for s >= 0, a smoothstep fall-off to 0 at
    s = -falloff); falloff must be > 0. Particles beyond the end line, far to the side or behind the start do not
    move; masked particles get zero. A zero-length push moves nothing; gradients in the action stay finite.
    """
    gate, left, along = _sweep(particles, action, plate_half_width, end_offset, falloff)
    push = jnp.where(mask, gate * left, 0.0)
    return jnp.concatenate([push[:, None] * along, jnp.zeros_like(push[:, None])], axis=-1)


SWEEP_REGIONS = ("swept", "band edge", "off the path")


def sweep_region(particles, action, plate_half_width):
    """Where each particle lies relative to a push, as the sweep heuristic sees it: particles [N, 3], action [4] (m)
    -> [N] int32 index into ``SWEEP_REGIONS``: 0 "swept", carried whole to the end line (gate 1); 1 "band edge", in
    the gate's fall-off at the band's sides or behind its start (0 < gate < 1); 2 "off the path", left where it is
    (gate 0, or already past the end line)."""
    gate, left, _ = _sweep(particles, action, plate_half_width, SWEEP_END_OFFSET, SWEEP_FALLOFF)
    moved = left > 0
    return jnp.where(moved & (gate >= 1), 0, jnp.where(moved & (gate > 0), 1, 2)).astype(jnp.int32)


def _smallest_by_top_k(d2, k):
    neg, index = jax.lax.top_k(-d2, k)
    return -neg, index


def _smallest_by_argmin(d2, k):
    values, indices = [], []
    for _ in range(k):
        index = jnp.argmin(d2, axis=-1)
        values.append(jnp.take_along_axis(d2, index[..., None], axis=-1)[..., 0])
        indices.append(index)
        d2 = jnp.where(jnp.arange(d2.shape[-1]) == index[..., None], jnp.inf, d2)
    return jnp.stack(values, -1), jnp.stack(indices, -1).astype(jnp.int32)


def k_smallest(d2, k: int):
    """(values, indices) [..., k] of the k smallest entries of each row of d2 [..., M] (k <= M), ascending, the lower
    index first on ties. Entries that are +inf may come back in any order (repeated indices included): callers mask
    them. lax.top_k on CPU; elsewhere k rounds of argmin, which XLA runs about 1.5x faster than its top_k on an H100
    for the planner's rows of 100 particles (and about 1.5x slower on CPU)."""
    return jax.lax.platform_dependent(d2, cpu=functools.partial(_smallest_by_top_k, k=k),
                                      default=functools.partial(_smallest_by_argmin, k=k))


KNN_KERNEL_MAX_PARTICLES = 128  # the kNN kernel holds a tile of a scene's [P, P] squared distances in registers
# Rows of the distance matrix per kernel program, and its warps: on an H100 at the planner's batch (1,500 scenes of
# 100 particles, k = 10) 8 rows on one warp take 0.26 ms, 16 rows on two 0.50, a whole scene on 8 warps 0.97, and
# k_smallest on the distance matrix 0.58 (scratch A/B of one session, docs/performance.md, "Planner speed").
KNN_ROWS, KNN_WARPS = 8, 1


def _knn_kernel(rows_ref, x_ref, y_ref, z_ref, mask_ref, row_x_ref, row_y_ref, row_z_ref, row_mask_ref, values_ref,
                index_ref, *, k: int):
    """R rows of one scene: their indices, coordinates and mask [R] against every particle's x, y, z, mask [P]
    (mask 1.0 valid) -> the k smallest squared distances of each row [R, K] and their columns [R, K] int32 (K >= k
    a power of two; slots past k are left +inf / 0). Row i excludes i itself and masked particles; ties go to the
    lower column; +inf entries repeat a column, as ``k_smallest``."""
    p = x_ref.shape[0]
    r = rows_ref.shape[0]
    cols = jax.lax.broadcasted_iota(jnp.int32, (r, p), 1)
    valid = (row_mask_ref[...] > 0.0)[:, None] & (mask_ref[...] > 0.0)[None, :] & (rows_ref[...][:, None] != cols)
    d2 = (jnp.square(row_x_ref[...][:, None] - x_ref[...][None, :])
          + jnp.square(row_y_ref[...][:, None] - y_ref[...][None, :])
          + jnp.square(row_z_ref[...][:, None] - z_ref[...][None, :]))
    d2 = jnp.where(valid, d2, jnp.inf)
    slots = jax.lax.broadcasted_iota(jnp.int32, values_ref.shape, 1)
    values = jnp.full(values_ref.shape, jnp.inf, jnp.float32)
    index = jnp.zeros(index_ref.shape, jnp.int32)
    for j in range(k):
        value = jnp.min(d2, axis=1)
        pick = jnp.min(jnp.where(d2 == value[:, None], cols, p), axis=1)
        values = jnp.where(slots == j, value[:, None], values)
        index = jnp.where(slots == j, pick[:, None], index)
        d2 = jnp.where(cols == pick[:, None], jnp.inf, d2)
    values_ref[...] = values
    index_ref[...] = index


def knn_kernel(positions, mask, k: int, *, interpret: bool = False, rows: int = KNN_ROWS, warps: int = KNN_WARPS):
    """The k nearest valid particles of each particle by a Pallas (Triton) kernel that keeps the distances in
    registers (a program per ``rows`` rows of a scene): positions [N, 3] m, mask [N] -> (squared distances [N, k],
    indices [N, k] int32), as ``k_smallest`` on the masked distance matrix. N <= KNN_KERNEL_MAX_PARTICLES, k <= N.
    Not differentiable (the positions pass through stop_gradient). interpret: Pallas' interpreter (for tests)."""
    from jax.experimental import pallas as pl

    n = positions.shape[0]
    if n > KNN_KERNEL_MAX_PARTICLES or k > n or rows < 1 or rows & (rows - 1):
        raise ValueError(f"knn_kernel takes k <= N <= {KNN_KERNEL_MAX_PARTICLES} and rows a power of two, got N = {n}, "
                         f"k = {k}, rows = {rows}")
    p, slots = max(16, 1 << (n - 1).bit_length()), max(16, 1 << (k - 1).bit_length())  # Triton: powers of two
    rows = min(rows, p)
    pad = lambda x: jnp.pad(x, (0, p - n))  # noqa: E731
    columns = [pad(c) for c in jax.lax.stop_gradient(jnp.asarray(positions, jnp.float32)).T]
    columns.append(pad(jnp.asarray(mask, jnp.float32)))
    params = None
    if not interpret:
        from jax.experimental.pallas import triton as plgpu

        params = plgpu.CompilerParams(num_warps=warps)
    whole, block = pl.BlockSpec((p,), lambda i: (0,)), pl.BlockSpec((rows,), lambda i: (i,))
    out = pl.BlockSpec((rows, slots), lambda i: (i, 0))
    values, index = pl.pallas_call(
        functools.partial(_knn_kernel, k=k), grid=(p // rows,), interpret=interpret, compiler_params=params,
        in_specs=[block] + [whole] * 4 + [block] * 4, out_specs=(out, out),
        out_shape=(jax.ShapeDtypeStruct((p, slots), jnp.float32), jax.ShapeDtypeStruct((p, slots), jnp.int32)),
    )(jnp.arange(p, dtype=jnp.int32), *columns, *columns)
    return values[:n, :k], index[:n, :k]


def nearest_by_matrix(positions, mask, k: int):
    """(squared distances, indices) [N, k] of each particle's k nearest valid others (k <= N), ascending:
    ``k_smallest`` of the masked [N, N] distance matrix."""
    n = positions.shape[0]
    d2 = jnp.sum(jnp.square(positions[:, None, :] - positions[None, :, :]), axis=-1)
    allowed = mask[:, None] & mask[None, :] & ~jnp.eye(n, dtype=bool)
    return k_smallest(jnp.where(allowed, d2, jnp.inf), k)


_GPU_KERNELS = [True]  # whether traces may use knn_kernel on CUDA; ``no_gpu_kernels`` clears it


@contextlib.contextmanager
def no_gpu_kernels():
    """Within it, new traces leave the Pallas kNN kernel out (the same edges, from the distance matrix): for
    ``jax.export``, which lowers for platforms the machine may lack (Pallas lowers for CUDA only on a CUDA machine)."""
    _GPU_KERNELS.append(False)
    try:
        yield
    finally:
        _GPU_KERNELS.pop()


def _nearest(positions, mask, k: int, kernel: bool):
    """``nearest_by_matrix``, by the kNN kernel on CUDA GPUs when ``kernel`` (up to KNN_KERNEL_MAX_PARTICLES
    particles)."""
    if not kernel or positions.shape[0] > KNN_KERNEL_MAX_PARTICLES:
        return nearest_by_matrix(positions, mask, k)
    return jax.lax.platform_dependent(positions, mask, cuda=functools.partial(knn_kernel, k=k),
                                      default=functools.partial(nearest_by_matrix, k=k))


def build_edges(positions, mask, radius=R_EDGE, k: int = K_NEIGHBOURS):
    """Radius + kNN edges. positions [N, 3] m (the guessed, swept positions), mask [N] bool, radius m, k static ->
    (neighbours [N, k] int32, edge_mask [N, k] bool).

    Edge j -> i (j in row i) when i and j are valid, j != i, |p_i - p_j| < radius and j is among i's k nearest valid
    particles. Rows are sorted by distance (nearest first; lowest index on ties); an entry without an edge holds i
    itself, so gathers stay in range. k may exceed N - 1: the extra entries are empty.
    """
    return _build_edges(positions, mask, radius, k, _GPU_KERNELS[-1])  # the kernel switch is a static argument


@functools.partial(jax.jit, static_argnames=("k", "kernel"))
def _build_edges(positions, mask, radius, k: int, kernel: bool):
    positions = jnp.asarray(positions, jnp.float32)
    n = positions.shape[0]
    nearest_d2, neighbours = _nearest(positions, mask, min(k, n), kernel)
    edge_mask = nearest_d2 < jnp.square(radius)
    neighbours = jnp.where(edge_mask, neighbours, jnp.arange(n)[:, None]).astype(jnp.int32)
    if k > n:
        neighbours = jnp.concatenate([neighbours, jnp.broadcast_to(jnp.arange(n)[:, None], (n, k - n))], axis=1)
        edge_mask = jnp.concatenate([edge_mask, jnp.zeros((n, k - n), bool)], axis=1)
    return neighbours, edge_mask


def sweep_rollout(positions, mask, actions, plate_half_width):
    """The sweep heuristic alone as a dynamics model: positions [N, 3], mask [N], actions [T, 4] (m) -> positions
    [T, N, 3] after each push. A baseline for the learned f, and the planner's model before one is trained."""

    def step(p, a):
        p = p + sweep_displacement(p, mask, a, plate_half_width)
        return p, p

    return jax.lax.scan(step, positions, actions)[1]
