"""Objective: goal masks, SDF, bilinear lookup, c against a loop-based NumPy reference, gradients, padding, vmap,
distribution distance d on a rendered observation, inside share, bad input."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dynres_jax.config import CameraConfig, SceneConfig, SimConfig
from dynres_jax.control import goals as goals_module
from dynres_jax.control import objective as obj
from dynres_jax.control.goals import (
    disc_goal,
    make_goal,
    make_goals,
    polygon_goal,
    random_polygon_goal,
    signed_distance,
    sort_goals,
    text_goal,
    with_objective,
)
from dynres_jax.control.objective import bilinear, distribution_distance, inside_share, squared_distance_to
from dynres_jax.perception import foreground
from dynres_jax.sim.camera import Camera
from dynres_jax.sim.env import PileEnv

CAM = Camera.top_down(CameraConfig())
PIXEL_M = 2 * CameraConfig().view_half_width / CameraConfig().width  # metres per pixel on the table


@pytest.fixture(scope="module")
def disc():
    return make_goal(disc_goal(CAM, (0.03, -0.02), 0.06), CAM)


# ----------------------------------------------------------------------------------------------------------------
# NumPy references
# ----------------------------------------------------------------------------------------------------------------
def np_project(camera, points):
    """World points [N, 3] -> pixel coordinates [N, 2], pinhole formula written out."""
    p_cam = (np.asarray(points, np.float64) - camera.centre) @ camera.rotation
    return p_cam[:, :2] / p_cam[:, 2:] * np.diag(camera.K)[:2] + camera.K[:2, 2]


def np_bilinear(image, u, v):
    H, W = image.shape
    x, y = min(max(u - 0.5, 0), W - 1), min(max(v - 0.5, 0), H - 1)
    j, i = min(int(np.floor(x)), W - 2), min(int(np.floor(y)), H - 2)
    fx, fy = x - j, y - i
    return ((1 - fy) * ((1 - fx) * image[i, j] + fx * image[i, j + 1])
            + fy * ((1 - fx) * image[i + 1, j] + fx * image[i + 1, j + 1]))


def np_cost(pixels, goal, hinge=False):
    """The formula by loops: pixels [ω, 2] of the valid points; hinge: the SDF clipped at 0 before its lookup."""
    distance, samples = np.asarray(goal.distance, np.float64), np.asarray(goal.samples, np.float64)
    distance = np.maximum(distance, 0.0) if hinge else distance
    omega = len(pixels)
    n_active = min(5 * omega, int(np.sum(goal.sample_mask)))
    sdf_term = sum(np_bilinear(distance, u, v) for u, v in pixels)
    coverage = 0.0
    for q in samples[:n_active]:
        coverage += min(np.hypot(*(p - q)) for p in pixels)
    return (sdf_term + coverage) / omega


def random_particles(seed, n=12, omega=8, spread=0.08):
    rng = np.random.default_rng(seed)
    pos = np.concatenate([rng.uniform(-spread, spread, (n, 2)), rng.uniform(0.004, 0.01, (n, 1))], 1)
    return pos.astype(np.float32), np.arange(n) < omega


# ----------------------------------------------------------------------------------------------------------------
# Goal masks
# ----------------------------------------------------------------------------------------------------------------
def test_disc_pixel_count_matches_area():
    for centre, r in [((0.0, 0.0), 0.05), ((0.1, -0.08), 0.08), ((-0.12, 0.1), 0.03)]:
        mask = disc_goal(CAM, centre, r)
        assert mask.shape == (CAM.height, CAM.width) and mask.dtype == bool
        assert abs(mask.sum() / (np.pi * r**2 / PIXEL_M**2) - 1) < 0.05


def test_text_goal_inside_image_at_its_size():
    mask = text_goal(CAM, "T", (0.02, -0.03), 0.15)
    assert mask.sum() > 0
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    assert rows[0] > 0 and cols[0] > 0 and rows[-1] < CAM.height - 1 and cols[-1] < CAM.width - 1
    assert abs((rows[-1] - rows[0] + 1) * PIXEL_M - 0.15) < 2 * PIXEL_M
    # the bar of the T is at the top of the image (rows run along -y): the top row is wider than the bottom row
    assert mask[rows[0]].sum() > 2 * mask[rows[-1]].sum()
    centre_uv = np_project(CAM, [[0.02, -0.03, 0.0]])[0]
    assert abs((rows[0] + rows[-1] + 1) / 2 - centre_uv[1]) < 1.5
    assert abs((cols[0] + cols[-1] + 1) / 2 - centre_uv[0]) < 1.5
    for text in ["J", "U", "42", "ab"]:
        assert text_goal(CAM, text, (0.0, 0.0), 0.1).sum() > 0


def test_text_goal_too_tall_fails_before_it_is_drawn(monkeypatch):
    """Text taller than the bin fails before OpenCV draws it (drawing large text costs most), yet that early check
    refuses nothing whose ink fits: the tallest "I" that fits is the bin's width to within a canvas pixel."""
    drawn = []
    put_text = cv2.putText
    monkeypatch.setattr(goals_module.cv2, "putText", lambda *a, **k: drawn.append(1) or put_text(*a, **k))
    with pytest.raises(ValueError, match="outside the bin"):
        text_goal(CAM, "I", (0.0, 0.0), 2.5 * goals_module.BIN_HALF_WIDTH)
    assert not drawn

    def fits(height):
        try:
            return text_goal(CAM, "I", (0.0, 0.0), height).any()
        except ValueError:
            return False
    lo, hi = 0.1, 0.5
    while hi - lo > 1e-5:
        lo, hi = ((lo + hi) / 2, hi) if fits((lo + hi) / 2) else (lo, (lo + hi) / 2)
    assert drawn and abs(lo - 2 * goals_module.BIN_HALF_WIDTH) < PIXEL_M / goals_module.TEXT_OVERSAMPLE


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_polygon_goal_matches_point_in_polygon(seed):
    rng = np.random.default_rng(seed)
    n = 6
    angle = np.sort(rng.uniform(0, 2 * np.pi, n))
    vertices = rng.uniform(-0.05, 0.05, 2) + rng.uniform(0.03, 0.12, n)[:, None] * np.stack(
        [np.cos(angle), np.sin(angle)], -1)
    mask = polygon_goal(CAM, vertices)
    contour = np_project(CAM, np.concatenate([vertices, np.zeros((n, 1))], 1)).astype(np.float32)
    centres = CAM.pixel_centres()
    ref = np.array([[cv2.pointPolygonTest(contour, (float(u), float(v)), False) >= 0 for u, v in row]
                    for row in centres])
    np.testing.assert_array_equal(mask, ref)


