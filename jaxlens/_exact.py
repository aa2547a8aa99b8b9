"""Closed forms for Schwarzschild photon orbits (units of R_S = 1).

Every escape angle here is an integral $\\int du / \\sqrt{P(u)}$ of the cubic
$P(u) = u^3 - u^2 + 1/b^2$, evaluated exactly with Carlson's symmetric elliptic
integral $R_F$. The roots of $P$ are computed in forms that stay accurate in the
weak field ($b \\to \\infty$, two roots $\\to 0$) and near the critical impact
parameter ($b \\to b_c$, two roots merge at $u = 2/3$).

The public functions take angles in radians or as astropy angle Quantities, lengths
(`distance`, `radius`, `plane_distance`, `b`) in units of R_S or as dimensionless
Quantities; a length in metres, km, ... is refused (`jaxlens.schwarzschild_radii`).
"""

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._status import CAPTURED, ESCAPED, UNRESOLVED
from ._units import angle, length

B_CRIT = 1.5 * math.sqrt(3.0)  # critical impact parameter 3 sqrt(3) / 2, units of R_S
R_PHOTON = 1.5  # photon-sphere radius, units of R_S
_SQRT3 = math.sqrt(3.0)


def _rf_series(a, e2, e3):
    # DLMF 19.36.1: Taylor series of R_F about the mean, to seventh order.
    s = (
        1.0
        - e2 / 10.0
        + e3 / 14.0
        + e2 * e2 / 24.0
        - 3.0 * e2 * e3 / 44.0
        - 5.0 * e2**3 / 208.0
        + 3.0 * e3 * e3 / 104.0
        + e2 * e2 * e3 / 16.0
    )
    return s / jnp.sqrt(a)


def carlson_rf(x, y, z, *, iterations: int = 12):
    """Carlson's symmetric elliptic integral of the first kind $R_F(x, y, z)$.

    $R_F = \\frac12 \\int_0^\\infty dt / \\sqrt{(t+x)(t+y)(t+z)}$ for $x, y, z \\ge 0$,
    at most one of them zero. A fixed number of duplication steps (each shrinks
    the relative spread of the arguments four-fold; the seventh-order series
    then has error $\\sim \\text{spread}^8$), so it is a plain differentiable
    function under `jit`, `vmap` and `grad`.

    **Arguments:** `x, y, z`: non-negative arrays (broadcast). `iterations`:
    number of duplication steps; 12 reach float64 round-off even when two
    arguments are $10^{-24}$ of the third.

    **Returns:** $R_F(x, y, z)$.
    """
    x, y, z = jnp.broadcast_arrays(x, y, z)

    def step(_, xyz):
        x, y, z = xyz
        sx, sy, sz = jnp.sqrt(x), jnp.sqrt(y), jnp.sqrt(z)
        lam = sx * (sy + sz) + sy * sz
        return 0.25 * (x + lam), 0.25 * (y + lam), 0.25 * (z + lam)

    x, y, z = jax.lax.fori_loop(0, iterations, step, (x, y, z))
    a = (x + y + z) / 3.0
    dx, dy = 1.0 - x / a, 1.0 - y / a
    dz = -(dx + dy)
    return _rf_series(a, dx * dy - dz * dz, dx * dy * dz)


def _cbrt(x):
    # Cube root of x > 0: exp(log(x)/3) and one Newton step (full precision).
    # jnp.cbrt is avoided: fused with this module's other code, XLA:CPU (jaxlib
    # 0.10.2) miscompiled its forward-mode derivative in vectorised loops.
    y = jnp.exp(jnp.log(x) / 3.0)
    return y - (y * y * y - x) / (3.0 * y * y)


def _hypot(x, y):
    # sqrt(x^2 + y^2) for the O(1)..O(1e6) magnitudes met here (see _cbrt).
    return jnp.sqrt(x * x + y * y)


def _csqrt(re, im):
    """Principal square root of re + i im in real arithmetic, without cancellation."""
    r = _hypot(re, im)
    big = jnp.sqrt(0.5 * (r + jnp.abs(re)))  # |the larger component|
    small = 0.5 * im / jnp.where(big > 0, big, 1.0)
    sgn = jnp.where(im < 0, -1.0, 1.0)
    pos = re >= 0
    return jnp.where(pos, big, jnp.abs(small)), jnp.where(pos, small, sgn * big)


def carlson_rf_conj(zr, zi, w, *, iterations: int = 12):
    """$R_F(z, \\bar z, w)$ for a complex-conjugate pair $z = z_r + i z_i$ and real $w \\ge 0$.

    The duplication keeps the pair conjugate, so everything is real arithmetic.

    **Returns:** the (real) value of $R_F(z, \\bar z, w)$.
    """
    zr, zi, w = jnp.broadcast_arrays(zr, zi, w)

    def step(_, zw):
        zr, zi, w = zw
        sr, si = _csqrt(zr, zi)
        sw = jnp.sqrt(w)
        lam = (sr * sr + si * si) + 2.0 * sw * sr  # |z| + 2 sqrt(w) Re sqrt(z)
        return 0.25 * (zr + lam), 0.25 * zi, 0.25 * (w + lam)

    zr, zi, w = jax.lax.fori_loop(0, iterations, step, (zr, zi, w))
    a = (2.0 * zr + w) / 3.0
    xr, xi = 1.0 - zr / a, -zi / a  # X = 1 - z / A, Y = conj(X)
    dz = -2.0 * xr
    xx = xr * xr + xi * xi
    return _rf_series(a, xx - dz * dz, xx * dz)


