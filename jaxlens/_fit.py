"""Fit the black hole to an observed Einstein ring: autodiff of a forward model, optimistix.

The observation model: a static pinhole camera at distance $D$ (units of R_S) looks
straight at the hole with horizontal field of view FOV; one star sits exactly behind
the hole at infinity, Gaussian in angular distance $d$ on the sky,
$I = A e^{-d^2 / 2\\sigma^2}$; a uniform sky level `floor` lies behind everything;
captured rays are 0; pixels are area-averaged; the noise is additive.

The model image is radially symmetric, so each area sample needs only its local angle
$\\alpha$: the escape angle comes from an `EscapeTable` of the distance (differentiable
with respect to $D$), the angular distance from the source is
$|(\\Phi \\bmod 2\\pi) - \\pi|$, and samples that straddle the shadow edge are weighted
by the exact fraction of their square footprint outside the (locally straight) edge, so
the edge contributes gradient with respect to $D$ and FOV. `optimistix.least_squares`
with Levenberg-Marquardt then solves for $\\log(D - 1.5)$,
$\\operatorname{logit}(\\mathrm{FOV}/\\pi)$, $\\log\\sigma$, $A$, the floor and the
relativistic rings' flux factor; standard errors come from the Gauss-Newton curvature
$J^T J$ and the residual variance.
"""

import functools
import math
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from ._exact import shadow_angle
from ._io import read_pixels
from ._trace import exact_for

# ----------------------------------------------------------------------------- units

GM_SUN = 1.3271244e20  # IAU 2015 nominal solar mass parameter, m^3 / s^2
C_LIGHT = 299792458.0  # m / s
RS_SUN_M = 2.0 * GM_SUN / C_LIGHT**2  # Schwarzschild radius of one solar mass: 2953.25 m


def schwarzschild_radius_m(mass_msun: ArrayLike):
    """Schwarzschild radius $2GM/c^2$ in metres of a mass in solar masses."""
    return RS_SUN_M * mass_msun


def distance_in_metres(distance: ArrayLike, mass_msun: ArrayLike):
    """Camera distance in metres, from the distance in units of R_S and the mass of the
    hole in solar masses."""
    return distance * schwarzschild_radius_m(mass_msun)


def mass_from_distance(distance: ArrayLike, distance_m: ArrayLike):
    """Mass of the hole in solar masses, from the camera distance in units of R_S and
    the same distance in metres."""
    return distance_m / (distance * RS_SUN_M)


# ------------------------------------------------------------- exact ring relations

_D_MIN = 1.5  # the camera sees a ring in front of it only outside the photon sphere


def einstein_ring_angle(distance: ArrayLike) -> Float[Array, "..."]:
    """Angle of the primary Einstein ring from the direction of the hole, radians.

    The local angle $\\alpha_E$ at which a static camera at `distance` (units of R_S,
    $D > 1.5$, any shape) sees a source exactly behind the hole at infinity:
    $\\Phi(\\alpha_E) = \\pi$, solved on an `EscapeTable` of the exact escape angle
    (error below $10^{-10}$ rad against `trace`). Works under `jit`, `vmap` and `grad`
    (the derivative is that of the implicit function). NaN where the ring lies beyond
    $\\pi/2$ (cameras with $D \\lesssim 1.9$): no pinhole camera sees it.

    **Returns:** $\\alpha_E$ (radians), e.g. 29.8283 deg at $D = 10$;
    $\\approx\\sqrt{2/D}$ for $D \\gg 1$.
    """

    def one(d):
        table = EscapeTable.build(d)
        visible = (d > _D_MIN) & (table.escape_angle(0.5 * jnp.pi) < jnp.pi)
        return jnp.where(visible, table.solve(jnp.pi)[0], jnp.nan)

    d = jnp.asarray(distance, jnp.result_type(float, distance))
    return jnp.vectorize(one)(d)


@functools.cache
def _ring_table():
    """$\\alpha_E$, $\\alpha_{sh}$ and $d\\Phi/d\\alpha$ at $\\alpha_E$ on a grid of camera
    distances $1.9 \\dots 10^5$, for the starting values (numpy, once a process)."""
    with jax.enable_x64(True):
        d = np.geomspace(1.9, 1e5, 49)

        @jax.jit
        @jax.vmap
        def one(d):
            table = EscapeTable.build(d, knots=2048)
            a, slope = table.solve(jnp.pi)
            ok = table.escape_angle(0.5 * jnp.pi) < jnp.pi
            return jnp.where(ok, a, jnp.nan), table.alpha_sh, slope

        a, sh, slope = (np.asarray(v) for v in one(jnp.asarray(d)))
    ok = np.isfinite(a) & (a < math.radians(88.0))
    return d[ok], a[ok], sh[ok], slope[ok]


# ---------------------------------------------------------------------- forward model


class EscapeTable(eqx.Module):
    """Escape angle $\\Phi(\\alpha)$ of one camera distance, tabulated for the ring fit.

    Values of `trace` on a grid uniform in $\\tau = \\ln(\\alpha - \\alpha_{sh})$ from
    $10^{-10}\\alpha_{sh}$ to $\\pi/2$ (a pinhole camera sees nothing wider), read back by
    four-point Lagrange interpolation in $\\tau$ and, below the first knot, the
    logarithmic law (linear in $\\tau$). Unlike `RayMap` (cubic Hermite with slopes from
    forward-mode autodiff), the table holds values only, so its derivative with respect
    to the distance is first-order autodiff of the closed form: the Levenberg-Marquardt
    program that differentiates it compiles in a quarter of the time (45 s against 190 s
    measured on a 2-core CPU).

    **Fields:** `distance` (units of R_S), `alpha_sh` (shadow angle, radians), the knot
    grid `tau0`, `dtau` and the knot values `phi` (radians).
    """

    distance: Float[Array, ""]
    alpha_sh: Float[Array, ""]
    tau0: Float[Array, ""]
    dtau: Float[Array, ""]
    phi: Float[Array, " n"]

    @classmethod
    def build(cls, distance: ArrayLike, *, knots: int = 4096) -> "EscapeTable":
        """Tabulate $\\Phi$ for a camera at `distance` ($D > 1.5$, units of R_S, scalar);
        `knots` values (4096: interpolation error below 2e-10 rad from $10^{-4}\\alpha_{sh}$
        beyond the edge out, measured against `trace` at D = 5, 20, 1000; nearer the
        edge the closed form itself is conditioned to ~1e-16 / relative gap)."""
        d = jnp.asarray(distance, jnp.result_type(float, distance))
        a_sh = shadow_angle(d)
        tau0 = jnp.log(1e-10 * a_sh)
        tau1 = jnp.log(0.5 * jnp.pi - a_sh) + 1e-3
        dtau = (tau1 - tau0) / (knots - 1)
        tau = tau0 + dtau * jnp.arange(knots, dtype=d.dtype)
        # The exact method of `trace` at its 1e-10 rad setting, called directly: the
        # distance is > 1.5 by construction, and `trace`'s check of it is a host
        # callback, which keeps XLA's persistent cache from storing the fit's programs.
        phi = exact_for(1e-10)(a_sh + jnp.exp(tau), d, 1e6).phi
        return cls(d, a_sh, tau0, dtau, phi)

    def _locate(self, s):
        n = self.phi.shape[0]
        i = jnp.clip(jnp.floor(s).astype(jnp.int32), 1, n - 3)
        p = jnp.stack([self.phi[i - 1], self.phi[i], self.phi[i + 1], self.phi[i + 2]])
        return i, s - i, p

    def escape_angle(self, alpha: ArrayLike) -> Float[Array, "..."]:
        """Interpolated escape angle (radians) at local angles `alpha` (radians); finite
        everywhere, meaningful outside the shadow."""
        alpha = jnp.asarray(alpha, self.phi.dtype)
        gap = alpha - self.alpha_sh
        gap0 = jnp.exp(self.tau0)
        gap_ = jnp.where(gap > gap0, gap, gap0)
        _, t, p = self._locate((jnp.log(gap_) - self.tau0) / self.dtau)
        inside = _lagrange(p, t)
        low = jnp.where(gap > 0, gap, gap0)
        below = self.phi[0] + (self.phi[1] - self.phi[0]) * (jnp.log(low) - self.tau0) / self.dtau
        return jnp.where(gap < gap0, below, inside)

    def solve(self, target: ArrayLike):
        """Where the escape angle equals `target` (radians, scalar, within the table):
        the knot interval by search, then three Newton steps on the interpolant
        (differentiable: their derivative is that of the implicit function).

        **Returns:** `(alpha, dphi_dalpha)`, radians and its slope there.
        """
        target = jnp.asarray(target, self.phi.dtype)
        fixed = jax.lax.stop_gradient(self.phi)
        j = jnp.sum(fixed >= target) - 1  # phi decreases: phi[j] >= target > phi[j + 1]
        i, _, p = self._locate(j.astype(self.phi.dtype))
        pf = jax.lax.stop_gradient(p)
        t = jax.lax.stop_gradient((pf[1] - target) / (pf[1] - pf[2]))
        for _ in range(3):
            t = t - (_lagrange(p, t) - target) / _lagrange_slope(p, t)
        gap = jnp.exp(self.tau0 + (i + t) * self.dtau)
        return self.alpha_sh + gap, _lagrange_slope(p, t) / (self.dtau * gap)