def test_random_polygon_and_sort_goals():
    rng = np.random.default_rng(3)
    for _ in range(5):
        assert random_polygon_goal(rng, CAM).sum() > 0
    goals = sort_goals(CAM, [[-0.1, 0.0], [0.1, 0.05]], 0.05)
    assert goals.shape == (2, CAM.height, CAM.width)
    assert goals[0].sum() > 0 and goals[1].sum() > 0 and not np.any(goals[0] & goals[1])


# ----------------------------------------------------------------------------------------------------------------
# Goal: SDF and samples
# ----------------------------------------------------------------------------------------------------------------
def test_sdf_sign_and_magnitude():
    mask = text_goal(CAM, "U", (0.0, 0.0), 0.12)
    goal = make_goal(mask, CAM)
    sdf = np.asarray(goal.distance)
    assert np.all(sdf[mask] < 0) and np.all(sdf[~mask] > 0)
    rng = np.random.default_rng(0)
    inside, outside = np.argwhere(mask), np.argwhere(~mask)
    for i, j in np.concatenate([inside[rng.choice(len(inside), 5)], outside[rng.choice(len(outside), 5)]]):
        other = outside if mask[i, j] else inside
        brute = np.min(np.hypot(*(other - [i, j]).T))
        assert abs(abs(sdf[i, j]) - brute) <= 1.0