def impact_parameter(alpha, distance):
    """Impact parameter of a ray leaving a static camera.

    $b = D \\sin\\alpha / \\sqrt{1 - 1/D}$.

    **Arguments:** `alpha`: local angle from the inward radial direction
    (radians, or an astropy angle). `distance`: camera radius $D > 1$ (units of R_S,
    or a dimensionless Quantity).

    **Returns:** $b \\ge 0$ (units of R_S).
    """
    alpha = angle(alpha, "alpha")
    distance = length(distance, "distance")
    return distance * jnp.abs(jnp.sin(alpha)) * jnp.sqrt(distance / (distance - 1.0))


def shadow_angle(distance):
    """Angular radius of the shadow seen by a static camera (Synge 1966).

    **Arguments:** `distance`: camera radius $D > 1$ (units of R_S).

    **Returns:** $\\alpha_{sh}$ in radians, measured from the direction of the
    hole; above $\\pi/2$ for $D < 1.5$.
    """
    distance = length(distance, "distance")
    return shadow_angle_with(jnp.asarray(distance), jnp)


def shadow_angle_with(d, xp):
    """`shadow_angle` with the array module `xp` (NumPy: on the host, nothing compiled)."""
    u0 = 1.0 / d
    s = B_CRIT * xp.sqrt((d - 1.0) / d) / d
    # cos(alpha_sh) = (2 - 3 u0) sqrt(1 + 3 u0) / 2 exactly (1 - s^2 factorises), so
    # atan2 keeps full accuracy at D = 1.5, where asin(s) would lose half the digits.
    c = (2.0 - 3.0 * u0) * xp.sqrt(1.0 + 3.0 * u0) / 2.0
    return xp.arctan2(s, c)


def real_roots(s, kappa):
    """Roots $u_1 < 0 < u_2 \\le u_3$ of $u^3 - u^2 + 1/b^2$ for $b > b_c$.

    Written through $\\chi = \\arcsin(b_c / b)$ so that $u_1, u_2 \\approx \\mp 1/b$
    keep full relative accuracy for huge $b$, and the distances of $u_2, u_3$
    from $2/3$ for $b \\to b_c$.

    **Arguments:** `s` $= b_c / b$ and `kappa` $= 1 - b_c^2/b^2 > 0$, each
    computed without cancellation by the caller.

    **Returns:** `u1, u2, e2, e3, om3, d32, d21, d31`, where `e2, e3` are
    $u_2 - 2/3$, $u_3 - 2/3$, `om3` is $1 - u_3$ and `dij` $= u_i - u_j$
    (units of 1/R_S).
    """
    rk = jnp.sqrt(kappa)
    t = jnp.arctan2(s, rk) / 3.0  # asin(b_c / b) / 3
    tc = jnp.arctan2(rk, s) / 3.0  # pi/6 - t, accurate near b_c
    st = jnp.sin(t)
    u1 = -(4.0 / 3.0) * st * jnp.sin(jnp.pi / 3.0 - t)
    u2 = (4.0 / 3.0) * st * jnp.sin(jnp.pi / 3.0 + t)
    e2 = -(4.0 / 3.0) * jnp.sin(tc) * jnp.cos(t)
    e3 = (4.0 / 3.0) * jnp.sin(tc) * jnp.sin(t + jnp.pi / 6.0)
    d32 = (2.0 / _SQRT3) * jnp.sin(2.0 * tc)
    d21 = (2.0 / _SQRT3) * jnp.sin(2.0 * t)
    d31 = (2.0 / _SQRT3) * jnp.sin(2.0 * jnp.pi / 3.0 - 2.0 * t)
    om3 = (4.0 / 3.0) * st * st
    return u1, u2, e2, e3, om3, d32, d21, d31


def complex_roots(b, kappa):
    """Real root $u_1 < 0$ and pair $m \\pm i n$ of $u^3 - u^2 + 1/b^2$ for $b < b_c$.

    Cardano's formula in the form without cancellation ($n \\propto \\sqrt{\\Delta}$
    directly, not as a difference).

    **Arguments:** `b` (units of R_S) and `kappa` $= 1 - b_c^2/b^2 < 0$.

    **Returns:** `u1, m - 2/3, n`.
    """
    c = 1.0 / (b * b)
    dc = -kappa / (B_CRIT * B_CRIT)  # c - 4/27 >= 0
    # floored so that the critical ray b = b_c (dc = 0) keeps a finite gradient
    sqrt_delta = 0.5 * jnp.sqrt(jnp.maximum(c * dc, jnp.finfo(c.dtype).tiny))
    w = 0.5 * dc + sqrt_delta
    a = _cbrt(1.0 / 27.0 + w)
    bb = 1.0 / (9.0 * a)
    u1 = 1.0 / 3.0 - a - bb
    a3 = 27.0 * w / (9.0 * a * a + 3.0 * a + 1.0)  # 3a - 1
    em = a3 * a3 / (18.0 * a)  # m - 2/3
    n = _SQRT3 * sqrt_delta / (a * a + 1.0 / 9.0 + bb * bb)
    return u1, em, n


def _integral_complex(x, y, dxy, xm, ym, u1, n, iterations):
    # int_y^x du / sqrt((u - u1)((u - m)^2 + n^2)), y < x, both > u1; dxy = x - y,
    # xm = x - m, ym = y - m, each passed in a form without cancellation.
    # Carlson's reduction with U_13 = conj(U_12); homogeneity takes out x - y.
    x1, y1 = jnp.sqrt(x - u1), jnp.sqrt(y - u1)
    xr, xi = _csqrt(xm, -n)
    yr, yi = _csqrt(ym, -n)
    ax, ay = _hypot(xm, n), _hypot(ym, n)  # |X2|^2, |Y2|^2
    v14 = x1 * ay + y1 * ax
    # V12 = x1 * X2 * conj(Y2) + y1 * Y2 * conj(X2)
    pr, pi_ = xr * yr + xi * yi, xi * yr - xr * yi  # X2 conj(Y2)
    vr, vi = (x1 + y1) * pr, (x1 - y1) * pi_
    rf = carlson_rf_conj(vr * vr - vi * vi, 2.0 * vr * vi, v14 * v14, iterations=iterations)
    return 2.0 * dxy * rf


