"""The weak-field series of the escape angle, with a rigorous truncation bound.

For a view in which every ray has its periapsis far out ($b \\gg b_c$), a short series
in $u_2 = 1/r_0$ gives the escape angle without a table; its remainder is bounded, so
the plan uses it only where the bound is below the requested accuracy.
"""

import math

import jax.numpy as jnp
from jaxtyping import ArrayLike

from ._exact import B_CRIT
from ._ray_inputs import ALPHA_RANGE, bad_alpha, check_distance, check_dtype, check_real
from ._units import angle, length

# Coefficients c_n of (1 - x)^(-1/2) = sum c_n x^n.
_C = (1.0, 0.5, 0.375, 0.3125, 0.2734375)
# I_n(pi/2) = int_0^{pi/2} h(sin t)^n dt, h(s) = s + 1/(1 + s).
_I_HALF = (0.5 * math.pi, 2.0, 1.25 * math.pi - 4.0 / 3.0, 122.0 / 15.0 - 1.5 * math.pi)
WEAK_ORDER = 3
# The series costs ~50 ns (CPU) a ray more than a table look-up (three transcendentals
# against one log) but needs no table (~8 ms CPU to build on the 2-core benchmark
# machine): it is the cheaper path up to ~1.3e5 rays a view there
# (benchmarks/results/effects.md). Larger views of a far field take the table, whose
# build is then amortised.
WEAK_MAX_SAMPLES = 1 << 17


def _periapsis_u(b):
    """$u_2 = 1/r_0$: the smallest positive root of $u^2 - u^3 = 1/b^2$, by Newton on
    $w = u b$, $w^2 (1 - w/b) = 1$, from $w = 1$ (four steps reach round-off for
    $u_2 < 0.1$, where the series is used; no $b^2$, which overflows for far cameras)."""
    ib = 1.0 / b
    w = jnp.ones_like(b)
    for _ in range(4):
        wb = w * ib
        w = w - (w * w * (1.0 - wb) - 1.0) / (w * (2.0 - 3.0 * wb))
    return w * ib


def weak_field_terms(y0, c0=None):
    """$I_n(t_0) = \\int_0^{t_0} h(\\sin t)^n dt$, $n = 0..3$, $h(s) = s + 1/(1+s)$, at
    $\\sin t_0 = y_0 \\in [0, 1]$ (and $\\cos t_0$ = `c0`, if known more accurately than
    from $y_0$), in closed form (through $w = \\tan(t_0/2)$)."""
    if c0 is None:
        c0 = jnp.sqrt((1.0 - y0) * (1.0 + y0))
    t0 = jnp.arctan2(y0, c0)
    w = y0 / (1.0 + c0)
    v = 1.0 + w
    iv = 1.0 / v
    j1 = 2.0 * w * iv
    j2 = 2.0 * (((-2.0 / 3.0 * iv + 1.0) * iv - 1.0) * iv + 2.0 / 3.0)
    j3 = 2.0 * (((((-0.8 * iv + 2.0) * iv - 8.0 / 3.0) * iv + 2.0) * iv - 1.0) * iv + 7.0 / 15.0)
    s1 = y0 * y0 / (1.0 + c0)  # 1 - cos t0
    s2 = 0.5 * (t0 - y0 * c0)
    s3 = s1 - (1.0 - c0**3) / 3.0  # 2/3 - cos t0 + cos^3 t0 / 3
    i1 = s1 + j1
    i2 = s2 + 2.0 * t0 - 2.0 * j1 + j2
    i3 = s3 + 3.0 * s1 - 3.0 * t0 + 6.0 * j1 - 3.0 * j2 + j3
    return t0, (t0, i1, i2, i3)


def weak_field_escape_angle(alpha: ArrayLike, distance: ArrayLike, *, order: int = WEAK_ORDER):
    """Escape angle of rays with a far periapsis, as a series in $u_2 = 1/r_0$, with a
    rigorous bound on the truncation error (`weak_field_series`, its values checked).

    **Arguments:** `alpha` (local angle from the hole, radians in $[0, \\pi]$, or an
    astropy angle Quantity), `distance` (camera radius, units of R_S or a
    dimensionless Quantity, $1 < D \\le 10^{30}$ as for `trace`; the
    series applies only outside the photon sphere, $D > 1.5$, and `bound` is `inf`
    elsewhere); `order` $N \\in \\{1, 2, 3\\}$ (static).

    **Returns:** `(phi, bound)`, radians; `bound` is `inf` where the series is not used
    (near rays, $b \\le 2 b_c$, or $1.5 u_2 \\ge 1/2$; every ray of a camera inside
    the photon sphere).

    A value out of range is a `ValueError` naming it (complex or text values a
    `TypeError`), eagerly, and an `eqx.error_if` error at run time under `jit`.
    """
    import equinox as eqx

    if order not in (1, 2, 3):
        raise ValueError(f"order={order!r} must be 1, 2 or 3")
    alpha = check_real("alpha", angle(alpha, "alpha"))
    distance = check_real("distance", length(distance, "distance"))
    dtype = check_dtype(jnp.result_type(float, alpha, distance), "dtype of alpha and distance")
    distance = check_distance(distance, dtype)
    bad = bad_alpha(alpha)
    phi, bound = weak_field_series(alpha, distance, order=order)
    if bad is not None:
        phi = eqx.error_if(phi, bad, "alpha must be " + ALPHA_RANGE)
    return phi, bound