def _lagrange(p, t):
    """Cubic through `p` at nodes -1, 0, 1, 2, at `t`."""
    t2, t3 = t * t, t * t * t
    return (
        -(t3 - 3.0 * t2 + 2.0 * t) / 6.0 * p[0]
        + (t3 - 2.0 * t2 - t + 2.0) / 2.0 * p[1]
        - (t3 - t2 - 2.0 * t) / 2.0 * p[2]
        + (t3 - t) / 6.0 * p[3]
    )


def _lagrange_slope(p, t):
    """Derivative in `t` of `_lagrange`."""
    t2 = t * t
    return (
        -(3.0 * t2 - 6.0 * t + 2.0) / 6.0 * p[0]
        + (3.0 * t2 - 4.0 * t - 1.0) / 2.0 * p[1]
        - (3.0 * t2 - 2.0 * t - 2.0) / 2.0 * p[2]
        + (3.0 * t2 - 1.0) / 6.0 * p[3]
    )


def _trapezoid(a, c):
    """Half-widths and heights of the trapezoid density of the coordinate across a
    straight edge of a rectangular footprint, with extents `a`, `c` (pixels) along the
    edge normal (the sum of two uniform variables of widths `a` and `c`)."""
    p, q = jnp.maximum(a, c), jnp.minimum(a, c)
    return 0.5 * (p + q), 0.5 * (p - q), p, jnp.maximum(q, 1e-12 * p)


def _edge_cover(t, a, c):
    """Fraction of a rectangular footprint outside a straight edge: the CDF of the
    trapezoid at the signed distance `t` (pixels) of the footprint centre outside it."""
    h1, h2, p, q = _trapezoid(a, c)
    lower = (t + h1) ** 2 / (2.0 * p * q)
    upper = 1.0 - (h1 - t) ** 2 / (2.0 * p * q)
    inner = jnp.where(t < -h2, lower, jnp.where(t > h2, upper, 0.5 + t / p))
    return jnp.where(t <= -h1, 0.0, jnp.where(t >= h1, 1.0, inner))


def _edge_density(t, a, c):
    """Density (1/pixels) of the same trapezoid at offset `t`: the share of the
    footprint that a thin ring at that offset crosses, per unit ring width."""
    h1, h2, p, q = _trapezoid(a, c)
    at = jnp.abs(t)
    return jnp.where(at >= h1, 0.0, jnp.where(at > h2, (h1 - at) / (p * q), 1.0 / p))