def small_b_integral(x, y, dxy, b):
    """$\\int_y^x du / \\sqrt{1/b^2 - u^2 + u^3}$ for $b \\to 0$ (`dxy` = x - y); error O(b^5)."""
    return b * (dxy - 0.5 * b * b * ((x**4 - y**4) / 4.0 - (x**3 - y**3) / 3.0))


def _ray_start(alpha, distance, kappa=None):
    """What every closed form here reads of a ray at the camera: `(u0, omu0, e0, sa, ca,
    root, b, inward, small, sa_, b_, kappa)`: $u_0 = 1/D$, $1 - u_0$ and $u_0 - 2/3$
    without cancellation, $|\\sin\\alpha|$, $\\cos\\alpha$, $u_0\\sqrt{1 - u_0}$, the
    impact parameter $b$, whether the ray moves inward, whether $b$ is small (the
    series' branch), $\\sin\\alpha$ and $b$ sanitised there (so no inf/NaN reaches any
    gradient) and $\\kappa = 1 - b_c^2/b^2$ (`kappa` where the caller has it more
    accurately: `kappa_from_offset`)."""
    u0 = 1.0 / distance
    omu0 = (distance - 1.0) / distance  # 1 - u0 without cancellation next to the horizon
    # u0 - 2/3: exact near D = 1.5 in the first form, which overflows (3 D) for a far
    # camera, where the second loses nothing.
    e0 = jnp.where(distance < 4.0, (3.0 - 2.0 * distance) / (3.0 * distance), u0 - 2.0 / 3.0)
    sa, ca = jnp.abs(jnp.sin(alpha)), jnp.cos(alpha)
    root = u0 * jnp.sqrt(omu0)
    b = sa / root
    inward = ca > 0
    b_small = 1e-3 if alpha.dtype == jnp.float64 else 1e-2
    small = b < b_small
    # Sanitised inputs for the other branches, so no inf/NaN reaches any gradient.
    sa_ = jnp.where(small, 1.0, sa)
    b_ = jnp.where(small, 1.0, b)
    if kappa is None:
        # kappa = 1 - b_c^2 / b^2 in whichever of two forms loses less: through b, or
        # as (A - cos^2 alpha) / sin^2 alpha with A = (3u0 - 2)^2 (3u0 + 1) / 4, whose
        # two small parts cancel exactly for a camera near the photon sphere.
        a_ps = (3.0 * e0) ** 2 * (3.0 * u0 + 1.0) / 4.0
        use_e = jnp.maximum(a_ps, ca * ca) < sa * sa
        kappa_e = jnp.where(use_e, a_ps - ca * ca, 0.0) / jnp.where(use_e, sa_ * sa_, 1.0)
        # Each factor divided by b on its own: b^2 overflows for far cameras (b ~ D).
        kappa_b = ((b_ - B_CRIT) / b_) * ((b_ + B_CRIT) / b_)
        kappa = jnp.where(use_e, kappa_e, kappa_b)
    return u0, omu0, e0, sa, ca, root, b, inward, small, sa_, b_, kappa


