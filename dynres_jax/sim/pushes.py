"""The push action space: where a push may start and end, how any action is put back into it, random pushes.

An action is (x_start, y_start, x_end, y_end) in metres, the bin centred at the origin. A push ends within ±bound
(``PileEnv.action_bound``: two piece widths inside the walls, so the plate never squeezes a piece against a wall) and
starts there too, or outside a wall: a start coordinate of ±reach (``PileEnv.reach``) lowers the plate beyond that
wall, where no piece can be (the plate passes through walls, pieces do not), and the push sweeps the pieces that rest
against the wall back in. A start between bound and reach would lower the plate onto pieces pinned against the wall:
``project`` moves it to the nearer of the two. reach None: every push starts inside (a robot's table, no walls).

Random pushes (the planner's first samples, the training data's pushes) pass through a point of the pile; with a
reach, a share ``WALL_SHARE`` of them are wall pushes: from outside the wall nearest to a pile point drawn with
weight ``exp(-distance to that wall / WALL_SCALE)``, inward within ``WALL_SPREAD`` of the wall's normal (when that
point lies within half a push's greatest length of the outside).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

ZERO_LENGTH_DIRECTION = (1.0, 0.0)  # a push of (near) zero length is pointed along +x by ``project``
WALL_SHARE = 0.2  # of random pushes that start outside a wall (when a reach is given)
WALL_SCALE = 0.02  # m: wall pushes favour pile points this close to a wall (weight e^-1 per WALL_SCALE further)
WALL_SPREAD = jnp.pi / 3  # a wall push's direction lies within ± this of the wall's inward normal
REACH_GAP = 0.002  # m: a push from outside a wall starts with the plate's surface this far beyond the wall
_TINY = 1e-12  # m²: squared lengths below this count as zero


def wall_reach(bin_half_width: float, plate_thickness: float) -> float:
    """m: where a push from outside a wall starts, the plate's surface REACH_GAP beyond the wall (``PileEnv.reach``)."""
    return bin_half_width + plate_thickness / 2 + REACH_GAP


def check_reach(bound: float, reach: float | None, min_length: float, max_length: float) -> None:
    """ValueError unless a reach leaves room for pushes from outside: reach - bound in [min_length,
    max_length / √2] (a push from outside a corner must get in)."""
    if reach is None:
        return
    gap = reach - bound
    if not min_length <= gap <= max_length / 2 ** 0.5:
        raise ValueError(f"reach {reach} m must lie at least min_length {min_length} m beyond bound {bound} m and at "
                         f"most max_length / √2 = {max_length / 2 ** 0.5:.4f} m beyond it; got {gap:.4f} m")


def direction(delta):
    """delta [..., 2] -> (unit direction [..., 2], length [...]); ZERO_LENGTH_DIRECTION where the length is ~0.
    The gradient stays finite at zero length (the unused branch divides by 1)."""
    sq = jnp.sum(jnp.square(delta), axis=-1)
    nonzero = sq > _TINY
    length = jnp.sqrt(jnp.where(nonzero, sq, 1.0))
    fixed = jnp.broadcast_to(jnp.asarray(ZERO_LENGTH_DIRECTION, delta.dtype), delta.shape)
    return jnp.where(nonzero[..., None], delta / length[..., None], fixed), jnp.where(nonzero, length, 0.0)


def _snap(start, bound, reach):
    """Start coordinates [..., 2] clipped to ±reach, those between bound and reach moved to the nearer of the two."""
    x = jnp.clip(start, -reach, reach)
    a = jnp.abs(x)
    between = (a > bound) & (a < reach)
    return jnp.where(between, jnp.sign(x) * jnp.where(a < (bound + reach) / 2, bound, reach), x)


