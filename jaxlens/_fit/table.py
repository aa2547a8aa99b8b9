"""The escape angle of one camera distance for the fit (a `RayMap` out to $\\pi/2$ with
values-only knots), and the exact Einstein ring relation $\\alpha_E(D)$ solved on it."""

import functools
import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._raymap import RayMap, tabulate

_D_MIN = 1.5  # the camera sees a ring in front of it only outside the photon sphere


def einstein_ring_angle(distance: ArrayLike) -> Float[Array, "..."]:
    """Angle of the primary Einstein ring from the direction of the hole, radians.

    The local angle $\\alpha_E$ at which a static camera at `distance` (units of R_S,
    $D > 1.5$, any shape) sees a source exactly behind the hole at infinity:
    $\\Phi(\\alpha_E) = \\pi$, solved on the ray map of the exact escape angle
    (`escape_table`; error below $10^{-10}$ rad against `trace`). Works under `jit`,
    `vmap` and `grad` (the derivative is that of the implicit function). NaN where the
    ring lies beyond $\\pi/2$ (cameras with $D \\lesssim 1.9$): no pinhole camera sees it.

    **Returns:** $\\alpha_E$ (radians), e.g. 29.8283 deg at $D = 10$;
    $\\approx\\sqrt{2/D}$ for $D \\gg 1$.
    """

    def one(d):
        table = escape_table(d)
        visible = (d > _D_MIN) & (table.escape_angle(0.5 * jnp.pi) < jnp.pi)
        return jnp.where(visible, table.solve(jnp.pi), jnp.nan)

    d = jnp.asarray(distance, jnp.result_type(float, distance))
    return jnp.vectorize(one)(d)


def escape_table(distance: ArrayLike, *, knots: int = 4096) -> RayMap:
    """The ray map the fit reads: $\\Phi(\\alpha)$ of a camera at `distance` (units of
    R_S, scalar) on `knots` knots out to $\\alpha = \\pi/2$ (a pinhole camera sees no
    wider ray), values only (`RayMap.build(..., exact_slopes=False)`), the closed form at
    the 1e-13 rad setting of `trace` (6 duplication steps): 1.1e-11 rad from the exact
    escape angle at 4096 knots.

    Its derivative with respect to $D$ (every field of the map: knots, values, slopes,
    shadow angle) is a five-point central difference of the map, the five distances
    built one after another in a loop: 3e-11 of the derivative from forward-mode
    autodiff of the closed form (float64), and a program that differentiates the map
    (the fit's Jacobian) holds no tangent of the closed form: it compiles in half the
    time, whatever the number of tangents.
    """
    d = jnp.asarray(distance, jnp.result_type(float, distance))
    return _escape_table(d, int(knots))


# Step of the difference, relative to D - 1 (the scale on which the map changes near
# the horizon), in float64 and in float32: the five-point rule's error ~ step^4, its
# round-off ~ eps / step.
_STEP_F64, _STEP_F32 = 1e-3, 3e-2


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _escape_table(d, knots: int) -> RayMap:
    # The fit checks its distance where it reads it (no error callback a table).
    return tabulate(d, knots=knots, alpha_max=0.5 * math.pi, exact_slopes=False, iterations=6)


@_escape_table.defjvp
def _escape_table_jvp(knots, primals, tangents):
    (d,), (dd,) = primals, tangents
    step = _STEP_F64 if d.dtype == jnp.float64 else _STEP_F32
    h = jax.lax.stop_gradient(step * jnp.abs(d - 1.0))
    at = d + h * jnp.asarray([0.0, -2.0, -1.0, 1.0, 2.0], d.dtype)
    # A loop, not a batch: under `vmap` the build's fusion barriers (`lax.cond` on the
    # distance) became selects, and XLA recomputed the closed form in each of 17
    # fusions that read it (the fit benchmark ring's Jacobian compiled in 2.5 s instead
    # of 2.1 s; the same values to 3e-16).
    maps = jax.lax.map(lambda x: _escape_table(x, knots), at)
    primal = jax.tree.map(lambda v: v[0], maps)
    slope = jax.tree.map(lambda v: (v[1] - 8.0 * v[2] + 8.0 * v[3] - v[4]) / (12.0 * h), maps)
    return primal, jax.tree.map(lambda v: v * dd, slope)


def solve_with_slope(table: RayMap, target: ArrayLike):
    """Where the escape angle of `table` equals `target` (radians), and
    $d\\Phi/d\\alpha$ there. **Returns:** `(alpha, slope)` (radians, per radian)."""
    return table.solve(target, with_slope=True)