def escape_angle(alpha, distance, *, iterations: int = 12, max_windings: float = 10.0,
                 _kappa=None):  # fmt: skip
    """Exact escape angle of rays from a static camera, via Carlson's $R_F$.

    **Arguments:**
    - `alpha`: local ray angle from the inward radial direction, radians in
      $[0, \\pi]$.
    - `distance`: camera radius $D > 1$, units of R_S. Broadcasts with `alpha`.
    - `iterations`: duplication steps of $R_F$ (accuracy control).
    - `max_windings`: rays whose swept azimuth exceeds $2\\pi$ times this are
      reported as unresolved.

    **Returns:** `(phi, status, r_min)`: the azimuth swept from the camera to the
    escaping asymptote (to the horizon for captured rays; radians), the status
    code (`ESCAPED`, `CAPTURED`, `UNRESOLVED`) and the smallest radius reached
    (units of R_S; 1 for captured rays).
    """
    # `_kappa`: $1 - b_c^2/b^2$ where the caller has it more accurately than `alpha`
    # gives it (from the offset to the shadow's edge, `kappa_from_offset`).
    alpha, distance = jnp.broadcast_arrays(alpha, distance)
    dtype = alpha.dtype
    u0, omu0, e0, sa, ca, root, b, inward, small, sa_, b_, kappa = _ray_start(
        alpha, distance, _kappa
    )
    turning = (kappa > 0) & ~small
    # Signed du/dphi at the camera: sqrt(G(u0)) = u0 sqrt(1 - u0) cot(alpha).
    sg = root * ca / sa_

    # --- b > b_c: three real roots; the ray passes a turning point or starts at one.
    kt = jnp.where(turning, kappa, 0.5)
    st = jnp.where(turning, B_CRIT / b_, 0.5)
    u1, u2, e2, e3, om3, d32, d21, d31 = real_roots(st, kt)
    outside = e0 < 0  # D > 1.5: the camera sits at u0 <= u2, else at u0 >= u3
    d_rp = jnp.where(outside, d21, d31)  # rho - u1
    q_end = jnp.where(outside, 2.0 / 3.0 + e3, 1.0 - 2.0 / 3.0 - e2)  # |end - q|
    end = jnp.where(outside, 0.0, 1.0)  # the asymptote or the horizon
    i_end = (
        2.0
        * jnp.sqrt(jnp.where(outside, u2, om3))  # sqrt|end - rho|
        * carlson_rf((end - u1) * d32, d_rp * d32, d_rp * q_end, iterations=iterations)
    )
    fac_q = jnp.where(outside, e3 - e0, e0 - e2)  # |q - u0|, no cancellation
    fac_q = jnp.where(turning, fac_q, 1.0)
    ys = sg / jnp.sqrt((u0 - u1) * fac_q)  # sqrt|u0 - rho|, signed as cos(alpha)
    j_cam = 2.0 * ys * carlson_rf((u0 - u1) * d32, d_rp * d32, d_rp * fac_q, iterations=iterations)
    phi_turn = jnp.where(outside, i_end + j_cam, i_end - j_cam)

    # --- b <= b_c: no turning point; out to the asymptote or in to the horizon.
    # b == b_c exactly and inward: the orbit winds onto the photon sphere for ever.
    critical = ~turning & ~small & inward & (kappa >= 0)
    free = ~turning & ~small & ~critical
    kf = jnp.where(free, kappa, -1.0)
    bf = jnp.where(free, b_, 0.5 * B_CRIT)
    v1, em, n = complex_roots(bf, kf)
    x = jnp.where(inward, 1.0, u0)
    y = jnp.where(inward, u0, 0.0)
    xm = jnp.where(inward, 1.0 / 3.0 - em, e0 - em)
    ym = jnp.where(inward, e0 - em, -2.0 / 3.0 - em)
    dxy = jnp.where(inward, omu0, u0)
    phi_free = _integral_complex(x, y, dxy, xm, ym, v1, n, iterations)
    phi_small = small_b_integral(x, y, dxy, b)

    phi = jnp.where(turning, phi_turn, jnp.where(small, phi_small, phi_free))
    captured = jnp.where(turning, ~outside, inward)
    cap = 2.0 * jnp.pi * max_windings
    unresolved = critical | ~(jnp.isfinite(phi) & (phi <= cap))
    phi = jnp.where(unresolved, cap, phi)
    status = jnp.where(unresolved, UNRESOLVED, jnp.where(captured, CAPTURED, ESCAPED))
    periapsis_r = 1.0 / jnp.where(turning, u2, 1.0)
    r_min = jnp.where(turning & outside & inward, periapsis_r, distance)
    r_min = jnp.where(captured, 1.0, r_min)
    return phi.astype(dtype), status.astype(jnp.int8), r_min.astype(dtype)


def darwin_deflection(b, *, iterations: int = 12):
    """Exact deflection of a ray from infinity back to infinity (Darwin 1959).

    **Arguments:** `b`: impact parameter $> b_c$ (units of R_S).

    **Returns:** total deflection $\\hat\\alpha = 2\\int_0^{u_2} du/\\sqrt{P} - \\pi$, radians.
    """
    b = length(b, "b")
    s = B_CRIT / b
    u1, u2, _, e3, _, d32, d21, _ = real_roots(s, (1.0 - s) * (1.0 + s))
    rf = carlson_rf(-u1 * d32, d21 * d32, d21 * (2.0 / 3.0 + e3), iterations=iterations)
    i = 2.0 * jnp.sqrt(u2) * rf
    return 2.0 * i - jnp.pi


def weak_field_deflection(b):
    """Weak-field series of the deflection: $2/b + (15\\pi/16)/b^2 + (16/3)/b^3$ (radians)."""
    b = length(b, "b")
    return 2.0 / b + (15.0 * jnp.pi / 16.0) / b**2 + (16.0 / 3.0) / b**3


def strong_field_deflection(b):
    """Strong-deflection limit (Bozza 2002) for $b \\to b_c^+$, radians."""
    b = length(b, "b")
    return -jnp.log(b / B_CRIT - 1.0) + math.log(216.0 * (7.0 - 4.0 * math.sqrt(3.0))) - jnp.pi


def grazing_angle(distance, radius):
    """Local angle (radians, below $\\pi/2$) of the ray from a static camera at
    `distance` $D$ whose periapsis is `radius` $R$ ($1.5 < R \\le D$, units of R_S):
    $\\sin\\alpha_R = (R/D)\\sqrt{R/(R-1)}\\sqrt{(D-1)/D}$, from $b = D\\sin\\alpha /
    \\sqrt{1 - 1/D}$ and $b^2 = R^3/(R-1)$. Rays nearer the hole's direction, outside
    the shadow, turn inside the sphere and cross it twice; those beyond miss it."""
    d, r = distance, radius
    s = (r / d) * jnp.sqrt(r / (r - 1.0)) * jnp.sqrt((d - 1.0) / d)
    return jnp.arcsin(jnp.clip(s, 0.0, 1.0))


def periapsis(b):
    """Periapsis radius $r_0$ of a ray with impact parameter $b > b_c$: $b^2 = r_0^3/(r_0-1)$."""
    b = length(b, "b")
    s = B_CRIT / b
    return 1.0 / real_roots(s, (1.0 - s) * (1.0 + s))[1]


class Crossings(NamedTuple):
    """Where rays from a static camera cross a sphere $r = R$ about the hole
    (`radius_crossings`).

    **Fields:**
    - `first`: the azimuth swept from the camera to the ray's first crossing
      (radians, in the ray's orbital plane; 0 where it has none).
    - `second`: the azimuth at its second crossing, after its turning point (radians;
      0 where it has none).
    - `count`: int8, how many times the ray crosses the sphere: 0, 1 or 2; -1 where
      the ray is unresolved (it winds onto the photon sphere, or beyond the winding
      budget). The camera's own position is not a crossing.
    """

    first: jax.Array
    second: jax.Array
    count: jax.Array