def _chunks(n_pix: int, k: int, chunk_samples: int) -> tuple[int, int]:
    per = max(1, chunk_samples // (k * k))
    # At least two chunks: XLA removes a loop of one trip and then fuses the table's
    # producer into every per-sample gather (measured 30x slower).
    chunks = max(2, -(-n_pix // per))
    return chunks, -(-n_pix // chunks)


def _quadrature(k: int):
    """Gauss-Legendre nodes and weights on [0, 1], and the cells they stand for (the
    weights laid end to end, which tile the interval): a pixel average with k x k nodes
    is exact for polynomials of degree 2k - 1 in each direction (a Gaussian ring one
    pixel wide: error 7e-6 of its peak with k = 3, against 4e-3 for k x k point
    samples)."""
    x, w = np.polynomial.legendre.leggauss(k)
    edges = np.concatenate([[0.0], np.cumsum(0.5 * w)])
    return 0.5 * (x + 1.0), 0.5 * w, 0.5 * (edges[1:] + edges[:-1])


# Images of order n >= 1 (Phi = 3 pi, 5 pi, ...) hug the shadow edge in rings a tiny
# fraction of a pixel wide (radial width ~ e^{-2 pi n} of the primary's): point samples
# alias them, so they enter as thin rings of their exact integrated flux instead.
_THIN_ORDERS = (1, 2)


def _thin_rings(table, focal, sigma):
    """Radius (pixels) and radially integrated intensity per unit peak brightness
    (pixels) of the images of order 1 and 2: at $\\Phi_n = (2n+1)\\pi$ the ring has
    $\\int e^{-d^2/2\\sigma^2} d\\rho = \\sqrt{2\\pi}\\,\\sigma\\,|d\\rho/d\\Phi|$."""
    targets = jnp.asarray([(2 * n + 1) * math.pi for n in _THIN_ORDERS], table.phi.dtype)
    # A loop over the orders (not a Python loop): the table enters it once, materialised,
    # instead of XLA duplicating its producer into every gather (3x the compile time).
    a, slope = jax.lax.map(table.solve, targets)
    radius = focal * jnp.tan(a)
    return radius, math.sqrt(2.0 * math.pi) * sigma * focal / (jnp.cos(a) ** 2 * jnp.abs(slope))


def _pixel_basis(table, focal, sigma, x0, y0, *, block, k, chunk_samples=1 << 16):
    """Per-pixel area averages of the two basis images: the star's light (unit peak
    brightness) and the floor's coverage.

    Each pixel is split into the $k \\times k$ cells of a Gauss-Legendre rule. The
    primary image (smooth) is evaluated at the nodes; the shadow edge enters through
    the exact fraction of each cell outside it (locally straight edge) and the images
    of order $\\ge 1$ through the share of each cell their thin rings cross, so all three
    are continuous in $D$ and FOV.

    **Arguments:** `table` (an `EscapeTable` of the distance), `focal` (pixels of the
    full image), `sigma` (radians), `x0`, `y0`: left and top edges of each (binned)
    pixel in full-image pixels from the image centre ($x$ right, $y$ up); `block`: side
    of a pixel in full-image pixels; `k`: the rule's order.

    **Returns:** `(g, t, c)` of the shape of `x0`: the primary image, the images of
    order 1 and 2 (both per unit peak brightness) and the floor's coverage.
    """
    shape = x0.shape
    x0, y0 = x0.ravel(), y0.ravel()
    n = x0.shape[0]
    chunks, per = _chunks(n, k, chunk_samples)
    pad = chunks * per - n
    x0 = jnp.pad(x0, (0, pad)).reshape(chunks, per)
    y0 = jnp.pad(y0, (0, pad)).reshape(chunks, per)
    dtype = table.phi.dtype
    node, weight, centre = (jnp.asarray(v * block, dtype) for v in _quadrature(k))
    w2 = (weight[:, None] * weight[None, :]) / block**2
    rho_sh = focal * jnp.tan(table.alpha_sh)
    a_edge = table.alpha_sh + jnp.exp(table.tau0)
    ring_r, ring_f = _thin_rings(table, focal, sigma)

    def grid(xb, yb, u):
        x = xb[:, None, None] + u[None, :, None] + jnp.zeros((1, 1, k), dtype)
        y = yb[:, None, None] - u[None, None, :] + jnp.zeros((1, k, 1), dtype)
        return x, y

    def one(xy):
        xb, yb = xy
        # Cells: coverage of the edge and crossings of the thin rings.
        x, y = grid(xb, yb, centre)
        rho = jnp.hypot(x, y)
        safe = rho > 0
        r_ = jnp.where(safe, rho, 1.0)
        ext_x = weight[None, :, None] * jnp.abs(jnp.where(safe, x / r_, 1.0))
        ext_y = weight[None, None, :] * jnp.abs(jnp.where(safe, y / r_, 0.0))
        cover = _edge_cover(rho - rho_sh, ext_x, ext_y)
        thin = sum(f * _edge_density(r - rho, ext_x, ext_y) for r, f in zip(ring_r, ring_f))
        # Nodes: the primary image, the Gaussian in |Phi - pi|.
        x, y = grid(xb, yb, node)
        alpha = jnp.maximum(jnp.arctan2(jnp.hypot(x, y), focal), a_edge)
        dist = table.escape_angle(alpha) - jnp.pi
        primary = jnp.exp(-0.5 * (dist / sigma) ** 2)
        sums = (w2 * cover * primary, w2 * thin, w2 * cover)
        return tuple(jnp.sum(v, axis=(1, 2)) for v in sums)

    out = jax.lax.map(one, (x0, y0))
    return tuple(v.reshape(-1)[:n].reshape(shape) for v in out)


def _pixel_edges(width: int, height: int, block: int, dtype):
    """Left/top edges (full-image pixels from the centre) of the `block` x `block`
    bins of a `width` x `height` image, centred crop when the size does not divide."""
    wb, hb = width // block, height // block
    c0, r0 = (width - wb * block) // 2, (height - hb * block) // 2
    x0 = c0 + block * jnp.arange(wb, dtype=dtype) - 0.5 * width
    y0 = 0.5 * height - (r0 + block * jnp.arange(hb, dtype=dtype))
    return jnp.broadcast_to(x0[None, :], (hb, wb)), jnp.broadcast_to(y0[:, None], (hb, wb))


def ring_image(
    distance: ArrayLike,
    fov: ArrayLike,
    width: int,
    height: int,
    *,
    sigma: ArrayLike,
    brightness: ArrayLike = 1.0,
    floor: ArrayLike = 0.0,
    ring_flux: ArrayLike = 1.0,
    supersample: int = 4,
) -> Float[Array, "H W"]:
    """The observation model: the single-channel image of a Gaussian star exactly behind
    the hole over a uniform floor, as the fit sees it.

    A pure function of its array arguments: works under `jit`, `vmap` and `grad`
    (forward and reverse mode) with respect to `distance`, `fov`, `sigma`, `brightness`,
    `floor` and `ring_flux`. Pixel (column $i$, row $j$) spans $x \\in [i - W/2, i + 1 - W/2]$,
    $y \\in [H/2 - j - 1, H/2 - j]$ on the image plane at focal length
    $f = (W/2) / \\tan(\\mathrm{FOV}/2)$ (row 0 at the top); its local angle from the
    hole is $\\alpha = \\arctan(\\sqrt{x^2 + y^2} / f)$. Each pixel is the area average by
    $k \\times k$ Gauss-Legendre nodes, the nodes straddling the shadow edge weighted by
    their exact footprint coverage (so the edge contributes gradient).

    **Arguments:**
    - `distance`: camera radius $D > 1.5$ (units of R_S).
    - `fov`: horizontal field of view (radians).
    - `width`, `height`: image size (pixels, static).
    - `sigma`: the star's Gaussian width in angular distance (radians).
    - `brightness`: peak radiance $A$ of the star; `floor`: the uniform sky level.
    - `ring_flux`: factor on the flux of the relativistic rings (images of order 1 and
      2); 1 is the exact area average, as `RingFit.ring_flux` reports it.
    - `supersample`: $k$ (static).

    **Returns:** linear intensity `(height, width)`; captured rays are 0.
    """
    distance = jnp.asarray(distance, jnp.result_type(float, distance))
    dtype = distance.dtype
    table = EscapeTable.build(distance)
    focal = 0.5 * width / jnp.tan(0.5 * jnp.asarray(fov, dtype))
    x0, y0 = _pixel_edges(width, height, 1, dtype)
    g, t, c = _pixel_basis(
        table, focal, jnp.asarray(sigma, dtype), x0, y0, block=1, k=int(supersample)
    )
    return brightness * (g + ring_flux * t) + floor * c


# ------------------------------------------------------------------ parametrisation


class _Setup(eqx.Module):
    """Static description of one least-squares problem: pixels of side `block` (full-
    image pixels) with a k x k rule, and optionally a second, coarser set of side
    `coarse` with `k_coarse` (`coarse` = 0: none)."""

    half_width: float = eqx.field(static=True)  # W/2 of the full image, pixels
    block: int = eqx.field(static=True)
    k: int = eqx.field(static=True)
    knots: int = eqx.field(static=True)
    fit_sigma: bool = eqx.field(static=True)
    coarse: int = eqx.field(static=True, default=0)
    k_coarse: int = eqx.field(static=True, default=2)


# The flux of the relativistic rings (order 1 and 2, radially a few thousandths of a
# pixel wide) is a nuisance factor `ring_flux` (1: the exact area average), with a
# Gaussian prior of this standard deviation about 1. Renderers that point-sample pixels
# alias these rings (k = 12 samples a pixel gave 55 % of the exact flux at D = 17, in a
# moire pattern), and a fit that trusted their flux was pulled 5 % in D on such images
# when sigma was fitted and no floor was seen; their positions, which fix D
# against the primary ring's radius, are still used.
_RING_FLUX_PRIOR = 1.0


def _unpack(theta, fixed_sigma, scale, setup: _Setup):
    """Internal parameters -> (D, fov, sigma, A, floor, ring_flux)."""
    d = _D_MIN + jnp.exp(theta[0])
    fov = jnp.pi * jax.nn.sigmoid(theta[1])
    if setup.fit_sigma:
        sigma, rest = jnp.exp(theta[2]), theta[3:]
    else:
        sigma, rest = fixed_sigma, theta[2:]
    return d, fov, sigma, rest[0] * scale, rest[1] * scale, rest[2]


def _pack(d, fov, sigma, a, floor, scale, fit_sigma):
    """(D, fov, sigma, A, floor) -> internal parameters, ring_flux starting at 1."""
    v = [math.log(d - _D_MIN), math.log(fov / (math.pi - fov))]
    if fit_sigma:
        v.append(math.log(sigma))
    return np.asarray(v + [a / scale, floor / scale, 1.0])


def _model(theta, args, setup: _Setup):
    """Model pixel values / scale: the fine pixels, then the coarse ones (if any)."""
    (x0, y0), coarse, _, _, fixed_sigma, scale = args[:6]
    d, fov, sigma, a, floor, ring_flux = _unpack(theta, fixed_sigma, scale, setup)
    table = EscapeTable.build(d, knots=setup.knots)
    focal = setup.half_width / jnp.tan(0.5 * fov)
    g, t, c = _pixel_basis(table, focal, sigma, x0, y0, block=setup.block, k=setup.k)
    if setup.coarse:
        gc, tc, cc = _pixel_basis(
            table, focal, sigma, *coarse, block=setup.coarse, k=setup.k_coarse
        )
        g, t, c = (jnp.concatenate(v) for v in ((g, gc), (t, tc), (c, cc)))
    return (a * (g + ring_flux * t) + floor * c) / scale


def _positive_part(u, s):
    """$E[(u + n)_+]$ for $n \\sim N(0, s^2)$: $u\\,\\Phi(u/s) + s\\,\\varphi(u/s)$."""
    z = u / s
    return u * jax.scipy.special.ndtr(z) + s * jnp.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)


def clipped_mean(m, lo, hi, noise):
    """Expected value of `clip(m + n, lo, hi)` with Gaussian noise $n$ of standard
    deviation `noise`: what an integer image stores where the noise crosses 0 or 1.

    $E = m + E[(lo - m - n)_+] - E[(m + n - hi)_+]$; `lo = -inf`, `hi = inf` give `m`.
    Broadcasts; works under `jit`, `vmap` and `grad`.

    **Arguments:** `m`: the noise-free pixel value; `lo`, `hi`: the stored range (0 and
    1 for an integer image normalised to [0, 1]); `noise`: the noise's standard
    deviation, in the units of `m`.

    **Returns:** the expected stored value, in the units of `m`.
    """
    s = jnp.maximum(noise, 1e-30)
    low = jnp.where(
        jnp.isfinite(lo), _positive_part(jnp.where(jnp.isfinite(lo), lo, 0.0) - m, s), 0.0
    )
    high = jnp.where(
        jnp.isfinite(hi), _positive_part(m - jnp.where(jnp.isfinite(hi), hi, 0.0), s), 0.0
    )
    return m + low - high


def clipped_slope(m, lo, hi, noise):
    """Derivative of `clipped_mean` with respect to `m`:
    $1 - \\Phi((lo - m)/s) - \\Phi((m - hi)/s)$."""
    s = jnp.maximum(noise, 1e-30)
    low = jnp.where(jnp.isfinite(lo), jax.scipy.special.ndtr((jnp.nan_to_num(lo) - m) / s), 0.0)
    high = jnp.where(jnp.isfinite(hi), jax.scipy.special.ndtr((m - jnp.nan_to_num(hi)) / s), 0.0)
    return 1.0 - low - high


def _residuals(theta, args, setup: _Setup):
    """weight x (expected observation - data) / scale.

    `args` = (fine edges, coarse edges, data, weights, fixed sigma, scale, clip): the
    weight of a pixel averaging b x b original ones is b, so every weighted residual
    has the noise of one original pixel; `clip` = (lo, hi, noise) / scale of the
    clipping of the stored values (infinite bounds: none)."""
    data, weight, scale, clip = args[2], args[3], args[5], args[6]
    m = clipped_mean(_model(theta, args, setup), clip[0], clip[1], clip[2])
    # The prior on ring_flux, in units of one pixel's noise.
    prior = clip[2] * (theta[-1:] - 1.0) / _RING_FLUX_PRIOR
    return jnp.concatenate([weight * (m - data / scale), prior])


def _dense_residuals(args, setup: _Setup):
    """The residual function with a dense Jacobian: `fn(theta) -> (r, J)`, whose JVP is
    `J @ dtheta` with `J` from one forward-mode pass over the 4-5 parameters.

    Optimistix applies the linearised residuals several times a step (the damped QR,
    the trust region's predicted reduction) and each application would otherwise be a
    further copy of the model's tangent program; with the Jacobian materialised once
    they are matrix products, and the solver's program compiles ~3x faster. `J` also
    comes back as the auxiliary output, for the covariance at the solution."""

    def both(theta):
        r = _residuals(theta, args, setup)
        return r, r

    @jax.custom_jvp
    def fn(theta):
        jac, r = jax.jacfwd(both, has_aux=True)(theta)
        return r, jac

    @fn.defjvp
    def _jvp(primals, tangents):
        (theta,), (dtheta,) = primals, tangents
        r, jac = fn(theta)
        return (r, jac), (jac @ dtheta, jnp.zeros_like(jac))

    return fn


@eqx.filter_jit
def _solve(theta0, args, setup: _Setup, rtol, atol, max_steps):
    fn = _dense_residuals(args, setup)
    sol = optx.least_squares(
        lambda th, _: (lambda r, jac: (r, (r, jac)))(*fn(th)),
        optx.LevenbergMarquardt(rtol=rtol, atol=atol),
        theta0,
        has_aux=True,
        max_steps=max_steps,
        throw=False,
    )
    # The solver returns the auxiliary output of the last accepted point but one: at
    # termination that step is below the tolerances, so (r, J) are those of the optimum
    # to that accuracy, and no further copy of the model's Jacobian is compiled.
    r, jac = sol.aux
    return sol.value, r, jac, sol.result, sol.stats["num_steps"]


_PROFILE_STEPS = 4  # Gauss-Newton steps on (log focal, log sigma) for each candidate


@eqx.filter_jit
def _candidate_losses(cands, halves, args, setup: _Setup):
    r"""Profile loss of each candidate distance.

    For each (D, fov, sigma) the distance is held fixed while a few Gauss-Newton steps
    (A and floor linear, steps on log focal length and log sigma clipped) fit the rest:
    candidates along the ring relation then differ by what D alone changes, not by the
    sub-pixel error of the measured ring radius. A NaN sigma is first taken from the
    half-maximum radii `halves` (inner, outer, pixels; inner NaN when the ring runs
    into the shadow): the Gaussian in $|\Phi - \pi|$ is at half its peak where
    $|\Phi - \pi| = \sqrt{2 \ln 2}\,\sigma$.

    **Returns:** loss, fov, sigma, A and floor of each candidate.
    """
    x0, y0, data, scale, clip = args
    y = (data / scale).ravel()
    lo, hi, noise = clip[0], clip[1], clip[2]
    hwhm = math.sqrt(2.0 * math.log(2.0))

    def one(c):
        d, fov = c[0], c[1]
        table = EscapeTable.build(d, knots=setup.knots)
        focal = setup.half_width / jnp.tan(0.5 * fov)
        phi_in = table.escape_angle(jnp.arctan(jnp.nan_to_num(halves[0], nan=1.0) / focal))
        phi_out = table.escape_angle(jnp.arctan(halves[1] / focal))
        width = jnp.where(
            jnp.isnan(halves[0]), (jnp.pi - phi_out) / hwhm, 0.5 * (phi_in - phi_out) / hwhm
        )
        sigma = jnp.where(jnp.isnan(c[2]), jnp.clip(width, 1e-5, 0.5), c[2])
        q0 = jnp.stack([jnp.log(focal), jnp.log(sigma)][: 2 if setup.fit_sigma else 1])

        def basis(q):
            s_ = jnp.exp(q[1]) if setup.fit_sigma else sigma
            g, t, cov = _pixel_basis(table, jnp.exp(q[0]), s_, x0, y0, block=setup.block, k=setup.k)
            g, cov = (g + t).ravel(), cov.ravel()
            return g, (g, cov)

        # A and floor by linear least squares, then Gauss-Newton on all four (through
        # the expected clipped value where the stored values were clipped).
        g, (_, cov) = basis(q0)
        xm = jnp.stack([g, cov], axis=1)
        mm = xm.T @ xm
        a0, f0 = jnp.linalg.solve(mm + 1e-10 * jnp.diag(jnp.diag(mm)), xm.T @ y)

        def step(carry, _):
            q, a, fl = carry
            jg, (g, cov) = jax.jacfwd(basis, has_aux=True)(q)
            m = a * g + fl * cov
            res = y - clipped_mean(m, lo, hi, noise)
            x = clipped_slope(m, lo, hi, noise)[:, None] * jnp.concatenate(
                [g[:, None], cov[:, None], a * jg], axis=1
            )
            mm = x.T @ x
            delta = jnp.linalg.solve(mm + 1e-10 * jnp.diag(jnp.diag(mm)), x.T @ res)
            delta = jnp.nan_to_num(delta)
            limit = jnp.asarray([0.05, 0.3][: q.shape[0]], q.dtype)
            q = q + jnp.clip(delta[2:], -limit, limit)
            return (q, a + delta[0], fl + delta[1]), jnp.sum(res**2)

        (q, a, fl), rss = jax.lax.scan(step, (q0, a0, f0), None, length=_PROFILE_STEPS)
        f = jnp.exp(q[0])
        fov = 2.0 * jnp.arctan(setup.half_width / f)
        s_ = jnp.exp(q[1]) if setup.fit_sigma else sigma
        loss = jnp.where(jnp.isfinite(rss[-1]), rss[-1], jnp.inf)
        return loss, fov, s_, a * scale, fl * scale

    def skip(c):  # rows with D = NaN are placeholders: not evaluated
        inf = jnp.asarray(jnp.inf, y.dtype)
        return inf, c[1], jnp.nan_to_num(c[2], nan=1.0), inf, inf

    return jax.lax.map(lambda c: jax.lax.cond(jnp.isfinite(c[0]), one, skip, c), cands)


# ------------------------------------------------------------------- starting values


class _Profile(eqx.Module):
    """What the radial profile about the image centre shows (pixels, data units)."""

    ring_radius: float
    ring_width: float  # radial Gaussian sigma of the ring, pixels
    inner_half: float  # radius of half maximum inside the ring (nan: cut by the shadow)
    outer_half: float  # radius of half maximum outside the ring
    peak: float  # ring peak above the floor
    peak_noise: float  # noise of the profile at the peak (the mean of its pixels)
    floor: float
    noise: float  # per-pixel noise, robust estimate
    shadow_radius: float  # nan when no dark disc against a floor is seen


def _noise_level(img):
    """Per-pixel noise from the median absolute second difference (robust to the ring)."""
    d = img[:, 2:] - 2.0 * img[:, 1:-1] + img[:, :-2]
    if d.size < 8:
        return float(np.std(img))
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(6.0))


def _profile(img) -> _Profile:
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w]
    rho = np.hypot(xx + 0.5 - 0.5 * w, 0.5 * h - (yy + 0.5))
    dr = 0.5
    idx = np.floor(rho / dr).astype(int).ravel()
    cnt = np.bincount(idx)
    tot = np.bincount(idx, weights=img.ravel())
    ok = cnt > 0
    r_mid = (np.arange(cnt.size) + 0.5) * dr
    prof = np.interp(r_mid, r_mid[ok], tot[ok] / np.maximum(cnt[ok], 1))
    smooth = np.convolve(prof, np.ones(3) / 3.0, mode="same")
    smooth[0], smooth[-1] = prof[0], prof[-1]
    noise = _noise_level(img)
    i_pk = int(np.argmax(smooth[1:-1])) + 1 if smooth.size > 2 else int(np.argmax(smooth))
    # Sub-bin peak position (parabola through the three bins about the maximum).
    if 0 < i_pk < smooth.size - 1:
        a, b, c = smooth[i_pk - 1 : i_pk + 2]
        den = a - 2 * b + c
        shift = 0.5 * (a - c) / den if den < 0 else 0.0
        ring_radius = float(r_mid[i_pk] + np.clip(shift, -1, 1) * dr)
    else:
        ring_radius = float(r_mid[i_pk])
    outside = smooth[i_pk:]
    floor = float(np.min(outside)) if outside.size else 0.0
    peak = float(smooth[i_pk] - floor)
    half = floor + 0.5 * peak
    # Half-maximum radii, interpolated between bins and corrected for the blur of the
    # pixels, the bins and the smoothing (variance 1/12 + dr^2/12 + 2 dr^2/3 pixels^2).
    blur = 1.0 / 12.0 + dr**2 / 12.0 + 2.0 * dr**2 / 3.0
    j = i_pk
    while j + 1 < smooth.size and smooth[j] > half:
        j += 1
    f = (smooth[j - 1] - half) / max(smooth[j - 1] - smooth[j], 1e-300)
    outer = max(r_mid[j - 1] + np.clip(f, 0, 1) * dr - ring_radius, 0.25)
    j = i_pk
    while j > 0 and smooth[j] > half:
        j -= 1
    if j == 0 or prof[j] < 0.25 * peak + 0.5 * floor and prof[max(j - 1, 0)] < 0.5 * floor:
        inner = float("nan")  # the ring runs into the shadow (or the centre)
    else:
        f = (smooth[j + 1] - half) / max(smooth[j + 1] - smooth[j], 1e-300)
        inner = max(ring_radius - (r_mid[j + 1] - np.clip(f, 0, 1) * dr), 0.25)

    def unblur(hw):
        return 1.1774 * math.sqrt(max((hw / 1.1774) ** 2 - blur, 0.04))

    outer = unblur(outer)
    inner = unblur(inner) if math.isfinite(inner) else inner
    hw = outer if not math.isfinite(inner) else 0.5 * (outer + inner)
    ring_width = hw / 1.1774
    # The dark disc: the profile is ~0 at the centre and jumps to the floor at the edge.
    shadow_radius = float("nan")
    if floor > 5.0 * noise and prof[0] < 0.5 * floor:
        above = np.nonzero(prof[: i_pk + 1] > 0.5 * floor)[0]
        if above.size:
            shadow_radius = float(r_mid[above[0]] - 0.5 * dr)
    n_peak = float(cnt[max(i_pk - 1, 0) : i_pk + 2].sum())
    return _Profile(
        ring_radius,
        ring_width,
        ring_radius - inner,
        ring_radius + outer,
        peak,
        noise / math.sqrt(max(n_peak, 1.0)),
        floor,
        noise,
        shadow_radius,
    )


def _ring_candidates(prof: _Profile, width: int, sigma):
    """(D, fov, sigma) along the exact ring relation: for each D of the table, the FOV
    that puts the ring at the measured radius; sigma is the known one, or NaN for the
    candidate program to take from the half-maximum radii."""
    d, a_e, _, _ = _ring_table()
    focal = prof.ring_radius / np.tan(a_e)
    fov = 2.0 * np.arctan(0.5 * width / focal)
    sig = np.full_like(d, np.nan if sigma is None else sigma)
    ok = (fov > math.radians(0.05)) & (fov < math.radians(179.0))
    # Invalid rows are kept with D = NaN (infinite loss): one candidate count, one program.
    return np.stack([np.where(ok, d, np.nan), np.where(ok, fov, 1.0), sig], -1)


def _from_init(init, prof: _Profile, width: int, sigma):
    """Candidates from a user's starting values: as given, and moved along one
    parameter onto the measured ring radius (ring relation interpolated in the table)."""
    try:
        d0 = float(init["distance"])
        fov0 = float(init["fov"]) if "fov" in init else math.radians(float(init["fov_deg"]))
    except (KeyError, TypeError) as e:
        raise ValueError(
            f"init={init!r} must be a dict with 'distance' (R_S) and 'fov' (radians) or 'fov_deg'"
        ) from e
    s0 = sigma if sigma is not None else init.get("sigma", np.nan)
    d, a_e, _, _ = _ring_table()
    if not (d[0] <= d0 <= d[-1]) or not (0 < fov0 < math.pi):
        raise ValueError(
            f"init distance={d0!r} R_S must be in [{d[0]:.3g}, {d[-1]:.3g}] and fov={fov0!r} "
            "radians in (0, pi)"
        )
    ld = np.log(d)
    focal0 = 0.5 * width / math.tan(0.5 * fov0)
    a0 = float(np.interp(math.log(d0), ld, a_e))
    focal1 = prof.ring_radius / math.tan(a0)
    out = [(d0, fov0, s0), (d0, 2.0 * math.atan(0.5 * width / focal1), s0)]
    target = math.atan(prof.ring_radius / focal0)
    if a_e.min() < target < a_e.max():
        out.append((float(np.exp(np.interp(-target, -a_e, ld))), fov0, s0))
    return np.asarray(out, float)


# ------------------------------------------------------------------------ the result


class RingFit(eqx.Module):
    """Result of `fit_ring`.

    **Fields:**
    - `distance`, `distance_err`: camera distance and its standard error (units of R_S).
    - `fov`, `fov_err`: horizontal field of view (radians); `fov_deg`, `fov_deg_err`
      are the same in degrees.
    - `brightness`, `floor` (+ `_err`): peak star radiance $A$ and sky level, in the
      image's units (linear, [0, 1] for integer formats).
    - `sigma`, `sigma_err`: star width (radians; `sigma_err` is 0 when it was given).
    - `ring_flux`, `ring_flux_err`: the flux of the relativistic rings (orders 1 and 2)
      relative to the exact area average, a nuisance factor with a prior N(1, 1): the
      rings are a few thousandths of a pixel wide and renderers that point-sample
      pixels alias them; ~1 for an exactly area-averaged image.
    - `covariance`: of (D, fov, [sigma,] A, floor) in those units; `correlation`.
    - `names`: the parameter names in that order.
    - `noise`: residual standard deviation per pixel of the fitted (binned) image.
    - `n_pixels`, `block`, `supersample`: pixels fitted, binning, k.
    - `result`: the optimistix `RESULTS` of the solve (`result_name`: its name);
      `num_steps`: its steps.
    - `converged`: optimistix succeeded and the curvature is finite and invertible.
    - `degenerate`: the data do not fix D and FOV separately, or the solve did not
      converge (see `message`); `variance_inflation`: the largest of
      $1/(1 - R^2)$ over D, FOV (and sigma), $R$ the multiple correlation of one with
      the others (above 1e9: degenerate).
    - `message`: human-readable diagnosis ("" when all is well).
    - `seconds`: wall time of the fit, compile included.
    """

    distance: float
    distance_err: float
    fov: float
    fov_err: float
    brightness: float
    brightness_err: float
    floor: float
    floor_err: float
    sigma: float
    sigma_err: float
    ring_flux: float
    ring_flux_err: float
    covariance: np.ndarray
    correlation: np.ndarray
    names: tuple
    noise: float
    n_pixels: int
    block: int
    supersample: int
    result: optx.RESULTS
    result_name: str
    num_steps: int
    converged: bool
    degenerate: bool
    variance_inflation: float
    message: str
    seconds: float
    start: tuple

    @property
    def fov_deg(self) -> float:
        """Horizontal field of view, degrees."""
        return math.degrees(self.fov)

    @property
    def fov_deg_err(self) -> float:
        """Standard error of the field of view, degrees."""
        return math.degrees(self.fov_err)

    @property
    def sigma_deg(self) -> float:
        """Star width, degrees."""
        return math.degrees(self.sigma)

    def distance_m(self, mass_msun: float) -> tuple[float, float]:
        """Camera distance in metres and its standard error, for a hole of `mass_msun`
        solar masses (taken as exact)."""
        rs = float(schwarzschild_radius_m(mass_msun))
        return self.distance * rs, self.distance_err * rs

    def mass_msun(self, distance_m: float) -> tuple[float, float]:
        """Mass of the hole in solar masses and its standard error, for a camera
        distance of `distance_m` metres (taken as exact)."""
        m = float(mass_from_distance(self.distance, distance_m))
        return m, m * self.distance_err / self.distance

    def to_dict(self) -> dict:
        """Plain-Python summary (JSON-serialisable)."""
        return {
            "distance": self.distance,
            "distance_err": self.distance_err,
            "fov": self.fov,
            "fov_err": self.fov_err,
            "fov_deg": self.fov_deg,
            "fov_deg_err": self.fov_deg_err,
            "brightness": self.brightness,
            "brightness_err": self.brightness_err,
            "floor": self.floor,
            "floor_err": self.floor_err,
            "sigma": self.sigma,
            "sigma_err": self.sigma_err,
            "sigma_deg": self.sigma_deg,
            "sigma_deg_err": math.degrees(self.sigma_err),
            "ring_flux": self.ring_flux,
            "ring_flux_err": self.ring_flux_err,
            "noise": self.noise,
            "n_pixels": self.n_pixels,
            "block": self.block,
            "supersample": self.supersample,
            "num_steps": self.num_steps,
            "result": self.result_name,
            "converged": self.converged,
            "degenerate": self.degenerate,
            "variance_inflation": self.variance_inflation,
            "message": self.message,
            "seconds": self.seconds,
        }

    def summary(self) -> str:
        """A readable report."""
        lines = [
            f"distance  D   = {self.distance:.6g} +- {self.distance_err:.2g} R_S",
            f"field of view = {self.fov_deg:.6g} +- {self.fov_deg_err:.2g} deg",
            f"star sigma    = {self.sigma_deg:.4g}"
            + (f" +- {math.degrees(self.sigma_err):.2g} deg" if self.sigma_err else " deg (given)"),
            f"brightness A  = {self.brightness:.4g} +- {self.brightness_err:.2g}",
            f"floor         = {self.floor:.4g} +- {self.floor_err:.2g}",
            f"ring flux     = {self.ring_flux:.3g} +- {self.ring_flux_err:.2g} "
            "(relativistic rings / exact)",
            f"noise         = {self.noise:.3g} per pixel ({self.n_pixels} pixels, "
            f"bin {self.block}, {self.supersample}x{self.supersample} samples)",
            f"solver        = {self.num_steps} steps, "
            + ("converged" if self.converged else "NOT converged")
            + f", {self.seconds:.1f} s",
        ]
        if self.degenerate:
            lines.append(f"DEGENERATE: {self.message}")
        elif self.message:
            lines.append(self.message)
        return "\n".join(lines)


# --------------------------------------------------------------------------- the fit


def read_observation(path) -> np.ndarray:
    """Read an image file as the observation model reads it: pixel values as stored
    (integer formats normalised to [0, 1]), no colour-space decoding, the colour
    channels averaged (an alpha channel, as OpenImageIO identifies it, is left out).

    `read_image` decodes sRGB-tagged 8/16-bit files (every PNG) to linear light; the
    fit's contract takes the stored values as linear intensity, so it reads here.

    **Returns:** float64 `(H, W)`; raises `ValueError` naming the file when it is
    missing, empty, not an image or unreadable.
    """
    data, info = read_pixels(path)
    data, alpha = np.asarray(data, np.float64), info["alpha"]
    colour = [i for i in range(data.shape[-1]) if i != alpha] or [0]
    return data[..., colour].mean(axis=-1)


def _as_gray(image) -> np.ndarray:
    if isinstance(image, (str, Path)):
        image = read_observation(image)
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 3:
        img = img.mean(axis=-1)
    if img.ndim != 2:
        raise ValueError(f"image of shape {np.shape(image)} is not (H, W) or (H, W, C)")
    if min(img.shape) < 8:
        raise ValueError(f"image of {img.shape[1]}x{img.shape[0]} pixels is too small to fit")
    if not np.all(np.isfinite(img)):
        raise ValueError("image has NaN or infinite pixels")
    span = float(img.max() - img.min())
    if span <= 1e-12 * max(1.0, abs(float(img.max()))):
        raise ValueError(
            f"image is blank (every pixel is {float(img.flat[0]):.6g}): no ring to fit"
        )
    return img


def _clipping(img):
    """Bounds at which the stored values were clipped: 0 (1) when at least 0.2 % of the
    pixels sit exactly there, else -inf (inf)."""
    lo = 0.0 if img.min() == 0.0 and np.mean(img == 0.0) > 2e-3 else -math.inf
    hi = 1.0 if img.max() == 1.0 and np.mean(img == 1.0) > 2e-3 else math.inf
    return lo, hi


def _noise_clipped(img, prof: "_Profile", lo, hi) -> float:
    """Per-pixel noise. Unclipped images: the robust second-difference estimate. Clipped
    ones: from the sky well outside the ring (flat there), as the 84th minus the 50th
    percentile, which clipping below the median leaves intact; inside the shadow (flat
    at 0) when the sky outside is too small."""
    if not (math.isfinite(lo) or math.isfinite(hi)):
        return prof.noise
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w]
    rho = np.hypot(xx + 0.5 - 0.5 * w, 0.5 * h - (yy + 0.5))
    for region in (
        rho > prof.ring_radius + 8.0 * prof.ring_width + 3.0,
        rho < 0.5 * np.nan_to_num(prof.inner_half, nan=0.0),
    ):
        v = img[region]
        if v.size >= 200:
            q50, q84 = np.percentile(v, [50.0, 84.13])
            if q84 > q50 and q50 < hi:
                return float(q84 - q50)
    return prof.noise


