"""`fit_ring`: the general fit's preset for an Einstein ring of a star behind the hole."""

import dataclasses
import math

from .._camera import Camera
from .._scene import Scene
from .._sky import GaussianStar, Uniform
from .._units import angle
from .._util import host_driver
from .fit_result import Fit
from .general import fit
from .observation import observe
from .source import SourceDistance


def fit_ring(
    image,
    *,
    transfer: str = "auto",
    pixels: str = "auto",
    star_sigma: float | None = None,
    psf=None,
    noise="gaussian",
    gain: float | None = None,
    mask=None,
    init: dict | None = None,
    supersample: int | None = None,
    block: int | None = None,
    max_pixels: int = 40_000,
    knots: int = 4096,
    rtol: float = 1e-6,
    atol: float | None = None,
    max_steps: int = 100,
    source_distance: SourceDistance | None = None,
    progress=None,
) -> Fit:
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
    - `image`: an `Observation` (`observe`), array `(H, W)` or `(H, W, C)` of linear
      intensity (channels averaged; NaN: not valid), or a path (FITS through astropy;
      other formats as linear intensity, alpha left out, decoded as `transfer` says).
    - `transfer`: how an 8/16-bit file's values are decoded: `"srgb"` (from sRGB to
      linear), `"linear"` (as stored, normalised to [0, 1]), or `"auto"` (the file's
      tag; an untagged file is fitted under both and the decoding whose residuals
      pass the noise test kept). Float files, FITS and arrays are linear.
      `Fit.transfer` and `Fit.transfer_reason` say which and why.
    - `pixels`: `"area"`, `"point"` or `"auto"`: how the pixels sampled the light
      (`observe`; a default render samples each pixel at its centre).
    - `star_sigma`: the star's Gaussian width (radians, or an astropy angle Quantity)
      when known; fitted otherwise.
    - `psf`, `noise`, `gain`, `mask`: the point-spread function (a `GaussianPSF`, an
      `ImagePSF`, a Gaussian width in pixels or a PSF image), the noise model and the
      bad pixels, as `observe` takes them.
    - `init`: optional starting values, a dict with `distance` (R_S) and `fov`
      (radians) or `fov_deg`, optionally `sigma` (radians).
    - `supersample`: $k$ ($k \\times k$ nodes a pixel); default from the ring width.
    - `block`, `max_pixels`: the fine bins' side (default 1, or the finest the ring's
      width allows) and the most bins compared (`fit`'s).
    - `knots`: of the escape-angle table (`escape_table`, a `RayMap`).
    - `rtol`, `atol`, `max_steps`: Levenberg-Marquardt settings (`fit`'s).
    - `source_distance`: a `SourceDistance` placing the star on a sphere at a finite
      distance behind the hole (its radius in R_S, or its distance behind the hole
      with the observer's distance or the mass: `Fit.mass` or
      `Fit.observer_distance` then measured); None: at infinity (`fit`'s).
    - `progress`: lines on stderr saying what the fit does; `None` (default): on where
      stderr is a terminal or in a notebook; `True`, `False` or a callable taking each
      stage's text (`fit`'s).

    **Returns:** the `Fit` of `fit`, with `degenerate` also set when it did not
    converge (D and FOV are then not fixed). Raises `ValueError` for an unreadable or
    blank image, one with fewer than 64 valid pixels (NaN and infinite pixels are left
    out), no ring that stands out of the noise, a ring under 6 px in radius, or a
    `transfer` not in "auto", "srgb", "linear"; a `TypeError` under `jit`, `vmap` or
    `grad` (it runs on the host: differentiate `ring_image` instead).
    """
    host_driver("fit_ring", "differentiate the model (jaxlens.ring_image) instead", image,
                star_sigma, init)  # fmt: skip
    star_sigma = angle(star_sigma, "star_sigma")
    if star_sigma is not None and not (0 < star_sigma < math.pi):
        raise ValueError(f"star_sigma={star_sigma!r} must be in (0, pi) radians")
    obs = observe(image, transfer=transfer, mask=mask, psf=psf, noise=noise, gain=gain,
                  pixels=pixels)  # fmt: skip
    fit_sigma = star_sigma is None
    sky = GaussianStar(0.01 if fit_sigma else float(star_sigma), 1.0) + Uniform(0.0)
    scene = Scene(Camera(20.0, 1.0, 8, 8), sky)
    free = ("distance", "fov") + (("sigma",) if fit_sigma else ())
    free += ("brightness", "floor", "ring_flux")
    f = fit(scene, obs, free=free, init=init, supersample=supersample, block=block,
            max_pixels=max_pixels, knots=knots, rtol=rtol, atol=atol,
            max_steps=max_steps, source_distance=source_distance,
            progress=progress)  # fmt: skip
    # A ring fit that did not converge fixes neither D nor FOV.
    return dataclasses.replace(f, degenerate=f.degenerate or not f.converged)