def weak_field_series(alpha: ArrayLike, distance: ArrayLike, *, order: int = WEAK_ORDER):
    """Escape angle of rays with a far periapsis, as a series in $u_2 = 1/r_0$, with a
    rigorous bound on the truncation error; the values are not checked (the renderer
    and the plan call it on checked ones).

    With $u = u_2\\sin t$ the azimuth from the asymptote to $u$ is exactly
    $\\int_0^{t}[1 - u_2 h(\\sin t')]^{-1/2} dt'$, $h(s) = s + 1/(1+s) \\in [1, 3/2]$;
    expanding the root gives $\\sum_n c_n u_2^n I_n(t)$ with $c_n = \\binom{2n}{n}4^{-n}$
    and closed-form $I_n$ (`weak_field_terms`). $\\Phi = \\phi(t_0)$ for outward rays,
    $2\\phi(\\pi/2) - \\phi(t_0)$ for inward ones ($\\sin t_0 = u_0/u_2$). For a camera at
    infinity this is the deflection $2/b + (15\\pi/16)/b^2 + \\dots$ (PHYSICS.md). The
    remainder after order $N$ is at most $L\\,c_{N+1}(1.5u_2)^{N+1}/(1 - 1.5u_2)$,
    $L = \\pi - t_0$ (inward) or $t_0$ (outward).

    **Arguments:** `alpha` (local angle from the hole, radians), `distance` (camera
    radius, units of R_S; $D > 1$, the series applies for $D > 1.5$); `order`
    $N \\in \\{1, 2, 3\\}$ (static).

    **Returns:** `(phi, bound)`, radians; `bound` is `inf` where $b \\le 2 b_c$ or
    $1.5u_2 \\ge 1/2$, where the series is not used (every ray of a camera at
    $D \\le 1.5$: there $b \\le D^{3/2}/\\sqrt{D - 1} \\le b_c$).
    """
    if order not in (1, 2, 3):
        raise ValueError(f"order={order!r} must be 1, 2 or 3")
    alpha = jnp.asarray(alpha, jnp.result_type(float, alpha))
    d = jnp.asarray(distance, alpha.dtype)
    sa = jnp.abs(jnp.sin(alpha))
    ca = jnp.cos(alpha)
    inward = ca > 0
    b = d * sa * jnp.sqrt(d / (d - 1.0))
    ok = b > 2.0 * B_CRIT
    b_ = jnp.where(ok, b, 10.0 * B_CRIT)
    u2 = _periapsis_u(b_)
    u0 = 1.0 / d
    y0 = jnp.clip(u0 / u2, 0.0, 1.0)
    # cos t0 from u2 - u0 = G(u0) / [(u2 + u0) - (u2^2 + u2 u0 + u0^2)], G(u0) =
    # u0^2 (1 - u0) cot^2(alpha): no cancellation for a camera near the periapsis.
    # Written as (u0 / u2) |cot| sqrt(...): u0^2 underflows for far cameras in float32.
    cot = ca / jnp.where(ok, sa, 1.0)
    den = (u2 + u0) - (u2 * u2 + u2 * u0 + u0 * u0)
    c0 = (u0 / u2) * jnp.abs(cot) * jnp.sqrt(jnp.clip(((d - 1.0) / d) * (u2 + u0) / den, 0.0, None))
    t0, terms = weak_field_terms(y0, jnp.minimum(c0, 1.0))
    phi_t = sum(_C[n] * u2**n * terms[n] for n in range(order + 1))
    phi_h = sum(_C[n] * u2**n * _I_HALF[n] for n in range(order + 1))
    phi = jnp.where(inward, 2.0 * phi_h - phi_t, phi_t)
    x = 1.5 * u2
    length = jnp.where(inward, jnp.pi - t0, t0)
    # truncation, plus the round-off of the sums (measured: < 20 eps over random rays)
    eps = jnp.finfo(alpha.dtype).eps
    bound = length * _C[order + 1] * x ** (order + 1) / (1.0 - x) + 64.0 * eps
    ok = ok & (x < 0.5)
    return jnp.where(ok, phi, jnp.pi - alpha), jnp.where(ok, bound, jnp.inf)