def _bin(img, block):
    h, w = img.shape
    hb, wb = h // block, w // block
    r0, c0 = (h - hb * block) // 2, (w - wb * block) // 2
    crop = img[r0 : r0 + hb * block, c0 : c0 + wb * block]
    return crop.reshape(hb, block, wb, block).mean(axis=(1, 3))


class _PixelSets(eqx.Module):
    """The pixels a fit compares (host-side numpy): `fine` edges (x0, y0) of pixels of
    side `block`, `coarse_edges` of blocks of side `coarse` (empty when `coarse` = 0),
    their stored values `data` (fine, then coarse) and weights (the side of each)."""

    fine: tuple
    coarse_edges: tuple
    data: np.ndarray
    weight: np.ndarray
    block: int
    coarse: int


def _pixel_sets(img, prof, rho_sh, max_pixels: int, block: int | None) -> _PixelSets:
    """Full resolution (or bins of `block`, the finest the ring allows) on the shadow
    edge and the ring; where the image is flat (inside the shadow, the far sky) blocks
    q times larger, q the smallest factor that brings the count to `max_pixels`.

    Fine bins: side `block` (default 1, or up to half the ring's radial width when the
    image is still too large). The bands at full resolution: the ring radius +- 6 ring
    widths and the shadow edge (from the starting distance and, when seen, the profile)
    +- 3 pixels, each widened by a coarse block's diagonal.
    """
    h, w = img.shape
    if block is None:
        block = 1
        while (h // block) * (w // block) > 4 * max_pixels and 2 * (block + 1) <= prof.ring_width:
            block += 1
    block = int(block)
    fine_all = _bin(img, block)
    hf, wf = fine_all.shape
    if hf * wf <= max_pixels:
        x0, y0 = (np.asarray(v).ravel() for v in _pixel_edges(w, h, block, np.float64))
        empty = (np.zeros(0), np.zeros(0))
        return _PixelSets((x0, y0), empty, fine_all.ravel(), np.full(x0.size, block), block, 0)
    ring_lo = prof.ring_radius - 6.0 * prof.ring_width - 3.0
    ring_hi = prof.ring_radius + 6.0 * prof.ring_width + 3.0
    edges = [r for r in (rho_sh, prof.shadow_radius) if math.isfinite(r)]
    for q in range(2, max(hf, wf) + 1):
        big = block * q
        hb, wb = h // big, w // big
        if hb < 2 or wb < 2:
            break
        bx, by = (np.asarray(v) for v in _pixel_edges(w, h, big, np.float64))
        rc = np.hypot(bx + 0.5 * big, by - 0.5 * big)
        half = big / math.sqrt(2.0)
        lo_r, hi_r = rc - half, rc + half
        sel = (hi_r > ring_lo) & (lo_r < ring_hi)
        for e in edges:
            sel |= (hi_r > e - 3.0) & (lo_r < e + 3.0)
        n = int(sel.sum()) * q * q + int((~sel).sum())
        if n <= max_pixels or q * block >= min(h, w) // 4:
            break
    # The fine pixels of the selected blocks, and the coarse blocks elsewhere.
    crop_r0, crop_c0 = (h - hb * big) // 2, (w - wb * big) // 2
    sub = np.arange(q) * block
    fx = (bx[sel][:, None, None] + sub[None, None, :]).repeat(q, axis=1).ravel()
    fy = (by[sel][:, None, None] - sub[None, :, None]).repeat(q, axis=2).ravel()
    cols = np.round(fx + 0.5 * w).astype(int)
    rows = np.round(0.5 * h - fy).astype(int)
    fine = img[
        rows[:, None, None] + np.arange(block)[None, :, None],
        cols[:, None, None] + np.arange(block)[None, None, :],
    ].mean(axis=(1, 2))
    coarse = _bin(img[crop_r0 : crop_r0 + hb * big, crop_c0 : crop_c0 + wb * big], big)
    data = np.concatenate([fine, coarse[~sel]])
    weight = np.concatenate([np.full(fine.size, block), np.full(int((~sel).sum()), big)])
    return _PixelSets((fx, fy), (bx[~sel], by[~sel]), data, weight.astype(float), block, big)


def _samples_for(ring_width_px, block):
    """Gauss-Legendre order $k$ for a ring of radial Gaussian width `ring_width_px`
    (full pixels) in pixels of side `block`: the smallest k whose error on a 1-D Gaussian
    is below ~4e-5 of its peak (3 for width/side >= 0.75, 4 >= 0.5, 5 >= 0.35,
    6 >= 0.25, else 8; measured against the exact erf average)."""
    ratio = ring_width_px / block
    for k, least in ((3, 0.75), (4, 0.5), (5, 0.35), (6, 0.25)):
        if ratio >= least:
            return k
    return 8


def fit_ring(
    image,
    *,
    star_sigma: float | None = None,
    init: dict | None = None,
    supersample: int | None = None,
    block: int | None = None,
    max_pixels: int = 40_000,
    knots: int = 4096,
    rtol: float = 1e-6,
    atol: float | None = None,
    max_steps: int = 100,
) -> RingFit:
    """Fit the camera distance and field of view to an image of an Einstein ring.

    The observation model is that of the module docstring; the fit runs in float64
    whatever the global precision. Starting values come from the radial profile about
    the image centre (ring radius and width) mapped through the exact ring relation
    $\\alpha_E(D)$ onto a grid of distances whose losses are compared on a binned
    image; `init` adds candidates of its own. Levenberg-Marquardt (optimistix) then
    fits $\\log(D-1.5)$, $\\operatorname{logit}(\\mathrm{FOV}/\\pi)$, $\\log\\sigma$ (when
    `star_sigma` is None), $A$ and the floor.

    **Arguments:**
    - `image`: array `(H, W)` or `(H, W, C)` of linear intensity (channels averaged),
      or a path read with `read_observation` (values as stored, integer formats
      normalised to [0, 1], no sRGB decoding, alpha left out).
    - `star_sigma`: the star's Gaussian width (radians) when known; fitted otherwise.
    - `init`: optional starting values, a dict with `distance` (R_S) and `fov`
      (radians) or `fov_deg`, optionally `sigma` (radians).
    - `supersample`: $k$ ($k \\times k$ samples a pixel); default from the ring width.
    - `block`: bin the image `block` x `block` before the fit (default: the smallest
      factor that leaves at most `max_pixels` pixels, never more than the ring width
      allows).
    - `knots`: size of the escape-angle table (`EscapeTable`).
    - `rtol`, `atol`, `max_steps`: Levenberg-Marquardt settings; it stops when a step
      changes no parameter by more than `atol + rtol |theta|` and no residual by more
      than `atol + rtol |r|` (residuals in units of the ring's peak). Default `atol`:
      1e-4 of the estimated noise, so the last step moves the fit by ~1e-4 of its
      standard errors.

    **Returns:** a `RingFit`. Raises `ValueError` for an unreadable, non-finite or
    blank image.
    """
    t_start = time.perf_counter()
    img = _as_gray(image)
    h, w = img.shape
    if star_sigma is not None and not (0 < star_sigma < math.pi):
        raise ValueError(f"star_sigma={star_sigma!r} must be in (0, pi) radians")
    prof = _profile(img)
    if not prof.peak > 8.0 * prof.peak_noise:
        raise ValueError(
            f"no ring found: the radial profile about the image centre peaks "
            f"{prof.peak:.3g} above its floor, within 8 times its noise "
            f"({prof.peak_noise:.3g}; {prof.noise:.3g} per pixel)"
        )
    fit_sigma = star_sigma is None
    scale = max(prof.peak + prof.floor, 1e-12)

    with jax.enable_x64(True):
        # --- starting values: candidates along the ring relation on a binned image.
        coarse = max(1, round(min(h, w) / 40))
        cimg = _bin(img, coarse)
        k0 = _samples_for(prof.ring_width, coarse)
        setup0 = _Setup(0.5 * w, coarse, k0, 1024, fit_sigma)
        x0c, y0c = _pixel_edges(w, h, coarse, jnp.float64)
        # Stored values clipped at 0 (or 1) where the noise crossed them: the model is
        # then the expected clipped value, with the noise of one original pixel.
        lo, hi = _clipping(img)
        noise = _noise_clipped(img, prof, lo, hi)
        clip0 = jnp.asarray([lo, hi, noise]) / scale  # clipping acts per original pixel
        args0 = (x0c, y0c, jnp.asarray(cimg), jnp.asarray(scale), clip0)
        cands = _ring_candidates(prof, w, star_sigma)
        extra = np.full((3, 3), np.nan)
        extra[:, 1] = 1.0
        if init is not None:
            # A start of the user's: its own candidates only (the grid rows are skipped).
            given = _from_init(init, prof, w, star_sigma)
            extra[: len(given)] = given
            cands[:, 0] = np.nan
        cands = np.concatenate([extra, cands], axis=0)
        if not np.any(np.isfinite(cands[:, 0])):
            raise ValueError(
                f"no camera distance puts an Einstein ring at {prof.ring_radius:.3g} pixels "
                f"from the centre of a {w}-pixel-wide image"
            )
        halves = jnp.asarray([prof.inner_half, prof.outer_half])
        loss, fovs, sig, amp, flo = (
            np.asarray(v) for v in _candidate_losses(jnp.asarray(cands), halves, args0, setup0)
        )
        loss = np.where(np.isfinite(loss), loss, np.inf)
        best = int(np.argmin(loss))
        d_s, fov_s, sig_s = float(cands[best][0]), float(fovs[best]), float(sig[best])
        a_s, fl_s = float(amp[best]), float(flo[best])

        # --- the fit: full resolution (or the finest level the ring needs) where the
        # image has structure, coarse blocks where it is flat.
        f_s = 0.5 * w / math.tan(0.5 * fov_s)
        rho_sh = f_s * math.tan(float(shadow_angle(d_s)))
        pix = _pixel_sets(img, prof, rho_sh, max_pixels, block)
        k = (
            int(supersample)
            if supersample is not None
            else _samples_for(prof.ring_width, pix.block)
        )
        setup = _Setup(0.5 * w, pix.block, k, int(knots), fit_sigma, pix.coarse, 2)
        fixed = jnp.asarray(star_sigma if star_sigma is not None else 1.0)
        theta0 = jnp.asarray(_pack(d_s, fov_s, sig_s, a_s, fl_s, scale, fit_sigma))
        if atol is None:
            atol = max(1e-4 * prof.noise / scale, 1e-12)
        passes = 2 if (math.isfinite(lo) or math.isfinite(hi)) else 1
        for _ in range(passes):
            clip = jnp.asarray([lo, hi, noise]) / scale
            args = (
                tuple(jnp.asarray(v) for v in pix.fine),
                tuple(jnp.asarray(v) for v in pix.coarse_edges),
                jnp.asarray(pix.data),
                jnp.asarray(pix.weight),
                fixed,
                jnp.asarray(scale),
                clip,
            )
            theta, r, jac, result, steps = _solve(
                theta0, args, setup, jnp.asarray(rtol), jnp.asarray(atol), int(max_steps)
            )
            theta, r = np.asarray(theta), np.asarray(r).ravel()
            jac = np.asarray(jac).reshape(r.size, -1)
            model = np.asarray(_model(jnp.asarray(theta), args, setup)) * scale
            # The noise of one original pixel, from the residuals well inside (lo, hi).
            inside = (model > lo + 4.0 * noise) & (model < hi - 4.0 * noise)
            if inside.sum() > 50:
                noise = float(np.std(r[:-1][inside]) * scale)
            theta0 = jnp.asarray(theta)
        d, fov, sig, a, fl, ring_flux = (
            float(v) for v in _unpack(jnp.asarray(theta), fixed, jnp.asarray(scale), setup)
        )

    n, p = r.size - 1, theta.size  # the last residual is the prior on ring_flux
    rss = float(np.sum(r[:-1] ** 2))
    s2 = rss / max(n - p, 1)
    # Jacobian of (D, fov, [sigma,] A, floor, ring_flux) with respect to the internal parameters.
    grad = [d - _D_MIN, fov * (1.0 - fov / math.pi)] + ([sig] if fit_sigma else [])
    grad += [scale, scale, 1.0]
    g = np.diag(grad)
    jtj = jac.T @ jac
    finite = bool(np.all(np.isfinite(jtj)) and np.all(np.isfinite(theta)))
    cov_int = np.full((p, p), np.nan)
    cond = np.inf
    if finite:
        dscale = np.sqrt(np.diag(jtj))
        if np.all(dscale > 0):
            norm = jtj / np.outer(dscale, dscale)
            ev = np.linalg.eigvalsh(norm)
            cond = float(ev[-1] / max(ev[0], 1e-300))
            cov_int = np.linalg.pinv(norm) / np.outer(dscale, dscale) * s2
    # Residuals and the internal A, floor are in units of `scale`; cov_int is invariant
    # under that scaling, and `g` carries A = a * scale, floor = fl * scale.
    cov = g @ cov_int @ g.T
    err = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(err, err)
    names = ("distance", "fov") + (("sigma",) if fit_sigma else ())
    names += ("brightness", "floor", "ring_flux")
    ok_result = result == optx.RESULTS.successful
    converged = bool(ok_result) and finite and np.all(np.isfinite(err)) and cond < 1e14
    degenerate, message, vif = _diagnose(
        d, fov, fl, ring_flux, err, corr, cond, converged, fit_sigma, prof, result
    )
    e = dict(zip(names, err))
    return RingFit(
        distance=d,
        distance_err=float(e["distance"]),
        fov=fov,
        fov_err=float(e["fov"]),
        brightness=a,
        brightness_err=float(e["brightness"]),
        floor=fl,
        floor_err=float(e["floor"]),
        sigma=sig,
        sigma_err=float(e.get("sigma", 0.0)),
        ring_flux=ring_flux,
        ring_flux_err=float(e["ring_flux"]),
        covariance=cov,
        correlation=corr,
        names=names,
        noise=math.sqrt(s2) * scale,
        n_pixels=int(n),
        block=pix.block,
        supersample=k,
        result=result,
        result_name=_result_name(result),
        num_steps=int(steps),
        converged=bool(converged),
        degenerate=bool(degenerate),
        variance_inflation=float(vif),
        message=message,
        seconds=time.perf_counter() - t_start,
        start=(float(d_s), float(fov_s), float(sig_s)),
    )


# Degeneracy thresholds: a relative standard error of D or FOV above 10 % means the
# image does not pin them down (the goal is 1 %); a variance inflation above 1e9
# (multiple correlation of D, FOV or sigma with the others above 1 - 1e-9) means the
# curvature is numerically singular along a valley where D trades off against FOV and
# sigma. Rings without a visible shadow edge and sigma fitted sit at 1e6-1e8 with D
# still fixed to 2-3 % by the ring's profile (320 x 240, noise 0.01): not degenerate.
_REL_ERR_DEGENERATE = 0.10
_VIF_DEGENERATE = 1e9
# With sigma fitted and no floor, what separates D from FOV and sigma is the relativistic
# ring (the primary ring alone fixed D to 5 % at D = 17, 320 x 240, noise 0.005). Where
# that ring's flux is measured to worse than 1/_RING_SIGNIFICANCE, fits from different
# noise realisations and starts scattered up to 4 times their reported errors (local minima
# along the valley): degenerate. A floor counts as seen above _EDGE_SIGNIFICANCE errors.
_RING_SIGNIFICANCE = 10.0
_EDGE_SIGNIFICANCE = 5.0


def _result_name(result) -> str:
    for name in (
        "successful",
        "nonlinear_max_steps_reached",
        "max_steps_reached",
        "nonlinear_divergence",
        "nonfinite",
        "singular",
        "breakdown",
        "stagnation",
    ):
        if bool(result == getattr(optx.RESULTS, name)):
            return name
    return "failed"


def _diagnose(d, fov, floor, ring_flux, err, corr, cond, converged, fit_sigma, prof, result):
    notes = []
    degenerate = False
    edge_seen = np.isfinite(prof.shadow_radius) or floor > _EDGE_SIGNIFICANCE * err[-2]
    ring_seen = ring_flux > _RING_SIGNIFICANCE * err[-1]
    rel_d = err[0] / d if d > 0 else np.inf
    rel_f = err[1] / fov if fov > 0 else np.inf
    try:
        vif = float(np.max(np.diag(np.linalg.inv(corr[: 2 + fit_sigma, : 2 + fit_sigma]))))
    except np.linalg.LinAlgError:
        vif = np.inf
    if not np.isfinite(vif):
        vif = np.inf
    if not (rel_d < _REL_ERR_DEGENERATE and rel_f < _REL_ERR_DEGENERATE) or vif > _VIF_DEGENERATE:
        degenerate = True
        why = (
            f"D and FOV are not fixed separately by this image (relative errors "
            f"{rel_d:.2g} and {rel_f:.2g}, variance inflation {vif:.3g})"
        )
        if fit_sigma and not np.isfinite(prof.shadow_radius):
            why += (
                "; sigma is unknown and no shadow edge is visible against a floor, so "
                "the ring's radius and width trade D against FOV and sigma: pass "
                "star_sigma, or use an image with a visible shadow edge"
            )
        notes.append(why)
    elif fit_sigma and not edge_seen and not ring_seen:
        degenerate = True
        notes.append(
            f"sigma is unknown, no shadow edge is visible against a floor, and the "
            f"relativistic ring is seen at {ring_flux / err[-1]:.2g} standard errors "
            f"(below {_RING_SIGNIFICANCE:g}): only it separates D from FOV and sigma, so "
            f"D = {d:.4g} +- {err[0]:.2g} rests on a faint, sub-pixel feature: pass "
            "star_sigma, or use an image with a visible shadow edge or less noise"
        )
    if not converged:
        notes.append(
            f"the solver did not converge ({_result_name(result)}, curvature condition "
            f"number {cond:.3g})"
        )
    return degenerate or not converged, "; ".join(notes), vif