def _turning_integral(a_t, a1, a_q, d32, d_tp, iterations):
    # int du / sqrt|P| from a point u to the turning root t: 2 sqrt|u - t|
    # R_F((u - u1) d32, d_tp d32, d_tp |u - q|), from the point's factors a1 = sqrt(u -
    # u1), a_t = sqrt|u - t|, a_q = sqrt|u - q| (q: the other root of the pair) and
    # d_tp = t - u1.
    return 2.0 * a_t * carlson_rf(a1 * a1 * d32, d_tp * d32, d_tp * a_q * a_q,
                                  iterations=iterations)  # fmt: skip


def _segment_integral(x, y, dxy, iterations):
    # int_y^x du / sqrt|(u - u1)(u - u2)(u - u3)| between two points of one interval
    # where no root lies, from each point's factors (sqrt|u - u_i|, i = 1, 2, 3) and
    # dxy = |x - y|: Carlson's (1988) 2 |x - y| R_F(V12^2, V13^2, V14^2), with no
    # difference of two integrals (which cancels where the points are close).
    (x1, x2, x3), (y1, y2, y3) = x, y
    v12 = x1 * x2 * y3 + y1 * y2 * x3
    v13 = x1 * x3 * y2 + y1 * y3 * x2
    v14 = x1 * y2 * y3 + y1 * x2 * x3
    return 2.0 * dxy * carlson_rf(v12 * v12, v13 * v13, v14 * v14, iterations=iterations)


def _camera_gap(sg, u0, e0, u1, e3, tiny):
    """$\\sqrt{u_2 - u_0}$ of a camera outside the photon sphere, through `sg` $=
    \\sqrt{P(u_0)}$ (exact from its angle): `sg` $/ \\sqrt{(u_0 - u_1)(u_3 - u_0)}$
    (`e0`, `e3`: offsets from 2/3; floored at `tiny`)."""
    return sg / jnp.maximum(jnp.sqrt(u0 - u1) * jnp.sqrt(jnp.maximum(jnp.abs(e0 - e3), tiny)), tiny)


def _sphere_gap(u, e, u2, e2, tiny):
    """$\\sqrt{|u - u_2|}$ at a point $u$ (`e` $= u - 2/3$): from the offsets to 2/3
    where $u_2$ is near it (a ray near the photon sphere), else directly: in the far
    field both are small, and their offsets from 2/3 would keep only float32's 6e-8 of
    them absolutely. Floored at `tiny`, so that a point on the root keeps a finite
    derivative."""
    return jnp.sqrt(jnp.maximum(jnp.where(e2 > -1.0 / 3.0, jnp.abs(e - e2), jnp.abs(u2 - u)), tiny))


def radius_crossings(alpha, distance, radius, *, iterations: int = 12,
                     max_windings: float = 10.0, _kappa=None) -> Crossings:  # fmt: skip
    """Exact azimuths at which rays from a static camera cross the sphere $r = R$.

    A ray that passes a turning point (its periapsis, or for a camera inside the
    photon sphere its apoapsis) can cross the sphere twice: on its way to the turning
    point and after it; a ray with none crosses it at most once; a ray that turns
    before reaching $R$, or is captured first, never does. Each azimuth is a Carlson
    $R_F$ integral of $du / \\sqrt{u^3 - u^2 + 1/b^2}$ between the camera's $u = 1/D$
    and $1/R$ (through the turning point for a second crossing), as `escape_angle`'s
    are to $u = 0$. `radius = inf` gives `escape_angle`'s escaping rays (one crossing
    at their escape angle, bit for bit).

    **Arguments:**
    - `alpha`: local ray angle from the inward radial direction, radians in
      $[0, \\pi]$.
    - `distance`: camera radius $D > 1$ (units of R_S).
    - `radius`: the sphere's radius $R > 1$ (units of R_S; `inf`: the sky at
      infinity). Broadcasts with `alpha` and `distance`.
    - `iterations`, `max_windings`: as `escape_angle`'s.

    **Returns:** `Crossings(first, second, count)`.
    """
    alpha = angle(alpha, "alpha")
    distance = length(distance, "distance")
    radius = length(radius, "radius")
    alpha, distance, radius = jnp.broadcast_arrays(alpha, distance, radius)
    dtype = alpha.dtype
    at_infinity = jnp.isinf(radius)
    phi_inf, status_inf, _ = escape_angle(alpha, distance, iterations=iterations,
                                          max_windings=max_windings, _kappa=_kappa)  # fmt: skip
    rr = jnp.where(at_infinity, 2.0 * distance + 2.0, radius)  # finite stand-in
    first, second, count = finite_crossings(alpha, distance, rr, iterations=iterations,
                                            max_windings=max_windings, _kappa=_kappa)  # fmt: skip
    # The sky at infinity: `escape_angle`'s own values.
    escaped = status_inf == ESCAPED
    first = jnp.where(at_infinity, jnp.where(escaped, phi_inf, 0.0), first)
    second = jnp.where(at_infinity, 0.0, second)
    count_inf = jnp.where(status_inf == UNRESOLVED, -1, escaped.astype(jnp.int8))
    count = jnp.where(at_infinity, count_inf, count)
    return Crossings(first.astype(dtype), second.astype(dtype), count.astype(jnp.int8))


