"""The particle graph: radius + kNN edges against a brute-force NumPy version, the sweep heuristic, masks inert."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dynres_jax.models.graph import (
    SWEEP_END_OFFSET,
    SWEEP_FALLOFF,
    SWEEP_REGIONS,
    _smallest_by_argmin,
    _smallest_by_top_k,
    build_edges,
    k_smallest,
    knn_kernel,
    nearest_by_matrix,
    sweep_displacement,
    sweep_region,
)

PLATE = 0.04


def brute_force_edges(positions, mask, radius, k):
    """Set of (i, j): j != i both valid, |p_i - p_j| < radius, j among i's k nearest valid (lowest index on ties)."""
    positions = np.asarray(positions, np.float32)
    edges = set()
    for i in range(len(positions)):
        if not mask[i]:
            continue
        candidates = []
        for j in range(len(positions)):
            if j != i and mask[j]:
                candidates.append((float(np.sum(np.square(positions[i] - positions[j]))), j))
        for d2, j in sorted(candidates)[:k]:
            if d2 < np.float32(radius) ** 2:
                edges.add((i, j))
    return edges


def edge_set(neighbours, edge_mask):
    neighbours, edge_mask = np.asarray(neighbours), np.asarray(edge_mask)
    return {(i, int(neighbours[i, c])) for i, c in zip(*np.nonzero(edge_mask), strict=True)}


def random_particles(seed, n=60, invalid_fraction=0.25):
    rng = np.random.default_rng(seed)
    positions = np.concatenate([rng.uniform(-0.1, 0.1, (n, 2)), rng.uniform(0.005, 0.01, (n, 1))], 1)
    return positions.astype(np.float32), rng.uniform(size=n) > invalid_fraction


# ----------------------------------------------------------------------------------------------------------------
# Edges
# ----------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed,radius,k", [(0, 0.032, 10), (1, 0.05, 4), (2, 0.02, 10), (3, 1.0, 70)])
def test_edges_match_brute_force(seed, radius, k):
    positions, mask = random_particles(seed)
    neighbours, edge_mask = build_edges(positions, mask, radius, k)
    assert neighbours.shape == (60, k) and edge_mask.shape == (60, k) and neighbours.dtype == jnp.int32
    expected = brute_force_edges(positions, mask, radius, k)
    assert len(expected) > 0
    assert edge_set(neighbours, edge_mask) == expected
    # rows nearest first; entries without an edge hold the receiver itself
    d = np.linalg.norm(positions[:, None] - positions[np.asarray(neighbours)], axis=-1)
    assert np.all(np.diff(np.where(np.asarray(edge_mask), d, 1e9), axis=1) >= 0)
    np.testing.assert_array_equal(np.asarray(neighbours)[~np.asarray(edge_mask)],
                                  np.nonzero(~np.asarray(edge_mask))[0])


@pytest.mark.parametrize("smallest", [_smallest_by_top_k, _smallest_by_argmin, k_smallest])
def test_k_smallest_matches_a_stable_sort(smallest):
    """Both ways of taking the k smallest (lax.top_k on CPU, argmin rounds elsewhere) and the dispatcher return a
    stable NumPy sort's first k (ascending, lower index first on ties), rows with +inf entries included, vmapped."""
    rng = np.random.default_rng(0)
    d2 = rng.integers(0, 6, (5, 7, 12)).astype(np.float32)  # small integers: many ties
    d2[:, :, 3] = np.inf
    d2[0, 0, :] = np.inf  # a row with nothing allowed
    values, index = jax.vmap(lambda x: smallest(x, k=4))(d2)
    expect = np.argsort(d2, axis=-1, kind="stable")[..., :4]
    finite = np.isfinite(np.take_along_axis(d2, expect, -1))
    np.testing.assert_array_equal(np.asarray(index)[finite], expect[finite])
    np.testing.assert_array_equal(np.asarray(values), np.take_along_axis(d2, expect, -1))
    assert np.asarray(index).dtype == np.int32


