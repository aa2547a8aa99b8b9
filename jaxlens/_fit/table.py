"""The escape angle of one camera distance for the fit (a `RayMap` out to $\\pi/2$ with
values-only knots), and the exact Einstein ring relation $\\alpha_E(D)$ solved on it."""

import math

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._raymap import RayMap

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
    escape angle at 4096 knots, and its derivative with respect to $D$ needs only
    first derivatives of the closed form, which keeps the fit's compiled Jacobian small.
    """
    return RayMap.build(
        distance, knots=knots, alpha_max=0.5 * math.pi, exact_slopes=False, iterations=6
    )


def solve_with_slope(table: RayMap, target: ArrayLike):
    """Where the escape angle of `table` equals `target` (radians), and
    $d\\Phi/d\\alpha$ there. **Returns:** `(alpha, slope)` (radians, per radian)."""
    return table.solve(target, with_slope=True)