def finite_crossings(alpha, distance, rr, *, iterations: int = 12, max_windings: float = 10.0,
                     _kappa=None) -> Crossings:  # fmt: skip
    """`radius_crossings` for a finite radius `rr` (broadcast with the others): its
    own program, without `escape_angle`'s for the sky at infinity."""
    alpha, distance, rr = jnp.broadcast_arrays(alpha, distance, rr)
    dtype = alpha.dtype
    u0, omu0, e0, sa, ca, root, b, inward, small, sa_, b_, kappa = _ray_start(
        alpha, distance, _kappa
    )
    turning = (kappa > 0) & ~small
    ur = 1.0 / rr
    # u_R - u0 and u_R - 2/3, each without cancellation (as e0).
    d_ur = (distance - rr) / (distance * rr)
    er = jnp.where(rr < 4.0, (3.0 - 2.0 * rr) / (3.0 * rr), ur - 2.0 / 3.0)
    sg = jnp.abs(root * ca / sa_)  # sqrt(P(u0)) = u0 sqrt(1 - u0) |cot alpha|
    forward = jnp.where(inward, d_ur > 0, d_ur < 0)  # R lies ahead of the camera

    # --- b > b_c: the roots u1 < 0 < u2 <= u3; the ray lives in [0, u2] (a camera
    # outside the photon sphere, turning point u2) or in [u3, 1] (inside, u3).
    kt = jnp.where(turning, kappa, 0.5)
    st = jnp.where(turning, B_CRIT / b_, 0.5)
    u1, u2, e2, e3, _, d32, d21, d31 = real_roots(st, kt)
    outside = e0 < 0

    tiny = jnp.finfo(dtype).tiny

    def factors(u, e):  # sqrt|u - u_i| at a point, the turning root's left for later
        # (floored at tiny: a point on a root, whose factor is replaced or multiplies
        # zero, keeps a finite derivative, which `where` would otherwise turn to NaN)
        return (jnp.sqrt(u - u1), jnp.sqrt(jnp.maximum(jnp.abs(e - e2), tiny)),
                jnp.sqrt(jnp.maximum(jnp.abs(e - e3), tiny)))  # fmt: skip

    c1, c2, c3 = factors(u0, e0)
    # The camera's factor at its turning root, through sqrt(P(u0)) (exact from alpha).
    c2 = jnp.where(outside, _camera_gap(sg, u0, e0, u1, e3, tiny), c2)
    c3 = jnp.where(outside, c3, sg / jnp.maximum(c1 * c2, tiny))
    s1, _, s3 = factors(ur, er)
    s2 = _sphere_gap(ur, er, u2, e2, tiny)
    d_tp = jnp.where(outside, d21, d31)
    t_cam = _turning_integral(jnp.where(outside, c2, c3), c1, jnp.where(outside, c3, c2), d32,
                              d_tp, iterations)  # fmt: skip
    t_r = _turning_integral(jnp.where(outside, s2, s3), s1, jnp.where(outside, s3, s2), d32,
                            d_tp, iterations)  # fmt: skip
    seg = _segment_integral((c1, c2, c3), (s1, s2, s3), jnp.abs(d_ur), iterations)
    # Toward the turning point: inward outside it, outward inside it.
    toward = inward == outside
    # R within the ray's interval: below u2 outside, in [u3, 1) inside.
    reach = jnp.where(outside, er <= e2, (er >= e3) & (ur < 1.0))
    # Before the turning point: R ahead of the camera (either way the ray moves); after
    # it: for a ray moving toward it, anywhere in the interval.
    before = turning & reach & forward
    after = turning & reach & toward

    # --- b <= b_c (or b -> 0): no turning point; u moves one way, from u0 to u_R.
    critical = ~turning & ~small & inward & (kappa >= 0)
    free = ~turning & ~small & ~critical
    kf = jnp.where(free, kappa, -1.0)
    bf = jnp.where(free, b_, 0.5 * B_CRIT)
    v1, em, n = complex_roots(bf, kf)
    hi_u, lo_u = jnp.where(d_ur > 0, ur, u0), jnp.where(d_ur > 0, u0, ur)
    hi_e, lo_e = jnp.where(d_ur > 0, er, e0), jnp.where(d_ur > 0, e0, er)
    phi_free = _integral_complex(hi_u, lo_u, jnp.abs(d_ur), hi_e - em, lo_e - em, v1, n,
                                 iterations)  # fmt: skip
    phi_small = small_b_integral(hi_u, lo_u, jnp.abs(d_ur), b)
    once = ~turning & ~critical & forward & (ur < 1.0)

    first = jnp.where(turning, jnp.where(before, seg, t_cam + t_r),
                      jnp.where(small, phi_small, phi_free))  # fmt: skip
    second = jnp.where(turning & before & after, t_cam + t_r, 0.0)
    count = jnp.where(turning, before.astype(jnp.int8) + after.astype(jnp.int8),
                      once.astype(jnp.int8))  # fmt: skip
    cap = 2.0 * jnp.pi * max_windings
    unresolved = (critical & forward) | ~(jnp.isfinite(first) & (first <= cap))
    unresolved = unresolved | ((count == 2) & ~(jnp.isfinite(second) & (second <= cap)))
    count = jnp.where(unresolved, -1, count)
    first = jnp.where(count > 0, first, 0.0)
    second = jnp.where(count > 1, second, 0.0)
    return Crossings(first.astype(dtype), second.astype(dtype), count.astype(jnp.int8))


def kappa_from_offset(offset, alpha_sh):
    """$\\kappa = 1 - b_c^2/b^2$ of the ray at local angle $\\alpha_{sh}$ + `offset`
    (radians; negative inside the shadow) from a camera whose shadow angle is
    `alpha_sh`: $\\sin\\delta \\sin(2\\alpha_{sh} + \\delta) / \\sin^2\\alpha$, to full
    relative accuracy however small the offset (through $\\alpha$ itself, $\\kappa$
    keeps only eps / |offset| of it: 1e-4 for the fourth relativistic image at Sgr A*'s
    distance)."""
    a = alpha_sh + offset
    s = jnp.sin(a)
    return jnp.sin(offset) * jnp.sin(2.0 * alpha_sh + offset) / (s * s)


