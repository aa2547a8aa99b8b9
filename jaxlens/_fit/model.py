"""The per-pixel observation model: the renderer's area-exact sampling of a star behind
the hole over a floor (the basis images of the fit) and `ring_image`."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .. import _kernel, _plan
from .._camera import Camera
from .._scene import Scene
from .._sky import GaussianStar, Uniform
from .._units import angle, length
from .._util import concrete
from .pixels import pixel_edges
from .table import escape_table


def chunk_layout(n_pix: int, k: int, chunk_samples: int) -> tuple[int, int]:
    """How `n_pix` pixels of `k` x `k` area samples split into chunks of at most
    `chunk_samples` samples: `(chunks, pixels a chunk)`."""
    per = max(1, chunk_samples // (k * k))
    # At least two chunks: XLA removes a loop of one trip and then fuses the table's
    # producer into every per-sample gather (measured 30x slower).
    chunks = max(2, -(-n_pix // per))
    return chunks, -(-n_pix // chunks)


def basis_scene(distance, focal, sigma, width: int, k: int) -> Scene:
    """The fit's model as a renderer scene: a camera at `distance` (R_S) of focal length
    `focal` (pixels) on an image `width` pixels wide, area-exact sampling of order `k`,
    and the two basis images as colour channels: the star (unit peak brightness,
    Gaussian width `sigma` radians, exactly behind the hole) in red, a unit floor in
    green."""
    fov = 2.0 * jnp.arctan(0.5 * width / focal)
    cam = Camera(distance, fov, width, width, supersample=k, sampling="gauss")
    sky = GaussianStar(sigma, 1.0, color=(1.0, 0.0, 0.0)) + Uniform((0.0, 1.0, 0.0))
    return Scene(cam, sky)


def _pixel_basis(
    table, focal, sigma, x0, y0, *, width, block, k, chunk_samples=1 << 16, rings=True
):
    """Per-pixel area averages of the two basis images: the star's light (unit peak
    brightness) and the floor's coverage, by the renderer's area-exact sampling
    (`Camera(..., sampling="gauss")`, the kernel's `cells`) of `basis_scene`.

    **Arguments:** `table` (the `escape_table` of the distance), `focal` (pixels of the
    full image), `sigma` (radians), `x0`, `y0`: left and top edges of each (binned)
    pixel in full-image pixels from the image centre ($x$ right, $y$ up); `width` (of
    the full image, pixels); `block`: side of a pixel in full-image pixels; `k`: the
    rule's order; `rings`: include the thin relativistic rings (else `t` is 0).

    **Returns:** `(g, t, c)` of the shape of `x0`: the primary image, the images of
    order 1 and 2 (both per unit peak brightness) and the floor's coverage.
    """
    scene = basis_scene(table.distance, focal, sigma, width, k)
    plan = _plan.plan(scene)
    shape = x0.shape
    x0, y0 = x0.ravel(), y0.ravel()
    n = x0.shape[0]
    chunks, per = chunk_layout(n, k, chunk_samples)
    pad = chunks * per - n
    x0 = jnp.pad(x0, (0, pad)).reshape(chunks, per)
    y0 = jnp.pad(y0, (0, pad)).reshape(chunks, per)

    refs = _kernel.ring_references(table, table.phi.dtype) if rings else None

    def one(xy):
        main, thin = _kernel.cells(
            scene, plan, table, xy[0], xy[1], block, k, references=refs, rings=rings
        )
        return main[:, 0], thin[:, 0], main[:, 1]

    out = jax.lax.map(one, (x0, y0))
    return tuple(v.reshape(-1)[:n].reshape(shape) for v in out)


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
    - `distance`: camera radius $D > 1.5$ (units of R_S, or a dimensionless astropy
      Quantity; a length in metres is refused: `schwarzschild_radii` converts it).
    - `fov`: horizontal field of view (radians, or an astropy angle Quantity).
    - `width`, `height`: image size (pixels, static).
    - `sigma`: the star's Gaussian width in angular distance (radians, or an astropy
      angle Quantity).
    - `brightness`: peak radiance $A$ of the star; `floor`: the uniform sky level.
    - `ring_flux`: factor on the flux of the relativistic rings (images of order 1 and
      2); 1 is the exact area average, as a fit's `ring_flux` reports it.
    - `supersample`: $k$ (static).

    **Returns:** linear intensity `(height, width)`; captured rays are 0. Bad values
    raise `ValueError` when known (eagerly), and an error at run time under `jit`.
    """
    for name, v in (("width", width), ("height", height), ("supersample", supersample)):
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
            raise ValueError(f"{name}={v!r} must be a whole number >= 1 (pixels)")
    distance = length(distance, "distance")
    fov, sigma = angle(fov, "fov"), angle(sigma, "sigma")
    distance, fov, sigma, brightness, floor, ring_flux = (
        _checked(v, name, ok, valid)
        for v, name, ok, valid in (
            (distance, "distance", lambda d: d > 1.5, "finite and > 1.5 (units of R_S)"),
            (fov, "fov", lambda f: (f > 0) & (f < np.pi), "in (0, pi) radians"),
            (sigma, "sigma", lambda s: s > 0, "finite and > 0 (radians)"),
            (brightness, "brightness", None, "finite"),
            (floor, "floor", None, "finite"),
            (ring_flux, "ring_flux", None, "finite"),
        )
    )
    distance = jnp.asarray(distance, jnp.result_type(float, distance))
    dtype = distance.dtype
    table = escape_table(distance)
    focal = 0.5 * width / jnp.tan(0.5 * jnp.asarray(fov, dtype))
    x0, y0 = pixel_edges(width, height, 1, dtype)
    g, t, c = _pixel_basis(
        table, focal, jnp.asarray(sigma, dtype), x0, y0, width=width, block=1, k=int(supersample)
    )
    return brightness * (g + ring_flux * t) + floor * c


def _checked(value, name, ok, valid):
    """`value` checked: finite, real and `ok` (a `ValueError` when it is known, an
    `eqx.error_if` at run time when traced)."""
    c = concrete(value)
    if c is not None:
        if c.dtype.kind not in "iuf":
            raise ValueError(f"{name} must be real numbers, got dtype {c.dtype}")
        good = np.isfinite(c) & (ok(c) if ok is not None else True)
        if not np.all(good):
            bad = c[~good] if c.ndim else c
            raise ValueError(f"{name}={float(bad.flat[0])!r} must be {valid}")
        return value
    bad = ~jnp.isfinite(value)
    if ok is not None:
        bad = bad | ~ok(value)
    return eqx.error_if(value, jnp.any(bad), f"{name} must be {valid}")


def samples_for(ring_width_px, block, lowest: int = 2):
    """Gauss-Legendre order $k$ for a ring of radial Gaussian width `ring_width_px`
    (full pixels) in pixels of side `block`: of the orders 2, 3, 4, 6 and 8 (none
    below `lowest`) the smallest whose error on a 1-D Gaussian is below ~4e-5 of its
    peak (2 for width/side >= 2.1, 3 >= 0.75, 4 >= 0.5, 6 >= 0.25, else 8; measured
    against the exact erf average; 5, enough from 0.35, is left out so that fewer
    programs are compiled)."""
    ratio = ring_width_px / block
    for k, least in ((2, 2.1), (3, 0.75), (4, 0.5), (6, 0.25)):
        if k >= lowest and ratio >= least:
            return k
    return 8


# Former names, kept while modules outside this one still import them by these.