def test_signed_distance_is_opencvs_exact_transform():
    """The goal's distance field, pure JAX (so it runs inside an exported decision), against OpenCV's exact Euclidean
    transform (DIST_MASK_PRECISE) of the mask and its complement: masks touching the border, thin ones, random ones."""
    rng = np.random.default_rng(4)
    masks = [text_goal(CAM, "S", (0.0, 0.0), 0.2), np.eye(40, 56, 3, dtype=bool), np.ones((9, 13), bool)]
    masks[2][4, 6] = False
    masks += [rng.uniform(size=tuple(rng.integers(3, 60, 2))) < rng.uniform(0.05, 0.95) for _ in range(8)]
    for mask in masks:
        u8 = mask.astype(np.uint8)
        reference = (cv2.distanceTransform(1 - u8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
                     - cv2.distanceTransform(u8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE))
        np.testing.assert_allclose(np.asarray(signed_distance(mask)), reference, rtol=2e-7, atol=1e-6)  # an ulp


def test_goal_samples_are_goal_pixels(disc):
    mask = np.asarray(disc.mask)
    n = int(mask.sum())
    samples = np.asarray(disc.samples)
    assert samples.shape == (500, 2) and int(disc.sample_mask.sum()) == min(500, n)
    assert np.all(mask[(samples[:, 1] - 0.5).astype(int), (samples[:, 0] - 0.5).astype(int)])
    assert len({tuple(s) for s in samples[: min(500, n)]}) == min(500, n)  # distinct until the goal is used up


def test_make_goals_equals_make_goal_one_by_one(monkeypatch):
    """The batched Goals (vectorised GOAL_BATCH masks at a time, here 2 for 5: a remainder) equal the one-by-one
    Goals leaf for leaf; a bad mask is named by its index before any work."""
    monkeypatch.setattr(goals_module, "GOAL_BATCH", 2)
    masks = [disc_goal(CAM, (0.0, 0.0), 0.05), disc_goal(CAM, (0.05, -0.03), 0.03)]
    masks += [text_goal(CAM, letter, (0.0, 0.01), 0.1) for letter in "JTU"]
    batch = make_goals(np.stack(masks), CAM, n_samples=64)
    assert batch.distance.shape == (5, CAM.height, CAM.width)
    for i, mask in enumerate(masks):
        for one, many in zip(make_goal(mask, CAM, n_samples=64), batch, strict=True):
            np.testing.assert_array_equal(np.asarray(many[i]), np.asarray(one))
    assert not np.array_equal(np.asarray(batch.distance[0]), np.asarray(batch.distance[1]))
    with pytest.raises(ValueError, match="goal mask 1 covers no pixel"):
        make_goals(np.stack([masks[0], np.zeros_like(masks[0])]), CAM)
    with pytest.raises(ValueError, match=r"\[B >= 1, H, W\]"):
        make_goals(masks[0], CAM)


# ----------------------------------------------------------------------------------------------------------------
# Bilinear lookup, c, gradients
# ----------------------------------------------------------------------------------------------------------------
def test_bilinear_matches_numpy(disc):
    rng = np.random.default_rng(1)
    uv = rng.uniform(-3, CAM.width + 3, (200, 2)).astype(np.float32)
    got = np.asarray(bilinear(disc.distance, jnp.asarray(uv)))
    ref = [np_bilinear(np.asarray(disc.distance, np.float64), u, v) for u, v in uv]
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("seed,omega", [(0, 8), (1, 3), (2, 12)])
def test_objective_matches_loop_reference(disc, seed, omega):
    pos, mask = random_particles(seed, omega=omega)
    got = float(obj.objective(pos, mask, disc, CAM))
    np.testing.assert_allclose(got, np_cost(np_project(CAM, pos[mask]), disc), rtol=1e-5)


@pytest.mark.parametrize("seed,omega", [(0, 8), (2, 12)])
def test_hinge_objective_matches_loop_reference_and_costs_only_particles_outside(disc, seed, omega):
    """c on a hinged goal (``with_objective``) is the loop formula with the SDF clipped at 0; the mask and samples are
    the goal's own; particles all inside the goal cost their coverage alone, where the paper's c rewards their depth."""
    hinge = with_objective(disc, "hinge")
    assert with_objective(disc, "paper") is disc
    for a, b in ((hinge.mask, disc.mask), (hinge.samples, disc.samples), (hinge.sample_mask, disc.sample_mask)):
        np.testing.assert_array_equal(a, b)
    pos, mask = random_particles(seed, omega=omega)
    pixels = np_project(CAM, pos[mask])
    np.testing.assert_allclose(float(obj.objective(pos, mask, hinge, CAM)), np_cost(pixels, disc, hinge=True),
                               rtol=1e-5)
    inside, _ = random_particles(seed, omega=omega, spread=0.02)
    inside[:, :2] += np.array([0.03, -0.02], np.float32)  # within 2.9 cm of the disc's centre, radius 6 cm
    paper, hinged = (float(obj.objective(inside, mask, g, CAM)) for g in (disc, hinge))
    coverage = np_cost(np_project(CAM, inside[mask]), disc, hinge=True)  # its SDF term is 0 inside
    np.testing.assert_allclose(hinged, coverage, rtol=1e-5)
    assert paper < hinged - 5  # the paper's SDF term is negative there: several pixels deep on average
    with pytest.raises(ValueError, match="objective must be one of"):
        with_objective(disc, "hinged")


def test_objective_truncates_goal_samples():
    """With 5 ω < Q only the first 5 ω samples count: a goal with Q = 40 samples and ω = 2 uses 10."""
    goal = make_goal(disc_goal(CAM, (0.0, 0.0), 0.04), CAM, n_samples=40)
    pos, mask = random_particles(4, n=5, omega=2)
    np.testing.assert_allclose(float(obj.objective(pos, mask, goal, CAM)),
                               np_cost(np_project(CAM, pos[mask]), goal), rtol=1e-5)


def test_gradient_matches_finite_differences():
    """Central differences with a small step, particles at sub-pixel offsets away from pixel centres (where the
    bilinear SDF has kinks) and few goal samples (each switch of a sample's nearest particle is a kink too)."""
    goal = make_goal(disc_goal(CAM, (0.03, -0.02), 0.06), CAM, n_samples=40)
    rng = np.random.default_rng(5)
    n, omega = 10, 7
    uv = rng.integers(40, 90, (n, 2)) + rng.uniform(0.6, 0.9, (n, 2))
    pos = np.asarray(CAM.pixel_to_world(uv, np.full(n, CAM.centre[2] - 0.006)), np.float32)
    mask = np.arange(n) < omega
    grad = np.asarray(jax.grad(obj.objective)(pos, mask, goal, CAM))
    assert np.all(np.isfinite(grad)) and np.all(grad[~mask] == 0)
    eps = 2e-5  # m: 0.006 pixel
    for k in range(omega):
        for a in range(2):
            step = np.zeros_like(pos)
            step[k, a] = eps
            fd = (float(obj.objective(pos + step, mask, goal, CAM))
                  - float(obj.objective(pos - step, mask, goal, CAM))) / (2 * eps)
            assert abs(fd - grad[k, a]) <= 2e-2 * max(1.0, abs(fd)), (k, a, fd, grad[k, a])


def test_gradient_finite_with_coincident_points(disc):
    """A particle exactly on a goal sample and two particles on top of each other: no NaN."""
    uv = np.asarray(disc.samples[:2], np.float64)[[0, 1, 1]]
    pos = np.asarray(CAM.pixel_to_world(uv, np.full(3, CAM.centre[2])), np.float32)
    grad = jax.grad(obj.objective)(pos, np.ones(3, bool), disc, CAM)
    assert np.all(np.isfinite(np.asarray(grad)))


def test_padding_is_inert(disc):
    pos, mask = random_particles(6)
    padded = pos.copy()
    padded[~mask] = [[np.nan, 5.0, -3.0]]
    f = jax.value_and_grad(obj.objective)
    (c0, g0), (c1, g1) = f(pos, mask, disc, CAM), f(padded, mask, disc, CAM)
    assert float(c0) == float(c1)
    np.testing.assert_array_equal(np.asarray(g0), np.asarray(g1))
    from dynres_jax.errors import InputError

    with pytest.raises(InputError, match="no valid particle"):  # a concrete empty set: undefined, said
        obj.objective(pos, np.zeros_like(mask), disc, CAM)
    assert float(jax.jit(obj.objective, static_argnums=3)(pos, np.zeros_like(mask), disc, CAM)) == 0.0  # traced


def test_vmap_equals_loop(disc):
    batch = [random_particles(s, omega=3 + s) for s in range(4)]
    pos, mask = np.stack([b[0] for b in batch]), np.stack([b[1] for b in batch])
    got = jax.vmap(obj.objective, in_axes=(0, 0, None, None))(pos, mask, disc, CAM)
    np.testing.assert_allclose(np.asarray(got), [float(obj.objective(p, m, disc, CAM)) for p, m in batch], rtol=1e-6)


def test_inside_scores_lower_than_outside(disc):
    rng = np.random.default_rng(7)
    pos = np.concatenate([(0.03, -0.02) + rng.uniform(-0.035, 0.035, (20, 2)), np.full((20, 1), 0.007)], 1)
    mask = np.ones(20, bool)
    shifted = pos + [0.1, 0.1, 0.0]
    assert float(obj.objective(pos, mask, disc, CAM)) < float(obj.objective(shifted, mask, disc, CAM))


# ----------------------------------------------------------------------------------------------------------------
# Distribution distance d and inside share on a rendered scene
# ----------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def scene():
    env = PileEnv(SimConfig(scene=SceneConfig(pieces=(6,)), camera=CameraConfig(width=48, height=48)),
                  backend="mujoco")
    return env, env.reset(jax.random.PRNGKey(0))


def np_distance(current, goal_mask):
    """The supplement's d by loops over pixels: unsigned, every foreground and every goal pixel, over |F|."""
    fg, goal = np.argwhere(current).astype(np.float64), np.argwhere(goal_mask).astype(np.float64)
    to_goal = sum(min(np.hypot(*(f - q)) for q in goal) for f in fg)
    to_fg = sum(min(np.hypot(*(q - f)) for f in fg) for q in goal)
    return (to_goal + to_fg) / len(fg)


def test_distribution_distance_matches_loop_formula(scene):
    env, state = scene
    cam = env.camera
    centre = np.asarray(state.pos[:, :2]).mean(0)
    goal = make_goal(disc_goal(cam, np.clip(centre + 0.03, -0.1, 0.1), 0.05), cam, n_samples=64)
    _, valid = foreground(state.obs, cam)
    current = np.asarray(valid).reshape(cam.height, cam.width)
    assert current.sum() > 0 and (current & np.asarray(goal.mask)).sum() > 0  # some pixels inside: 0 there
    ref = np_distance(current, np.asarray(goal.mask))
    np.testing.assert_allclose(float(distribution_distance(state.obs, goal, cam)), ref, rtol=1e-5)
    np.testing.assert_allclose(float(distribution_distance(current, goal, cam)), ref, rtol=1e-5)


def test_distribution_distance_unsigned_and_edge_cases():
    """d is 0 when the foreground is the goal exactly (a signed d would be negative), grows as the pile leaves the
    goal, is +inf with no foreground, and names a mask of the wrong shape."""
    cam = CAM
    goal = make_goal(disc_goal(cam, (0.0, 0.0), 0.05), cam)
    mask = np.asarray(goal.mask)
    assert float(distribution_distance(mask, goal, cam)) == 0.0
    shifted = [float(distribution_distance(np.roll(mask, k, axis=1), goal, cam)) for k in (2, 6, 12)]
    assert 0 < shifted[0] < shifted[1] < shifted[2]
    assert float(distribution_distance(np.zeros_like(mask), goal, cam)) == np.inf
    with pytest.raises(ValueError, match="foreground mask has shape"):
        distribution_distance(mask[:-1], goal, cam)


def test_squared_distance_to_matches_brute_force():
    rng = np.random.default_rng(3)
    for shape, p in [((9, 14), 0.1), ((16, 5), 0.02), ((7, 7), 0.0)]:
        mask = rng.uniform(size=shape) < p
        got = np.asarray(squared_distance_to(mask))
        if not mask.any():
            assert np.all(np.isinf(got))
            continue
        ii, jj = np.nonzero(mask)
        for i in range(shape[0]):
            for j in range(shape[1]):
                assert got[i, j] == np.min((i - ii) ** 2 + (j - jj) ** 2)



def test_coverage_chunking_changes_nothing(disc, monkeypatch):
    pixels = jnp.asarray(np.random.default_rng(8).uniform(20, 100, (50, 2)), jnp.float32)
    valid = jnp.arange(50) < 45
    whole = float(obj._cost(pixels, valid, disc))
    monkeypatch.setattr(obj, "MAX_PAIRS", 7 * 50)  # 7 goal samples at a time: 500 is not a multiple of 7
    np.testing.assert_allclose(float(obj._cost(pixels, valid, disc)), whole, rtol=1e-6)


@pytest.mark.parametrize("p", [1, 2, 100, 128, 129, 1000])
def test_argmin_by_packed_min_matches_numpy(p):
    """The coverage term's argmin (float bits with the index in the low bits, one int min): the smallest value's
    index where it is clear, the lower index on exact ties, index 0 when every value is +inf (as np.argmin)."""
    rng = np.random.default_rng(p)
    for _ in range(20):
        values = rng.uniform(0.0, 100.0, p).astype(np.float32) ** 2
        values[rng.uniform(size=p) < 0.3] = np.inf
        values[rng.integers(p, size=2)] = values.min()  # an exact tie, possibly with itself
        assert int(obj._argmin_nonnegative(jnp.asarray(values))) == int(np.argmin(values))
    assert int(obj._argmin_nonnegative(jnp.full(p, jnp.inf))) == 0


def test_inside_share_matches_numpy_count(scene):
    env, state = scene
    cam = env.camera
    pos = np.asarray(state.pos)
    goal = make_goal(disc_goal(cam, np.clip(pos[0, :2], -0.12, 0.12), 0.06), cam)
    for mask in [np.ones(6, bool), np.arange(6) < 4]:
        uv = np.floor(np_project(cam, pos)).astype(int)
        gm = np.asarray(goal.mask)
        hits = [m and 0 <= u < cam.width and 0 <= v < cam.height and gm[v, u]
                for (u, v), m in zip(uv, mask, strict=True)]
        np.testing.assert_allclose(float(inside_share(pos, mask, goal, cam)), sum(hits) / mask.sum(), rtol=1e-6)
    assert float(inside_share(pos, np.zeros(6, bool), goal, cam)) == 0.0
    broken = pos.copy()
    broken[1, 0] = np.nan  # a valid piece without a position: no share, not 0 %
    assert np.isnan(float(inside_share(broken, np.ones(6, bool), goal, cam)))
    masked = np.arange(6) != 1  # the same NaN in a masked slot is inert
    assert float(inside_share(broken, masked, goal, cam)) == float(inside_share(pos, masked, goal, cam))


# ----------------------------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------------------------
def test_bad_input_raises_naming_it():
    with pytest.raises(ValueError, match="no pixels"):
        disc_goal(CAM, (0.0, 0.0), 1e-4)  # between pixel centres
    with pytest.raises(ValueError, match="no pixels"):
        make_goal(np.zeros((CAM.height, CAM.width), bool), CAM)
    with pytest.raises(ValueError, match="whole image"):
        make_goal(np.ones((CAM.height, CAM.width), bool), CAM)
    with pytest.raises(ValueError, match="shape"):
        make_goal(np.ones((4, 4), bool), CAM)
    with pytest.raises(ValueError, match="outside the bin"):
        disc_goal(CAM, (0.18, 0.0), 0.05)
    with pytest.raises(ValueError, match="outside the camera image"):
        disc_goal(Camera.top_down(CameraConfig(view_half_width=0.1)), (0.12, 0.0), 0.02)
    with pytest.raises(ValueError, match="radius must be positive"):
        disc_goal(CAM, (0.0, 0.0), 0.0)
    with pytest.raises(ValueError, match="radius must be positive"):
        disc_goal(CAM, (0.0, 0.0), -0.1)
    with pytest.raises(ValueError, match="height_m must be positive"):
        text_goal(CAM, "T", (0.0, 0.0), 0.0)
    with pytest.raises(ValueError, match="thickness_m must be positive"):
        text_goal(CAM, "T", (0.0, 0.0), 0.1, thickness_m=-1.0)
    with pytest.raises(ValueError, match="non-empty string"):
        text_goal(CAM, " ", (0.0, 0.0), 0.1)
    with pytest.raises(ValueError, match="outside the bin"):
        text_goal(CAM, "WIDE", (0.0, 0.0), 0.15)
    with pytest.raises(ValueError, match="K >= 3"):
        polygon_goal(CAM, [[0.0, 0.0], [0.1, 0.0]])
    with pytest.raises(ValueError, match="outside the bin"):
        polygon_goal(CAM, [[0.0, 0.0], [0.3, 0.0], [0.0, 0.1]])
    with pytest.raises(ValueError, match="overlap"):
        sort_goals(CAM, [[0.0, 0.0], [0.05, 0.0]], 0.04)


def test_scores_name_a_goal_of_another_camera_and_positions_of_another_shape(disc):
    """A goal made for other images and pieces not [N, 3]: a ValueError naming them (JAX's broadcasting message
    before), from distribution_distance, seen_inside and inside_share, under vmap too."""
    from dynres_jax.control.goals import disc_goal, make_goal
    from dynres_jax.sim.camera import Camera

    other = Camera.top_down(CameraConfig(width=2 * CAM.width, height=2 * CAM.height))
    big = make_goal(disc_goal(other, (0.0, 0.0), 0.05), other)
    frame = np.zeros((CAM.height, CAM.width), bool)
    for score in (obj.distribution_distance, obj.seen_inside):
        with pytest.raises(ValueError, match="goal was made for .* images, the camera's are"):
            score(frame, big, CAM)
    pos, mask = random_particles(5)
    with pytest.raises(ValueError, match="goal was made for"):
        obj.inside_share(pos, mask, big, CAM)
    with pytest.raises(ValueError, match="piece_pos must be \\[N, 3\\]"):
        obj.inside_share(pos[:, :2], mask, disc, CAM)
    with pytest.raises(ValueError, match="goal was made for"):
        jax.vmap(obj.distribution_distance, in_axes=(0, None, None))(frame[None], big, CAM)
    assert 0 <= float(obj.inside_share(pos, mask, disc, CAM)) <= 1