# Gauss-Legendre nodes and weights on [0, 1] for the smooth remainder of the travel
# time (`crossing_times`).
_GL_X, _GL_W = np.polynomial.legendre.leggauss(48)
_GL_X, _GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W


def _far_part(r):
    """$r + \\ln(r - 1)$, minus the antiderivative of $1/u^2 + 1/u + 1/(1 - u)$ at
    $u = 1/r$ (units of R_S)."""
    return r + jnp.log(r - 1.0)


def _remainder_to_turning(sw, d21, d32, b, dtype):
    """$\\int_u^{u_2} du' / (1 + b\\sqrt{P(u')})$ from a point $u$ below the turning
    root $u_2$ (`sw` $= \\sqrt{u_2 - u}$, computed without cancellation; $w$ = `sw`$^2$),
    with $u' = u_2 - w s^2$: $\\int_0^1 2 w s\\, ds / (1 + b s \\sqrt{w (d_{21} - w
    s^2)(d_{32} + w s^2)})$, smooth in $s$, by Gauss-Legendre."""
    s = jnp.asarray(_GL_X, dtype)
    ws = jnp.asarray(_GL_W, dtype)
    sw_, d21_, d32_, b_ = (v[..., None] for v in (sw, d21, d32, b))
    w_ = sw_ * sw_
    w2 = w_ * s * s
    f = 2.0 * w_ * s / (1.0 + b_ * s * sw_ * jnp.sqrt((d21_ - w2) * (d32_ + w2)))
    return jnp.sum(ws * f, axis=-1)


def _remainder_between(lo, hi, b, dtype):
    """$\\int_{lo}^{hi} du / (1 + b\\sqrt{P(u)})$ where $P > 0$ on the whole interval
    (no turning point in it), by Gauss-Legendre in $u$."""
    x = jnp.asarray(_GL_X, dtype)
    ws = jnp.asarray(_GL_W, dtype)
    lo_, hi_, b_ = (v[..., None] for v in (lo, hi, b))
    u = lo_ + (hi_ - lo_) * x
    q = jnp.maximum(1.0 - b_ * b_ * u * u * (1.0 - u), 0.0)  # b^2 P
    return (hi - lo) * jnp.sum(ws / (1.0 + jnp.sqrt(q)), axis=-1)


def crossing_times(alpha, distance, radius, *, iterations: int = 12, _kappa=None):
    """Coordinate time light takes from the sphere $r = R$ to a static camera at $r = D$
    along each ray's first and second crossing (`radius_crossings`), less the part every
    ray to those two radii shares (units of R_S/c).

    Along a null geodesic $t = b\\,\\Phi + W$ (Hamilton-Jacobi: the radial action $W$ is
    homogeneous of degree one in energy and angular momentum), with $\\Phi$ the exact
    crossing azimuth and $W = \\int \\sqrt{1 - b^2u^2(1-u)} / (u^2(1-u))\\, du$ along
    the path. The integrand is $1/u^2 + 1/u + 1/(1-u) - b^2/(1 + b\\sqrt{P})$: the
    first three integrate in closed form (they carry the divergence at $u \\to 0$ and
    $D + \\ln(D-1) + R + \\ln(R-1)$, which is subtracted), the last is bounded and
    smooth after $u = u_2 - w s^2$ at a turning point, and is summed by 48-point
    Gauss-Legendre. Near the photon sphere, where a ray winds, the time is carried by
    $b\\,\\Phi$, so every winding order keeps the closed form's accuracy.

    Differences between rays to the same two points (images of one source) are the
    time delays; the subtracted part cancels in them. `radius = inf`: the time less
    $D + \\ln(D-1)$ and the infinite $R + \\ln(R-1)$; the differences are the delays
    between images of a source at infinity (a plane wave).

    **Arguments:** as `radius_crossings`' (`alpha` radians, `distance` $D > 1.5$,
    `radius` $R > 1$ or `inf`, units of R_S).

    **Returns:** `(first, second)`: the reduced times of the two crossings (units of
    R_S/c; `nan` where the ray has no such crossing). float32 keeps about
    $10^{-7} b$ of them absolutely ($b$ the impact parameter).
    """
    alpha, distance, radius = jnp.broadcast_arrays(alpha, distance, radius)
    dtype = alpha.dtype
    far = jnp.isinf(radius)
    rr = jnp.where(far, 2.0 * distance + 2.0, radius)
    c = radius_crossings(alpha, distance, radius, iterations=iterations, max_windings=1e6,
                         _kappa=_kappa)  # fmt: skip
    u0, omu0, e0, sa, ca, root, b, inward, small, sa_, b_, kappa = _ray_start(
        alpha, distance, _kappa
    )
    turning = (kappa > 0) & ~small & (e0 < 0)
    ur = jnp.where(far, 0.0, 1.0 / rr)
    er = jnp.where(rr < 4.0, (3.0 - 2.0 * rr) / (3.0 * rr), ur - 2.0 / 3.0)
    kt = jnp.where(turning, kappa, 0.5)
    st = jnp.where(turning, B_CRIT / b_, 0.5)
    u1, u2, e2, e3, _, d32, d21, _ = real_roots(st, kt)
    tiny = jnp.finfo(dtype).tiny
    sw0 = _camera_gap(jnp.abs(root * ca / sa_), u0, e0, u1, e3, tiny)
    j0 = _remainder_to_turning(sw0, d21, d32, b_, dtype)
    jr = _remainder_to_turning(_sphere_gap(ur, er, u2, e2, tiny), d21, d32, b_, dtype)
    # A(u) = -(r + ln(r - 1)) at the camera, the sphere and the periapsis.
    a0 = -_far_part(distance)
    ar = jnp.where(far, 0.0, -_far_part(rr))
    r0 = 1.0 / jnp.where(turning, u2, 1.0)
    a2 = -_far_part(jnp.where(turning, r0, 2.0))
    # Between the camera and the sphere without a turning point (b <= b_c, or a ray
    # moving away from its turning point, or before it reaches it).
    lo, hi = jnp.minimum(u0, ur), jnp.maximum(u0, ur)
    direct = jnp.where(turning, jnp.abs(j0 - jr), _remainder_between(lo, hi, b, dtype))
    a_end = jnp.where(ur > u0, ar, a0)  # the nearer of the two to the hole
    t_direct = b * c.first + 2.0 * a_end - b * b * direct
    t_after_first = b * c.first + 2.0 * a2 - b * b * (j0 + jr)
    t_after_second = b * c.second + 2.0 * a2 - b * b * (j0 + jr)
    # Which crossing is after the turning point: the second where there are two, the
    # first where the sphere lies beyond the camera's radius on an inward ray.
    first_after = turning & inward & (ur <= u0)
    first = jnp.where(first_after, t_after_first, t_direct)
    first = jnp.where(c.count > 0, first, jnp.nan)
    second = jnp.where(c.count > 1, t_after_second, jnp.nan)
    return first.astype(dtype), second.astype(dtype)