@pytest.mark.parametrize("n, k, rows", [(60, 10, 8), (100, 10, 16), (17, 3, 128)])
def test_knn_kernel_equals_the_distance_matrix_way(n, k, rows):
    """The GPU's kNN kernel (run in Pallas' interpreter) picks what k_smallest picks on the masked distance matrix,
    vmapped over scenes: one with a duplicated particle (a tie), one with every particle masked, row tiles of
    several sizes; gradients through it are zero, not an error."""
    scenes = [random_particles(s, n) for s in range(3)]
    positions, mask = (np.stack(x) for x in zip(*scenes, strict=True))
    positions[0, 3] = positions[0, 5]
    mask[0, [3, 5]] = True
    mask[1] = False
    got = jax.vmap(lambda p, m: knn_kernel(p, m, k, interpret=True, rows=rows))(positions, mask)
    want = jax.vmap(lambda p, m: nearest_by_matrix(p, m, k))(positions, mask)
    finite = np.isfinite(np.asarray(want[0]))
    np.testing.assert_allclose(np.asarray(got[0]), np.asarray(want[0]), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(got[1])[finite], np.asarray(want[1])[finite])
    grad = jax.grad(lambda p: jnp.sum(knn_kernel(p, mask[2], k, interpret=True)[0]))(jnp.asarray(positions[2]))
    assert np.all(np.asarray(grad) == 0)
    with pytest.raises(ValueError, match="knn_kernel takes"):
        knn_kernel(np.zeros((200, 3), np.float32), np.ones(200, bool), k)


def test_edges_padding_inert():
    positions, mask = random_particles(4)
    garbage = np.where(mask[:, None], positions, np.float32(3e5)).astype(np.float32)
    garbage[~mask, 0] = np.linspace(-1e4, 1e4, (~mask).sum())  # masked particles anywhere, even on top of others
    garbage[np.flatnonzero(~mask)[0]] = positions[np.flatnonzero(mask)[0]]
    for a, b in zip(build_edges(positions, mask, 0.04, 10), build_edges(garbage, mask, 0.04, 10), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    neighbours, edge_mask = build_edges(garbage, mask, 0.04, 10)
    assert not np.asarray(edge_mask)[~mask].any()
    assert not np.isin(np.asarray(neighbours)[np.asarray(edge_mask)], np.flatnonzero(~mask)).any()


def test_edges_vmap_over_scenes_equals_loop():
    scenes = [random_particles(s) for s in range(3)]
    positions, mask = (jnp.stack(x) for x in zip(*scenes, strict=True))
    batched = jax.vmap(lambda p, m: build_edges(p, m, 0.04, 8))(positions, mask)
    for i, (p, m) in enumerate(scenes):
        for a, b in zip(build_edges(p, m, 0.04, 8), batched, strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b)[i])


# ----------------------------------------------------------------------------------------------------------------
# Sweep heuristic
# ----------------------------------------------------------------------------------------------------------------
def along_side(positions, action):
    """(s, t): distance along the push from its start and sideways from its line, for positions [N, 3]."""
    start, end = np.asarray(action[:2]), np.asarray(action[2:])
    along = (end - start) / np.linalg.norm(end - start)
    side = np.array([-along[1], along[0]])
    rel = np.asarray(positions)[:, :2] - start
    return rel @ along, rel @ side


