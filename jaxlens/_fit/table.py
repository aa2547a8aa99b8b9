"""The escape angle of one camera distance for the fit (a `RayMap` out to $\\pi/2$ with
values-only knots), and the exact Einstein ring relation $\\alpha_E(D)$ solved on it."""

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._exact import finite_crossings, grazing_angle
from .._messages import shown
from .._ray_inputs import check_distance, check_dtype, check_real
from .._raymap import RayMap, _difference_slopes, tabulate
from .._units import length
from .._util import concrete
from .._weak import _C, _I_HALF, weak_field_terms

# Below this distance (units of R_S) the primary Einstein ring lies beyond pi/2 from the
# direction of the hole, where no pinhole camera sees it: Phi(pi/2) = pi there (found by
# bisection on `trace` at accuracy 1e-14; tests/test_checks.py checks both sides).
D_RING = 1.7603089815759632

# From these distances the ring comes from the weak-field series rather than the table:
# solving Phi = pi on the table loses eps pi / 2 in alpha to the rounding of Phi ~ pi
# (relative eps pi / (2 alpha) ~ eps sqrt(D / 2)), the series' truncation is relative
# 0.39 D^-1.5; they cross near 2e3 in float32 (2e-6) and 4e7 in float64 (1e-12).
_SERIES_FROM = {"float32": 2e3, "float64": 4e7}
_SERIES_ITERATIONS = 6  # each gains ~ -log10(u2) >= 1.8 digits at D >= 2e3


def einstein_ring_angle(distance: ArrayLike) -> Float[Array, "..."]:
    """Angle of the primary Einstein ring from the direction of the hole, radians.

    The local angle $\\alpha_E$ at which a static camera at `distance` (units of R_S or
    a dimensionless astropy Quantity,
    $D_{ring} = 1.7603089815759632 \\le D \\le 10^{30}$, any shape) sees a source
    exactly behind the hole at infinity: $\\Phi(\\alpha_E) = \\pi$. Solved on the ray
    map of the exact escape angle (`escape_table`; error below $10^{-10}$ rad against
    `trace`) up to $D = 4 \\times 10^7$ in float64 ($2 \\times 10^3$ in float32), and
    beyond from the weak-field series of the escape angle (`weak_field_escape_angle`),
    written without cancellation against $\\pi$: relative error $\\le 10^{-12}$ in
    float64 and a few float32 ulps beyond $10^4$ in float32 (the table's solve lost
    relative $\\epsilon \\sqrt{D/2}$: 9 % at $D = 10^{12}$ in float32).

    Below $D_{ring}$ the ring lies beyond $\\pi/2$, where no pinhole camera sees it:
    such a distance (and one `trace` refuses) is a `ValueError` naming it, eagerly, and
    an `eqx.error_if` error at run time under `jit`. Works under `jit`, `vmap` and
    `grad` (the derivative is that of the implicit function).

    **Returns:** $\\alpha_E$ (radians), e.g. 29.8283 deg at $D = 10$;
    $\\approx\\sqrt{2/D}$ for $D \\gg 1$; $\\pi/2$ at $D_{ring}$.
    """
    distance = check_real("distance", length(distance, "distance"))
    dtype = check_dtype(jnp.result_type(float, distance), "dtype of distance")
    distance = check_distance(distance, dtype)
    known = concrete(distance)
    message = (
        f"is below {D_RING!r} R_S: the primary Einstein ring then lies beyond pi/2 from "
        "the hole, where no pinhole camera sees it"
    )
    if known is not None:
        if np.any(known < D_RING):
            raise ValueError(f"distance={shown(known[known < D_RING].flat[0])} {message}")
    else:
        distance = eqx.error_if(distance, jnp.any(distance < D_RING), "distance " + message)
    d = jnp.asarray(distance, dtype)
    split = _SERIES_FROM[dtype.name]

    def one(d):
        far = d >= split
        # Each branch at a distance it handles (the other one's value is discarded).
        table = escape_table(jnp.where(far, 10.0, d))
        near = jnp.minimum(table.solve(jnp.pi), 0.5 * jnp.pi)
        return jnp.where(far, _ring_series(jnp.where(far, d, split)), near)

    return jnp.vectorize(one)(d)