class PlaneCrossings(NamedTuple):
    """Where rays from a static camera cross the plane $z = L$ behind the hole, on
    their way out (`plane_crossings`).

    **Fields:** `phi`: the azimuth swept from the camera to the crossing point, in the
    ray's orbital plane (radians: the point lies in the direction at `phi` from the
    hole->camera axis, a sky direction as for a sky at infinity); `radius`: its distance
    from the hole (units of R_S); `hit`: whether the ray crosses the plane outward (it
    escapes, its asymptote heads behind the hole, and Newton's iteration converged).
    Where `hit` is false both values are 0.
    """

    phi: jax.Array
    radius: jax.Array
    hit: jax.Array


def plane_crossings(alpha, distance, plane_distance, *, steps: int = 12) -> PlaneCrossings:
    """Exact outward crossings of the plane $z = L$ (perpendicular to the line of sight,
    `plane_distance` $L$ behind the hole) by rays from a static camera at `distance`.

    The point where a ray leaves through the plane lies on the sphere of some radius
    $R$, at the azimuth $\\varphi_R$ of the ray's outward crossing of that sphere
    (`radius_crossings`: its only crossing for $R \\ge D$, its second for $R < D$);
    Newton's method solves $-R\\cos\\varphi_R = L$ for $R$ (the slope from
    $d\\varphi/dr = u^2/\\sqrt{1/b^2 - u^2 + u^3}$, $u = 1/r$), from the point where
    the ray's asymptote, taken through the hole's centre, meets the plane: what
    `PlaneImage.at_distance` reads.
    The direction from the hole to that point, given to a `PlaneImage.at_distance` of
    the same $L$, is the picture's exact point (its gnomonic projection is the plane's).

    **Arguments:** `alpha` (local angle, radians), `distance` $D > 1$ and
    `plane_distance` $L > 0$ (units of R_S), broadcasting; `steps` (static): Newton
    steps (the iteration converges quadratically from an error of order $b/L$).

    **Returns:** `PlaneCrossings(phi, radius, hit)`.
    """
    alpha = angle(alpha, "alpha")
    distance = length(distance, "distance")
    plane_distance = length(plane_distance, "plane_distance")
    alpha, d, plane = jnp.broadcast_arrays(
        *(jnp.asarray(v, jnp.result_type(float, alpha, distance, plane_distance))
          for v in (alpha, distance, plane_distance))
    )  # fmt: skip
    phi_inf, status, r_min = escape_angle(alpha, d)
    heads_behind = (status == ESCAPED) & (jnp.cos(phi_inf) < 0)
    c0 = jnp.where(heads_behind, -jnp.cos(phi_inf), 1.0)
    # The crossing of the outgoing branch lies beyond the periapsis.
    floor = r_min * (1.0 + 1e-6)

    def crossing(r):  # the azimuth of the outward crossing of r = R
        c = finite_crossings(alpha, d, r)
        return jnp.where(r >= d, c.first, c.second)

    inv_b2 = 1.0 / impact_parameter(alpha, d) ** 2

    def step(_, r):
        phi = crossing(r)
        # On the way out d(phi)/dr = u^2 / sqrt(G(u)), G = 1/b^2 - u^2 + u^3, u = 1/r.
        u = 1.0 / r
        dphi = u * u / jnp.sqrt(jnp.maximum(inv_b2 - u * u * (1.0 - u), jnp.finfo(u.dtype).tiny))
        z = -r * jnp.cos(phi)
        dz = -jnp.cos(phi) + r * jnp.sin(phi) * dphi
        new = r - (z - plane) / jnp.where(dz > 0, dz, 1.0)
        return jnp.where(heads_behind & (dz > 0), jnp.maximum(new, floor), r)

    r = jnp.maximum(plane / c0, floor)
    r = jax.lax.fori_loop(0, steps, step, r)
    phi = crossing(r)
    tol = 1e4 * jnp.finfo(r.dtype).eps  # relative: 2e-12 in float64, 1e-3 in float32
    hit = heads_behind & (jnp.abs(-r * jnp.cos(phi) - plane) <= tol * jnp.maximum(plane, r))
    return PlaneCrossings(jnp.where(hit, phi, 0.0), jnp.where(hit, r, 0.0), hit)