def _entry(start, heading, bound):
    """Where the rays start + t heading [..., 2] enter and leave the square ±bound: (t_in, t_out) [...]; t_in > t_out
    when a ray misses it."""
    still = jnp.abs(heading) < 1e-9
    safe = jnp.where(still, 1.0, heading)
    t1, t2 = (-bound - start) / safe, (bound - start) / safe
    inside = jnp.abs(start) <= bound
    lo = jnp.where(still, jnp.where(inside, -jnp.inf, jnp.inf), jnp.minimum(t1, t2))
    hi = jnp.where(still, jnp.where(inside, jnp.inf, -jnp.inf), jnp.maximum(t1, t2))
    return jnp.max(lo, axis=-1), jnp.min(hi, axis=-1)


def project(actions, bound, min_length, max_length, reach=None):
    """Actions [..., 4] m -> the nearest-in-spirit actions of the action space, same shape.

    A start inside: clipped to ±bound; the length clipped to [min_length, max_length] keeping the start and the
    direction (a zero-length push points along ZERO_LENGTH_DIRECTION); if the end then leaves ±bound, the whole push is
    translated back inside, axis by axis (direction and length kept; it fits because max_length <= 2 bound).
    A start outside (a coordinate at ±reach, after ``_snap``): the direction is kept if the push can enter ±bound
    within max_length, else it is turned to the walls' inward normal; the length is clipped to the part of
    [min_length, max_length] that ends inside ±bound. Idempotent, pure, jit/vmap-able, finite gradients everywhere.
    """
    actions = jnp.asarray(actions, jnp.float32)
    heading, length = direction(actions[..., 2:] - actions[..., :2])
    start = jnp.clip(actions[..., :2], -bound, bound)
    end = start + heading * jnp.clip(length, min_length, max_length)[..., None]
    lo, hi = jnp.minimum(start, end), jnp.maximum(start, end)
    shift = jnp.maximum(-bound - lo, 0.0) - jnp.maximum(hi - bound, 0.0)
    inside = jnp.concatenate([start + shift, end + shift], axis=-1)
    if reach is None:
        return inside
    start = _snap(actions[..., :2], bound, reach)
    beyond = jnp.abs(start) > bound
    t_in, t_out = _entry(start, heading, bound)
    enters = (t_in <= t_out) & (t_out > 0) & (t_in <= max_length)
    # Else the walls' inward normal (a corner's diagonal): it enters at (reach - bound) √k, leaves at (reach + bound) √k
    root = jnp.sqrt(jnp.sum(beyond, axis=-1).astype(jnp.float32))
    heading = jnp.where(enters[..., None], heading, -jnp.sign(start) * beyond / jnp.maximum(root, 1.0)[..., None])
    t_in = jnp.where(enters, t_in, (reach - bound) * root)
    t_out = jnp.where(enters, t_out, (reach + bound) * root)
    length = jnp.clip(length, jnp.maximum(min_length, t_in), jnp.minimum(max_length, t_out))
    outside = jnp.concatenate([start, start + heading * length[..., None]], axis=-1)
    return jnp.where(jnp.any(beyond, axis=-1)[..., None], outside, inside)


def pile_points(key, points, valid, shape, reach=None):
    """Points (x, y) [*shape, 2] m of the valid points [P, 3] (valid [P]) drawn at random: uniformly, or with reach
    given, with weight exp(-distance to the nearest wall / WALL_SCALE) (reach stands in for the wall: the same
    order); the origin if no point is valid."""
    if reach is None:
        count = jnp.sum(valid)
        k = jnp.minimum(jnp.floor(jax.random.uniform(key, shape) * count), count - 1)  # the k-th valid point ...
        index = jnp.searchsorted(jnp.cumsum(valid), k + 1)  # ... wherever it sits, so masked padding changes nothing
    else:
        near = (jnp.max(jnp.abs(points[:, :2]), axis=-1) - reach) / WALL_SCALE
        index = jax.random.categorical(key, jnp.where(valid, near, -jnp.inf), shape=shape)
    return jnp.where(jnp.any(valid), points[jnp.minimum(index, valid.shape[0] - 1), :2], 0.0)