def _ring_series(d):
    """The primary ring angle (radians) of a far camera at `d` (units of R_S) from the
    weak-field series (`_weak`): with $\\sin t_0 = u_0/u_2$, $\\Phi = \\pi$ reads
    $t_0 = S = \\sum_{n \\ge 1} c_n u_2^n [2 I_n(\\pi/2) - I_n(t_0)]$, every term
    positive (no cancellation against $\\pi$); iterated as $t_0 \\leftarrow
    \\sqrt{t_0 S}$ ($t_0 S \\approx 2 u_0$ barely depends on $t_0$), from
    $t_0 = \\sqrt{2 u_0}$. Then $\\sin\\alpha = \\sin t_0 \\sqrt{(1 - u_0)/(1 - u_2)}$."""
    u0 = 1.0 / d
    t = jnp.sqrt(2.0 * u0)
    for _ in range(_SERIES_ITERATIONS):
        s = jnp.sin(t)
        u2 = u0 / s
        _, terms = weak_field_terms(s, jnp.cos(t))
        total = sum(_C[n] * u2**n * (2.0 * _I_HALF[n] - terms[n]) for n in (1, 2, 3))
        t = jnp.sqrt(t * total)
    s = jnp.sin(t)
    return jnp.arcsin(s * jnp.sqrt((1.0 - u0) / (1.0 - u0 / s)))


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
    # fusions that read it (the same values to 3e-16; the Jacobian compiled longer).
    maps = jax.lax.map(lambda x: _escape_table(x, knots), at)
    primal = jax.tree.map(lambda v: v[0], maps)
    slope = jax.tree.map(lambda v: (v[1] - 8.0 * v[2] + 8.0 * v[3] - v[4]) / (12.0 * h), maps)
    return primal, jax.tree.map(lambda v: v * dd, slope)


def solve_with_slope(table: RayMap, target: ArrayLike):
    """Where the escape angle of `table` equals `target` (radians), and
    $d\\Phi/d\\alpha$ there. **Returns:** `(alpha, slope)` (radians, per radian)."""
    return table.solve(target, with_slope=True)


def source_table(distance: ArrayLike, radius: ArrayLike, *, knots: int = 4096) -> RayMap:
    """The ray map the fit reads for a source on the sphere $r = R$ about the hole:
    `escape_table`'s knots in $\\alpha$ (out to $\\pi/2$), their values the azimuth
    $\\varphi_R(\\alpha)$ at which each ray leaves through the sphere after its
    periapsis (`finite_crossings`, at the table's 6 duplication steps) in place of the
    escape angle, the slopes by the same fourth-order differences.

    A ray from a camera at $D \\le R$ crosses the sphere once, after its periapsis (a
    captured ray never). For $1.5 < R < D$ a ray that turns outside the photon sphere
    crosses it twice: on its way in, on the camera's side of the hole, and after its
    periapsis; the map holds the second, where a source behind the hole is seen (for
    the rays that turn beyond $R$ and never meet it, the grazing ray's azimuth falling
    on with a slope of one: the map stays monotone, and nothing behind the hole is read
    there). A source in front
    of the hole, seen through the first crossings, is not what it holds. So the
    renderer's area-exact cells, given this map, draw a sky behind the hole on the
    sphere, its thin rings included (where $\\varphi_R = 3\\pi, 5\\pi$), with the
    shadow edge of the distance. Differentiable in forward and reverse mode with
    respect to `distance` (the knots through `escape_table`'s difference rule, the
    values by autodiff of the closed form) and `radius` (units of R_S, scalars). A
    sphere inside the photon sphere ($R \\le 1.5$), whose light behind the hole reaches
    the camera only inside the shadow, is not either; the fit flags it.
    """
    d = jnp.asarray(distance, jnp.result_type(float, distance))
    r = jnp.asarray(radius, d.dtype)
    base = escape_table(d, knots=knots)
    alpha = base.alpha_sh + jnp.exp(base.tau)
    c = finite_crossings(alpha, d, r, iterations=6)
    # The rays that turn beyond a sphere inside the camera's radius never meet it:
    # past the ray that grazes it (alpha_R, its periapsis R), the azimuth of the
    # grazing point less alpha - alpha_R, monotone with a slope (the area-exact cells
    # divide by it) and far from anything behind the hole.
    inner = r < d
    rr = jnp.where(inner, r, 0.5 * d)
    alpha_r = grazing_angle(d, rr)
    graze = finite_crossings(alpha_r, d, rr, iterations=6).first
    beyond = graze - (alpha - alpha_r)
    phi = jnp.where(inner, jnp.where(c.count == 2, c.second, beyond), c.first)
    # At R = inf the crossing is the escape angle: the map's own values, bit for bit.
    phi = jnp.where(jnp.isinf(r), base.phi, phi)
    return eqx.tree_at(lambda m: (m.phi, m.slope), base,
                       (phi, _difference_slopes(phi, base.dtau)))  # fmt: skip
