"""The per-pixel observation model: shadow-edge coverage of a footprint, Gauss-Legendre
pixel quadrature, the thin relativistic rings, the pixel basis images and
`ring_image`."""

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .table import escape_table, solve_with_slope


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
    a, slope = jax.lax.map(lambda t: solve_with_slope(table, t), targets)
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

    **Arguments:** `table` (the `escape_table` of the distance), `focal` (pixels of the
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
    a_edge = table.alpha_sh + jnp.exp(table.tau[0])
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
    table = escape_table(distance)
    focal = 0.5 * width / jnp.tan(0.5 * jnp.asarray(fov, dtype))
    x0, y0 = _pixel_edges(width, height, 1, dtype)
    g, t, c = _pixel_basis(
        table, focal, jnp.asarray(sigma, dtype), x0, y0, block=1, k=int(supersample)
    )
    return brightness * (g + ring_flux * t) + floor * c


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