def wall_pushes(key, point, reach, min_length, max_length):
    """Pushes [..., 4] m from outside the wall nearest to each point [..., 2], inward within WALL_SPREAD of the wall's
    normal, through the point and on for a random part of the rest of max_length (not yet ``project``ed)."""
    k_angle, k_len = jax.random.split(key)
    axis = jnp.argmax(jnp.abs(point), axis=-1)
    side = jnp.sign(jnp.take_along_axis(point, axis[..., None], -1))[..., 0]
    normal_angle = jnp.where(axis == 0, jnp.where(side > 0, jnp.pi, 0.0), -side * jnp.pi / 2)
    angle = normal_angle + jax.random.uniform(k_angle, axis.shape, minval=-WALL_SPREAD, maxval=WALL_SPREAD)
    heading = jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1)
    across = jnp.abs(jnp.take_along_axis(heading, axis[..., None], -1))[..., 0]
    back = (reach - jnp.abs(jnp.take_along_axis(point, axis[..., None], -1))[..., 0]) / across  # to the outside
    start = point - heading * back[..., None]
    start = start.at[..., 0].set(jnp.where(axis == 0, side * reach, start[..., 0]))
    start = start.at[..., 1].set(jnp.where(axis == 1, side * reach, start[..., 1]))
    length = jnp.clip(back + jax.random.uniform(k_len, axis.shape) * (max_length - back), min_length, max_length)
    return jnp.concatenate([start, start + heading * length[..., None]], axis=-1)


def sample_actions(key, m, t, bound, min_length, max_length, centre_xy=None, spread=0.03, reach=None, wall_xy=None):
    """M random action sequences [m, t, 4] m, inside the action space (``project``ed).

    Every push has a uniform direction and a length uniform in [min_length, max_length]. It passes through a point
    drawn uniformly in the workspace or, with centre_xy given ([2], or one point per push [m, t, 2]; the planner
    passes random particles: pushes through the pile, as the reference's initial pushes), uniformly in the disc of
    radius ``spread`` around it; the point lies 20-60 % of the way along the push, so the push starts behind it.
    With reach and wall_xy [m, t, 2] (``pile_points`` with reach) given, a share WALL_SHARE of the pushes are
    ``wall_pushes`` through wall_xy instead, where wall_xy lies within max_length / 2 of the outside (farther, a push
    from outside would stop short of the pile).
    """
    k_point, k_angle, k_len, k_frac = jax.random.split(key, 4)
    shape = (m, t)
    if centre_xy is None:
        point = jax.random.uniform(k_point, shape + (2,), minval=-bound, maxval=bound)
    else:
        k_r, k_phi = jax.random.split(k_point)
        radius = spread * jnp.sqrt(jax.random.uniform(k_r, shape))
        phi = jax.random.uniform(k_phi, shape, minval=-jnp.pi, maxval=jnp.pi)
        point = jnp.asarray(centre_xy, jnp.float32) + radius[..., None] * jnp.stack([jnp.cos(phi), jnp.sin(phi)], -1)
    angle = jax.random.uniform(k_angle, shape, minval=-jnp.pi, maxval=jnp.pi)
    heading = jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1)
    length = jax.random.uniform(k_len, shape, minval=min_length, maxval=max_length)[..., None]
    start = point - heading * length * jax.random.uniform(k_frac, shape + (1,), minval=0.2, maxval=0.6)
    actions = jnp.concatenate([start, start + heading * length], axis=-1)
    if reach is not None and wall_xy is not None:
        k_wall, k_share = jax.random.split(jax.random.fold_in(key, 1))
        wall_xy = jnp.asarray(wall_xy, jnp.float32)
        near = reach - jnp.max(jnp.abs(wall_xy), axis=-1) < max_length / 2  # a push from outside gets there and on
        wall = (jax.random.uniform(k_share, shape) < WALL_SHARE) & near
        actions = jnp.where(wall[..., None], wall_pushes(k_wall, wall_xy, reach, min_length, max_length), actions)
    return project(actions, bound, min_length, max_length, reach)


__all__ = ["REACH_GAP", "WALL_SHARE", "ZERO_LENGTH_DIRECTION", "check_reach", "direction", "pile_points", "project",
           "sample_actions", "wall_pushes", "wall_reach"]