@pytest.mark.parametrize("action", [(-0.1, 0.02, 0.08, 0.02), (0.05, 0.1, -0.03, -0.05)])
def test_sweep_moves_the_band_past_the_end_line(action):
    action = np.array(action, np.float32)
    rng = np.random.default_rng(0)
    positions = np.concatenate([rng.uniform(-0.19, 0.19, (400, 2)), np.full((400, 1), 0.007)], 1).astype(np.float32)
    mask = rng.uniform(size=400) > 0.1
    disp = np.asarray(sweep_displacement(positions, mask, action, PLATE))
    length = np.linalg.norm(action[2:] - action[:2])
    s, t = along_side(positions, action)
    s_new, t_new = along_side(positions + disp, action)
    band = mask & (s >= 0) & (s <= length) & (np.abs(t) <= PLATE)
    assert band.sum() > 10
    np.testing.assert_allclose(s_new[band], length + SWEEP_END_OFFSET, atol=1e-5)  # just past the end line
    np.testing.assert_allclose(t_new, t, atol=1e-5)  # nothing moves sideways
    far = (np.abs(t) >= PLATE + SWEEP_FALLOFF) | (s <= -SWEEP_FALLOFF) | (s >= length + SWEEP_END_OFFSET)
    assert far.sum() > 100 and np.all(disp[far] == 0)
    assert np.all(disp[~mask] == 0) and np.all(disp[:, 2] == 0)
    # soft fall-off: partial moves only in the fringe, never past the end line
    fringe = mask & ~band & ~far
    assert np.all(s_new[fringe] <= length + SWEEP_END_OFFSET + 1e-5) and np.all(s_new >= s - 1e-6)


def test_sweep_region_against_the_band_by_loops():
    action = np.array([0.05, 0.1, -0.03, -0.05], np.float32)
    rng = np.random.default_rng(1)
    positions = np.concatenate([rng.uniform(-0.19, 0.19, (2000, 2)), np.full((2000, 1), 0.007)], 1).astype(np.float32)
    region = np.asarray(sweep_region(positions, action, PLATE))
    length = np.linalg.norm(action[2:] - action[:2])
    expected = []
    for s, t in zip(*along_side(positions, action), strict=True):
        before_end = s < length + SWEEP_END_OFFSET
        if before_end and s >= 0 and abs(t) <= PLATE:
            expected.append("swept")
        elif before_end and s > -SWEEP_FALLOFF and abs(t) < PLATE + SWEEP_FALLOFF:
            expected.append("band edge")
        else:
            expected.append("off the path")
    assert [SWEEP_REGIONS[r] for r in region] == expected
    assert min(expected.count(name) for name in SWEEP_REGIONS) > 20
    # the heuristic moves "swept" particles to the end line, "band edge" ones part of the way, the rest not at all
    disp = np.linalg.norm(np.asarray(sweep_displacement(positions, np.ones(2000, bool), action, PLATE)), axis=1)
    full = length + SWEEP_END_OFFSET - along_side(positions, action)[0]
    np.testing.assert_allclose(disp[region == 0], full[region == 0], atol=1e-5)
    assert np.all(disp[region == 2] == 0) and np.all(disp[region == 1] < full[region == 1])


def test_sweep_fall_off_is_monotone_sideways():
    action = jnp.array([0.0, 0.0, 0.1, 0.0])
    t = np.linspace(0, PLATE + 2 * SWEEP_FALLOFF, 50)
    positions = np.stack([np.full_like(t, 0.05), t, np.zeros_like(t)], 1)
    push = np.asarray(sweep_displacement(positions, np.ones(50, bool), action, PLATE))[:, 0]
    assert np.all(np.diff(push) <= 1e-7) and push[0] == pytest.approx(0.05 + SWEEP_END_OFFSET, abs=1e-6)
    assert push[-1] == 0


def test_sweep_padding_inert_and_gradients_finite():
    positions, mask = random_particles(5)
    action = jnp.array([-0.05, 0.0, 0.05, 0.01])
    garbage = np.where(mask[:, None], positions, np.float32(-7e4)).astype(np.float32)
    a = np.asarray(sweep_displacement(positions, mask, action, PLATE))
    b = np.asarray(sweep_displacement(garbage, mask, action, PLATE))
    np.testing.assert_array_equal(a, b)
    assert np.all(a[~mask] == 0) and np.any(a[mask] != 0)
    for act in (action, jnp.array([0.02, 0.02, 0.02, 0.02])):  # a zero-length push moves nothing
        grad = jax.jit(jax.grad(lambda u: jnp.sum(sweep_displacement(positions, mask, u, PLATE) ** 2)))(act)
        assert np.all(np.isfinite(np.asarray(grad)))
    assert np.all(np.asarray(sweep_displacement(positions, mask, jnp.full(4, 0.02), PLATE)) == 0)
