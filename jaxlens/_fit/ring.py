"""`fit_ring`: the general fit's preset for an Einstein ring of a star behind the hole."""

import math

from .._camera import Camera
from .._scene import Scene
from .._sky import GaussianStar, Uniform
from .._util import host_driver
from .general import fit
from .pixels import _as_gray
from .result import RingFit
from .starts import _profile


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

    A preset of `fit`: the model is a Gaussian star exactly behind the hole over a
    uniform floor, Gaussian noise of a level estimated from the image (values clipped
    at the format's range modelled as such), no PSF; free are D, the FOV, sigma (when
    `star_sigma` is None), the star's peak brightness $A$, the floor and the
    relativistic rings' flux factor (prior N(1, 1)). The fit runs in float64 whatever
    the global precision. Starting values come from the radial profile about the image
    centre (ring radius and width) mapped through the exact ring relation
    $\\alpha_E(D)$ onto a grid of distances whose losses are compared on a binned image;
    `init` adds candidates of its own. Levenberg-Marquardt (optimistix) then fits
    $\\log(D-1.5)$, $\\operatorname{logit}(\\mathrm{FOV}/\\pi)$, $\\log\\sigma$, $A$ and
    the floor, at full resolution on the ring and the shadow's edge and on coarse
    blocks where the image is flat.

    **Arguments:**
    - `image`: array `(H, W)` or `(H, W, C)` of linear intensity (channels averaged),
      or a path read with `read_observation` (linear intensity: sRGB-tagged or
      untagged 8/16-bit files decoded, float and linear-tagged files as stored;
      alpha left out).
    - `star_sigma`: the star's Gaussian width (radians) when known; fitted otherwise.
    - `init`: optional starting values, a dict with `distance` (R_S) and `fov`
      (radians) or `fov_deg`, optionally `sigma` (radians).
    - `supersample`: $k$ ($k \\times k$ nodes a pixel); default from the ring width.
    - `block`, `max_pixels`: the fine bins' side (default 1, or the finest the ring's
      width allows) and the most bins compared (`fit`'s).
    - `knots`: of the escape-angle table (`escape_table`, a `RayMap`).
    - `rtol`, `atol`, `max_steps`: Levenberg-Marquardt settings (`fit`'s).

    **Returns:** a `RingFit`. Raises `ValueError` for an unreadable, non-finite or
    blank image, or one with no ring, and a `TypeError` under `jit`, `vmap` or `grad`
    (it runs on the host: differentiate `ring_image` instead).
    """
    host_driver("fit_ring", "differentiate the model (jaxlens.ring_image) instead", image,
                star_sigma, init)  # fmt: skip
    img, transfer = _as_gray(image)
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
    sky = GaussianStar(0.01 if fit_sigma else float(star_sigma), 1.0) + Uniform(0.0)
    scene = Scene(Camera(20.0, 1.0, 8, 8), sky)
    free = ("distance", "fov") + (("sigma",) if fit_sigma else ())
    free += ("brightness", "floor", "ring_flux")
    f = fit(scene, img, free=free, init=init, supersample=supersample, block=block,
            max_pixels=max_pixels, knots=knots, rtol=rtol, atol=atol,
            max_steps=max_steps)  # fmt: skip
    v, e = f.values, f.errors
    # The solver's verdict first, then what the image cannot fix.
    converged = f.result_name == "successful" and bool(all(math.isfinite(x) for x in e.values()))
    message = f.message
    return RingFit(
        distance=v["distance"],
        distance_err=e["distance"],
        fov=v["fov"],
        fov_err=e["fov"],
        brightness=v["brightness"],
        brightness_err=e["brightness"],
        floor=v["floor"],
        floor_err=e["floor"],
        sigma=v["sigma"],
        sigma_err=e.get("sigma", 0.0),
        ring_flux=v["ring_flux"],
        ring_flux_err=e["ring_flux"],
        covariance=f.covariance,
        correlation=f.correlation,
        names=f.names,
        noise=math.sqrt(f.chi2_dof) * f.noise_sigma,
        n_pixels=f.n_pixels,
        block=f.block,
        supersample=f.supersample,
        result=f.result,
        result_name=f.result_name,
        num_steps=f.num_steps,
        converged=converged,
        degenerate=f.degenerate or not converged,
        variance_inflation=f.variance_inflation,
        message=message,
        seconds=f.seconds,
        start=(f.start["distance"], f.start["fov"], f.start["sigma"]),
        transfer=transfer,
    )
