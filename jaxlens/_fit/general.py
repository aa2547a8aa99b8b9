"""`fit`: any parameter of a scene fitted to an image through the renderer's area-exact
sampling, with a point-spread function, Gaussian or Poisson noise and a mask."""

import dataclasses
import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .. import _kernel, _plan
from .._camera import Camera
from .._compile import ahead, program
from .._exact import _shadow_angle
from .._scene import Scene
from .._util import host_driver, to_device
from . import psf as _psf, starts as _starts
from .arcs import find_arcs, source_offset_from_arcs
from .fit_result import Fit
from .model import _chunks, _pixel_edges, _samples_for
from .noise import (
    clipped_mean,
    clipped_slope,
    clipping_bounds,
    noise_clipped,
    noise_level,
    white_noise_found,
)
from .params import apply, floor_of, in_scene, parameter, split_name, star_of, values_of
from .pixels import _grid_sets, _pixel_sets, read_observation, read_observation_transfer, real_image
from .result import _result_name, _ring_verdict
from .solve import dense_least_squares, newton_decrement
from .table import escape_table

DEFAULT_FREE = (
    "distance",
    "fov",
    "source_lon",
    "source_lat",
    "sigma",
    "brightness",
    "floor",
    "ring_flux",
)
# The flux of the relativistic rings (order 1 and 2, radially a few thousandths of a
# pixel wide) is a nuisance factor `ring_flux` (1: the exact area average), with a
# Gaussian prior of this standard deviation about 1. Renderers that point-sample pixels
# alias these rings (k = 12 samples a pixel gave 55 % of the exact flux at D = 17, in a
# moire pattern), and a fit that trusted their flux was pulled 5 % in D on such images
# when sigma was fitted and no floor was seen; their positions, which fix D
# against the primary ring's radius, are still used.
_RING_FLUX_PRIOR = 1.0
# A fit of a clipped image with the noise estimated takes a second pass with the noise
# re-estimated from its residuals, unless the first pass's point gains less than this
# in chi^2 under the new noise (its Newton decrement): a step of 0.03 standard errors,
# three times the solver's own stop (`solve.SETTLED_CHI2`), well inside what the noise
# estimate itself is uncertain by. On the fit benchmark's first ring (400 x 300, the
# noise re-estimated 1.3 % lower) the decrement was 2.3e-4 and the second pass moved
# D by 0.004 and the rings' flux by 0.01 standard errors, in three more steps.
_RENOISED_CHI2 = 1e-3


class _Problem(eqx.Module):
    """Static description of a family of fits: every parameter of the model (`names`:
    the scene's, as `values_of` lists them, then `psf_sigma` with a Gaussian PSF and
    `ring_flux`), the bins' side and the model's settings. Which parameters are free
    and the held values are arguments (`_Select`), so fits of one image size and model
    share their compiled programs."""

    names: tuple = eqx.field(static=True)
    block: int = eqx.field(static=True)
    k: int = eqx.field(static=True)
    pad: int = eqx.field(static=True)
    noise: str = eqx.field(static=True)
    psf: str | None = eqx.field(static=True)  # None, "gaussian" or "image"
    knots: int = eqx.field(static=True)
    # Yaw and pitch held at zero and no roll: the model's view is concretely unrotated
    # (a plan without the view rotation and its tangents, the edge's offsets exact in
    # the image plane), whose Jacobian compiles sooner.
    centred: bool = eqx.field(static=True)


class _Select(eqx.Module):
    """Which of `_Problem.names` are fitted and the values of the others: `index`
    (int, one an entry of theta: its position in `names`), `free` (bool, one a
    name), `internal` and `value` (one a name: the internal and the physical value;
    the held ones are used as they are). Fits freeing as many parameters share a
    program. (Padding theta with spare entries would share more, but each spare is
    one more tangent of the Jacobian: a ring fit's step took 30 % longer with one.)"""

    index: jax.Array
    free: jax.Array
    internal: jax.Array
    value: jax.Array


def _select(names, free, values) -> _Select:
    """The `_Select` of the parameters `free` (physical `values` for every name)."""
    return _Select(
        to_device([names.index(n) for n in free], jnp.int32),
        to_device([n in free for n in names]),
        to_device([parameter(n).transform.inverse(values[n]) for n in names]),
        to_device([float(values[n]) for n in names]),
    )


def _internal(theta, sel: _Select):
    return sel.internal.at[sel.index].set(theta)


def _physical(u, sel: _Select, prob: _Problem):
    """Every parameter's physical value from the internal values `u` (`_internal`)."""
    return {n: jnp.where(sel.free[i], parameter(n).transform.forward(u[i]), sel.value[i])
            for i, n in enumerate(prob.names)}  # fmt: skip


def _model(p, scene, grid, otf, prob: _Problem):
    """Grey model of the compared bins (before clipping), data units, one value a bin:
    the fine bins then the coarse blocks (one rule of order k for both), or with a PSF the regular
    grid of bins, rendered on a margin, blurred and cropped (row-major); `p` the
    physical value of every parameter (`_physical`)."""
    # Concrete zeros, which the plan reads as no rotation: the model's camera is at the
    # origin of the sky's frame (`fit` places it there), and with `prob.centred` its
    # view is unrotated.
    zero = np.zeros((), scene.camera.dtype)
    fields = ["azimuth", "elevation"] + ["yaw", "pitch", "roll"] * prob.centred
    scene = eqx.tree_at(lambda s: [getattr(s.camera, n) for n in fields], scene,
                        [zero] * len(fields))  # fmt: skip
    p = {n: v for n, v in p.items() if n not in fields}
    scene = apply(scene, {n: v for n, v in p.items() if in_scene(n)})
    table = escape_table(scene.camera.distance, knots=prob.knots)
    plan = _plan.plan(scene)
    refs = _kernel.ring_references(table, table.phi.dtype)
    rf = p["ring_flux"]

    def render(x0, y0, side):
        n = x0.size
        chunks, per = _chunks(n, prob.k, 1 << 16)
        pad = chunks * per - n
        xs, ys, ss = (jnp.pad(jnp.broadcast_to(v, x0.shape).ravel(), (0, pad),
                              constant_values=1.0).reshape(chunks, per)
                      for v in (x0, y0, side))  # fmt: skip

        def one(xys):
            main, thin = _kernel.cells(scene, plan, table, *xys, prob.k, references=refs)
            return jnp.mean(main, -1) + rf * jnp.mean(thin, -1)

        return jax.lax.map(one, (xs, ys, ss)).reshape(-1)[:n]

    if prob.psf is None:
        # The fine bins and the coarse blocks in one pass (the side a cell).
        x0, y0, side = grid
        return render(x0, y0, side)
    x0, y0 = grid
    img = render(x0, y0, jnp.asarray(float(prob.block))).reshape(x0.shape)
    if prob.psf == "gaussian":
        # The width is positive by its transform: the OTF without the run-time check,
        # whose host callback would keep the program out of the command line's cache.
        otf = _psf._gaussian_otf(img.shape, p["psf_sigma"] / prob.block)
    return _psf.convolve_psf(img, otf, pad=prob.pad).ravel()


def _gaussian_rows(m, data, weight, clip):
    """Gaussian residuals (noise units) of the model `m` (before clipping) under `clip`:
    lo, hi, the noise of one original pixel and the residuals' scale."""
    return weight * (clipped_mean(m, clip[0], clip[1], clip[2]) - data) / clip[3]


def _residuals(theta, args, prob: _Problem):
    return _residuals_model(theta, args, prob)[0]


def _residuals_model(theta, args, prob: _Problem):
    """The residuals (noise units; a last one for the ring-flux prior, 0 when the flux
    is held) and the model."""
    scene, grid, otf, data, weight, clip, gain, sel = args
    u = _internal(theta, sel)
    m0 = m = _model(_physical(u, sel, prob), scene, grid, otf, prob)
    if prob.noise == "poisson":
        # Deviance residuals: their squares sum to twice the negative log-likelihood
        # of the counts (less its minimum), so least squares is the Poisson ML fit.
        mu = jnp.maximum(gain * weight**2 * m, 1e-12)
        y = gain * weight**2 * data
        q = y / mu
        d = q - 1.0
        small = jnp.abs(d) < 1e-3
        qs = jnp.where(small, 2.0, q)
        ratio = jnp.where(
            small,
            1.0 - d / 3.0 + d * d / 6.0,
            2.0 * (qs * jnp.log(jnp.maximum(qs, 1e-300)) - qs + 1.0) / (qs - 1.0) ** 2,
        )
        r = (y - mu) / jnp.sqrt(mu) * jnp.sqrt(jnp.maximum(ratio, 0.0))
        r = jnp.where(weight > 0, r, 0.0)
    else:
        r = _gaussian_rows(m, data, weight, clip)
    i = prob.names.index("ring_flux")
    prior = jnp.where(sel.free[i], (u[i] - 1.0) / _RING_FLUX_PRIOR, 0.0)
    return jnp.concatenate([r.ravel(), prior[None]]), m0


@program(profile="legacy_fusion_o1")
def _solve(theta0, args, prob: _Problem, rtol, atol, max_steps):
    """`dense_least_squares` on the residuals, the model as its auxiliary output."""
    return dense_least_squares(
        lambda th: _residuals_model(th, args, prob), theta0, rtol, atol, max_steps
    )


@program(profile="legacy_fusion_o1")
def _loss(theta, args, prob: _Problem):
    return jnp.sum(_residuals(theta, args, prob) ** 2)


@program(profile="legacy_fusion_o0_side")
def _renoised(model, data, weight, old, new, r, jac, moved):
    """The residuals and Jacobian of a Gaussian fit's point (model `model` before
    clipping, residuals `r` and Jacobian `jac` under the clipping and noise `old`)
    under the noise `new` (`clip` of `_residuals_model`: lo, hi, noise, scale), and
    the Newton decrement under it at the point moved by `moved` (the solve's settling
    step; the residuals there to first order): what a pass with the new noise would
    still gain. The rows' derivatives of the model are the old rows' with the
    clipped slope and the noise scale changed (rows whose old slope is below 1e-6,
    clipped away, are dropped); the last residual, the ring-flux prior, is kept."""
    rows = _gaussian_rows(model, data, weight, new)
    slope_old = clipped_slope(model, old[0], old[1], old[2])
    slope_new = clipped_slope(model, new[0], new[1], new[2])
    factor = jnp.where(slope_old > 1e-6, slope_new / jnp.maximum(slope_old, 1e-6), 0.0)
    factor = factor * old[3] / new[3]
    r = jnp.concatenate([rows.ravel(), r[-1:]])
    jac = jac * jnp.concatenate([factor.ravel(), jnp.ones(1, jac.dtype)])[:, None]
    return r, jac, newton_decrement(r + jac @ moved, jac)


def _load(image):
    """`(img, fits, transfer)`: the image as float64 `(H, W)` (channels averaged, NaN
    kept), the `FitsImage` when it came from a FITS file (else `None`) and how a file's
    values were read (`read_observation_transfer`; `"linear"` for FITS, `None` for an
    array)."""
    from pathlib import Path

    fits, transfer = None, None
    if isinstance(image, (str, Path)):
        if str(image).lower().endswith((".fits", ".fit", ".fts", ".fits.gz")):
            from .fits import read_fits

            fits = read_fits(image)
            img, transfer = fits.data, "linear"
        else:
            img, transfer = read_observation_transfer(image)
    else:
        img = real_image(image)
    if img.ndim == 3:
        img = img.mean(axis=-1)
    if img.ndim != 2 or min(img.shape) < 8:
        raise ValueError(f"image of shape {np.shape(img)} is not (H, W) or (H, W, C) of >= 8 px")
    return np.asarray(img, np.float64), fits, transfer


def _read_mask(mask, shape):
    if mask is None:
        return np.zeros(shape, bool)
    if isinstance(mask, str) or hasattr(mask, "__fspath__"):
        mask = read_observation(mask) > 0.5
    mask = np.asarray(mask, bool)
    if mask.shape != shape:
        raise ValueError(f"mask of shape {mask.shape} does not match the image {shape}")
    return mask


def _gain_estimate(img, valid):
    """Counts per data unit from the mean-variance relation of Poisson noise
    (variance = mean / gain), over 8 x 8 tiles (robust variance from second
    differences), the median of mean / variance over tiles with signal."""
    h, w = img.shape
    ratios = []
    for r in range(0, h - 7, 8):
        for c in range(0, w - 7, 8):
            t, ok = img[r : r + 8, c : c + 8], valid[r : r + 8, c : c + 8]
            if not ok.all():
                continue
            var = noise_level(t) ** 2
            mean = float(t.mean())
            if var > 0 and mean > 0:
                ratios.append(mean / var)
    if not ratios:
        raise ValueError("cannot estimate the gain (no tile with signal): give gain=")
    return float(np.median(ratios))


def _source_start(img, valid, floor, ring_px):
    """Azimuth (radians, image plane, 0 = +x toward +y) of the brighter arc: the first
    moment of the light above the floor in an annulus about the ring radius."""
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w]
    x, y = xx + 0.5 - 0.5 * w, 0.5 * h - (yy + 0.5)
    rho = np.hypot(x, y)
    band = valid & (np.abs(rho - ring_px) < max(3.0, 0.3 * ring_px))
    wgt = np.clip(img - floor, 0.0, None) * band
    total = wgt.sum()
    if total <= 0:
        return 0.0
    c, s = (wgt * x / np.maximum(rho, 1e-9)).sum(), (wgt * y / np.maximum(rho, 1e-9)).sum()
    return math.atan2(s, c)


def _psf_width(psf) -> float:
    """The Gaussian width (pixels) of a PSF: a Gaussian's own, or an image's rms offset
    from its centroid along one axis (negative pixels counted as 0)."""
    if np.ndim(psf) == 0:
        return float(psf)
    p = np.clip(np.asarray(psf, np.float64), 0.0, None)
    total = p.sum()
    if not total > 0:
        return 0.0
    y, x = np.indices(p.shape)
    cx, cy = (p * x).sum() / total, (p * y).sum() / total
    return math.sqrt((p * ((x - cx) ** 2 + (y - cy) ** 2)).sum() / (2.0 * total))


def _unblurred_width(width_px: float, psf_px: float) -> float:
    """A ring's radial Gaussian width before a PSF of Gaussian width `psf_px` blurred
    it to `width_px` (pixels): the widths in quadrature, at least a quarter of
    `width_px` (where the PSF makes nearly all of it, the difference is noise)."""
    return math.sqrt(max(width_px**2 - psf_px**2, (0.25 * width_px) ** 2))


def _arcs_candidates(arcs, width: int, blur_px: float = 0.0):
    """Cameras along the exact ring relation that put the Einstein ring at the arcs'
    radius: `(distance, fov, focal, sigma)` arrays (R_S, radians, pixels, radians),
    sigma the star width the arcs' radial width implies (radial magnification 1/2 at
    the Einstein ring, the blur `blur_px` and the pixel removed in quadrature)."""
    d, a_e, _, _ = _starts._ring_table()
    focal = arcs.ring_radius / np.tan(a_e)
    fov = 2.0 * np.arctan(0.5 * width / focal)
    ok = (fov > math.radians(0.05)) & (fov < math.radians(179.0))
    intrinsic = math.sqrt(max(arcs.ring_width**2 - blur_px**2 - 1.0 / 12.0, 0.25))
    return d[ok], fov[ok], focal[ok], 2.0 * intrinsic / focal[ok]


def _arcs_camera(arcs, width: int, sigma: float):
    """A first `{"distance", "fov", "sigma"}` for arcs with no shadow in view: the
    camera whose ring relation and radial magnification give arcs of the measured
    radius and width for a star of width `sigma` (radians); refined by
    `_arcs_distance_scan` once the model is set up."""
    d, fov, _, sig = _arcs_candidates(arcs, width)
    i = int(np.argmin(np.abs(np.log(sig / sigma))))
    return {"distance": float(d[i]), "fov": float(fov[i])}


def _arcs_distance_scan(theta0, free, arcs, width, blur_px, args, prob):
    """The internal parameters `theta0` with D, FOV, the source (and sigma, when free)
    set to the candidate of `_arcs_candidates` whose full-model loss is lowest: the
    source offset at each D from the arcs' radii, along their azimuth."""
    d, fov, focal, sig = _arcs_candidates(arcs, width, blur_px)
    beta = np.asarray(source_offset_from_arcs(arcs, d, focal), float)
    ok = np.isfinite(beta)
    values = {"distance": d, "fov": fov, "source_lon": beta * math.cos(arcs.psi),
              "source_lat": beta * math.sin(arcs.psi), "sigma": sig}  # fmt: skip
    best, best_loss = theta0, math.inf
    for j in np.flatnonzero(ok):
        cand = np.array(theta0, float)
        for n, v in values.items():
            if n in free:
                cand[free.index(n)] = parameter(n).transform.inverse(float(v[j]))
        loss = float(_loss(to_device(cand), args, prob))
        if loss < best_loss:
            best, best_loss = cand, loss
    return best


def fit(
    scene: Scene,
    image,
    *,
    free=DEFAULT_FREE,
    psf=None,
    noise="gaussian",
    gain: float | None = None,
    mask=None,
    init: dict | None = None,
    supersample: int | None = None,
    block: int | None = None,
    max_pixels: int | None = None,
    knots: int = 4096,
    rtol: float = 1e-6,
    atol: float | None = None,
    max_steps: int = 100,
):
    """Fit the parameters of a scene to an observed image.

    The model is the scene rendered by area-exact sampling (`Camera(...,
    sampling="gauss")`, Gauss-Legendre cells with the exact shadow-edge coverage and
    the thin relativistic rings), averaged over the colour channels, optionally blurred
    by a point-spread function (FFT, on a margin rendered around the frame), compared
    with the image's pixels (or bins of them) under a noise model by
    `optimistix.least_squares` (Levenberg-Marquardt) on unbounded internal parameters
    (`jaxlens._fit.params` transforms: D > 1, 0 < FOV < pi, sigma > 0, ...). Errors
    come from the Gauss-Newton curvature at the optimum (Laplace approximation).

    **Arguments:**
    - `scene`: the model `Scene` (its camera's width/height are replaced by the
      image's). Its sky must hold a `GaussianStar` (the source) and, to fit `floor`, a
      `Uniform`. Its values are the starting point for what `init` and the image do
      not give.
    - `image`: array `(H, W)` / `(H, W, C)` of linear values (NaN: masked), or a path
      (FITS through astropy: the WCS pixel scale fixes the FOV; other formats by
      `read_observation`: sRGB-tagged or untagged 8/16-bit files decoded to linear,
      float and linear-tagged files as stored; `Fit.transfer` says which).
    - `free`: names of the parameters to fit: `distance`, `fov`, `yaw`, `pitch`,
      `source_lon`, `source_lat`, `sigma`, `brightness`, `floor`, `psf_sigma`,
      `ring_flux` (the thin rings' flux factor, with a prior N(1, 1), for images of
      renderers that alias them).
    - `psf`: `None`; a number (a Gaussian PSF of that width, pixels; fitted when
      `psf_sigma` is in `free`, starting there); or a PSF image (array).
    - `noise`: `"gaussian"` (sigma estimated from the image and the residuals), a
      number (Gaussian of that sigma, data units), or `"poisson"` (counts = `gain` x
      value; `gain` estimated from the image when not given).
    - `mask`: bool array (True = bad pixel) or a mask image path (> 0.5 = bad).
    - `init`: starting values by parameter name (physical units; `fov_deg` allowed).
    - `supersample`: the Gauss-Legendre order k (default: from the ring's width in the
      compared bins before the PSF, the image's width less the PSF's in quadrature:
      the smallest k averaging its Gaussian to ~4e-5 of its peak; 3 at least under a
      PSF).
    - `block`, `max_pixels`: the bins compared. Without a PSF, bins of side `block`
      (default 1, larger only when the ring is wide and the image large) where the
      image has structure (the ring's band, the shadow's edge, any light 3 noise
      sigmas above the floor) and coarse blocks where it is flat, at most
      `max_pixels` (default 40,000) in all; with a PSF, a regular grid of bins of side
      `block` (default: the smallest leaving at most `max_pixels`, default 65,536).
    - `knots`: of the ray map; `rtol`, `atol`, `max_steps`: Levenberg-Marquardt settings.

    **Returns:** a `Fit`. A host driver: under `jit`, `vmap` or `grad` it raises a
    `TypeError` (differentiate the model, `ring_image` or `render_array`, instead).
    """
    host_driver("fit", "differentiate the model (jaxlens.ring_image, "
                "jaxlens.render_array) instead", scene, image, init)  # fmt: skip
    t_start = time.perf_counter()
    img, fits, transfer = _load(image)
    h, w = img.shape
    valid = np.isfinite(img) & ~_read_mask(mask, img.shape)
    if fits is not None:
        valid &= ~fits.mask
    if valid.sum() < 64:
        raise ValueError(f"only {int(valid.sum())} valid pixels: nothing to fit")
    free = tuple(free)
    for n in free:
        star_index = split_name(n)[1]  # an unknown name is refused here
        if star_index > 1:
            star_of(scene.sky, star_index)  # ... and a star the sky does not have
    init = dict(init or {})
    if "fov_deg" in init:
        init["fov"] = math.radians(init.pop("fov_deg"))
    if fits is not None and fits.fov is not None and "fov" not in init:
        init["fov"] = fits.fov
        free = tuple(n for n in free if n != "fov")  # the WCS fixes it
    psf_kind = None
    if psf is not None:
        psf_kind = "image" if np.ndim(psf) == 2 else "gaussian"
        if psf_kind == "gaussian":
            try:
                width = float(psf) if np.ndim(psf) == 0 else math.nan
            except (TypeError, ValueError):
                width = math.nan
            if not 0 < width < math.inf:
                raise ValueError(f"psf={psf!r} must be a Gaussian PSF's width in pixels "
                                 "(> 0, finite) or a PSF image (2-D)")  # fmt: skip
    if "psf_sigma" in free and psf_kind != "gaussian":
        raise ValueError("psf_sigma is fitted only for a Gaussian PSF: give psf=<width in px>")
    gray = np.where(valid, img, np.nanmedian(img[valid]))
    lo, hi = clipping_bounds(gray)
    sigma_known = isinstance(noise, (int, float))
    noise_sigma = float(noise) if sigma_known else noise_level(gray)
    # An estimated noise must be the image's own: a noiseless (rendered, averaged)
    # image gives errors that measure the misfit, not a measurement's scatter.
    noise_seen = sigma_known or noise == "poisson" or white_noise_found(gray)[0]
    kind = "poisson" if noise == "poisson" else "gaussian"
    if kind == "poisson" and gain is None:
        gain = _gain_estimate(img, valid)

    with jax.enable_x64(True):
        cam0 = scene.camera
        span = float(np.max(img[valid]) - np.min(img[valid]))
        if span <= 1e-12 * max(1.0, abs(float(np.max(img[valid])))):
            raise ValueError(f"image is blank (every valid pixel is {float(img[valid][0]):.6g}): "
                             "no ring to fit")  # fmt: skip
        prof = _starts._profile(gray)
        scale = max(prof.peak + prof.floor, 1e-12)
        masked = np.where(valid, img, np.nan)
        # The hole's image and the source: the arcs' centre, azimuth and radii.
        arcs = find_arcs(masked)
        found = arcs.score > 10.0
        arc_like = found and arcs.offset > max(1.0, 0.5 * arcs.ring_width)
        if arc_like:
            # Arcs, not a ring: the radial profile about the image centre mixes the two
            # arcs' radii, so the ring start takes the arcs' Einstein radius and width.
            r, wr = arcs.ring_radius, arcs.ring_width
            prof = eqx.tree_at(lambda q: (q.ring_radius, q.ring_width, q.inner_half,
                                          q.outer_half), prof,
                               (r, wr, r - 1.1774 * wr, r + 1.1774 * wr))  # fmt: skip
        if not prof.peak > 8.0 * prof.peak_noise and arcs.score <= 10.0:
            raise ValueError(
                f"no ring or arcs found: the radial profile about the image centre peaks "
                f"{prof.peak:.3g} above its floor, within 8 times its noise "
                f"({prof.peak_noise:.3g}), and no arcs stand out of the noise"
            )
        if not sigma_known and (math.isfinite(lo) or math.isfinite(hi)):
            # Values clipped at the format's range: the noise from the flat sky, which
            # clipping below the median leaves intact (second differences of clipped
            # zeros would underestimate it).
            noise_sigma = noise_clipped(gray, prof, lo, hi)
        start = values_of(scene) | {"psf_sigma": float(psf) if psf_kind == "gaussian"
                                    else 1.0, "ring_flux": 1.0}  # fmt: skip
        psf_px = 0.0 if psf_kind is None else _psf_width(psf)
        if atol is None:
            atol = 1e-6

        def setup(start, f_px, centre):
            """The compared bins and the model's arguments for the starting values
            `start`, a focal length `f_px` (pixels) and the hole's image at `centre`:
            `(pix, k, model_scene, args, prob, theta0, solve_args)`."""
            b = block
            if psf_kind is None:
                # The shadow's edge where the image shows it (its radial profile's, which
                # `_pixel_sets` takes itself, else the arcs' model's), else where the
                # starting distance puts it.
                if math.isfinite(prof.shadow_radius):
                    rho_sh = math.nan
                elif math.isfinite(edge_seen):
                    rho_sh = edge_seen
                else:
                    rho_sh = f_px * math.tan(_shadow_angle(max(start["distance"], 1.6), np))
                pix = _pixel_sets(gray, prof, rho_sh, max_pixels or 40_000, block,
                                  valid=valid, centre=centre,
                                  structure=prof.floor + 3.0 * noise_sigma)  # fmt: skip
            else:
                if b is None:
                    b = 1
                    while (h // b) * (w // b) > (max_pixels or 65_536):
                        b += 1
                pix = _grid_sets(gray, valid, int(b))
            b = pix.block
            # The rendered ring's width: the image's, less the PSF's in quadrature (a
            # narrow ring under a wide PSF needs a higher order than its image shows).
            # Under a PSF order 2 is not used: the measured width's error grows as the
            # PSF's share of it does.
            k = (int(supersample) if supersample is not None
                 else _samples_for(_unblurred_width(prof.ring_width, psf_px), b,
                                   2 if psf_kind is None else 3))  # fmt: skip
            yaw, pitch, roll = (np.asarray(v) for v in (cam0.yaw, cam0.pitch, cam0.roll))
            cam = Camera(start["distance"], start["fov"], w, h, yaw=yaw, pitch=pitch, roll=roll,
                         supersample=k, sampling="gauss", dtype=np.float64)  # fmt: skip
            sky = jax.tree.map(lambda a: to_device(a, np.float64), scene.sky)
            # Values given for parameters held fixed are the model's.
            held = {n: v for n, v in init.items() if n not in free}
            model_scene = apply(Scene(cam, sky), {n: v for n, v in held.items() if in_scene(n)})
            pad, otf = 0, None
            if psf_kind is None:
                grid = tuple(to_device(np.concatenate(v)) for v in zip(pix.fine, pix.coarse_edges))
                grid += (to_device(pix.side, jnp.float64),)
            else:
                if psf_kind == "gaussian":
                    pad = -(-math.ceil(4.0 * max(start["psf_sigma"], 0.5) * 1.5) // b)
                else:
                    pad = -(-(max(np.shape(psf)) // 2 + 1) // b)
                pad = -(-pad // 4) * 4  # margins in steps of 4 bins: PSFs share programs
                x0, y0 = (np.asarray(v) for v in _pixel_edges(w, h, b, np.float64))
                xs = x0[0, 0] + b * np.arange(-pad, x0.shape[1] + pad)
                ys = y0[0, 0] - b * np.arange(-pad, y0.shape[0] + pad)
                grid = tuple(to_device(v) for v in np.meshgrid(xs, ys))
                if psf_kind == "image":
                    otf = _psf.image_otf(grid[0].shape, np.asarray(psf, np.float64))
            # Every parameter of the model: the scene's own, then the PSF's width and the
            # rings' flux factor.
            given = values_of(model_scene)
            names = tuple(given) + ("psf_sigma",) * (psf_kind == "gaussian") + ("ring_flux",)
            for n in free:
                if n not in names:  # a floor the sky does not have: say so
                    floor_of(model_scene.sky)
            given |= {n: start[n] for n in ("psf_sigma", "ring_flux")}
            sel = _select(names, free, {n: start[n] if n in free else given[n] for n in names})
            turned = (
                bool({"yaw", "pitch"} & set(free))
                or bool(np.any(roll))
                or any(given.get(n, 0.0) != 0.0 for n in ("yaw", "pitch"))
            )
            prob = _Problem(names, b, k, pad, kind, psf_kind, int(knots), centred=not turned)
            # Clipping acts on each original pixel, with its own noise.
            clip = to_device([lo, hi, noise_sigma, max(noise_sigma, 1e-12 * scale)])
            args = (model_scene, grid, otf, to_device(pix.data), to_device(pix.weight), clip,
                    to_device(gain if gain is not None else 1.0), sel)  # fmt: skip
            theta0 = np.asarray([parameter(n).transform.inverse(start[n]) for n in free])
            solve_args = (args, prob, to_device(rtol), to_device(atol), int(max_steps))
            return pix, k, model_scene, args, prob, theta0, solve_args

        # Arcs with no shadow in view: nothing in the ring's profile fixes D (a centred
        # ring's candidates fit the arcs' azimuthal mean: D 3300 for the benchmark's
        # D 150 arcs), so D is chosen below by the full model along the ring relation.
        scan_d = (arc_like and not math.isfinite(arcs.shadow_radius)
                  and {"distance", "fov", "source_lon", "source_lat"} <= set(free)
                  and not {"distance", "fov", "source_lon", "source_lat"} & set(init))  # fmt: skip
        # The source's offset is scanned with the loss where it is free and not given,
        # and the image shows arcs (or nothing the arcs' model took for a ring): for a
        # ring, offset by less than a pixel or half its width, it starts behind the hole
        # (where the scan put it on 13 of the fit benchmark's 14 rings; on the other
        # 2.8e-4 of its loss away), and the fit compiles neither the loss nor the arcs'
        # exact rays.
        scan_source = ({"source_lon", "source_lat"} <= set(free)
                       and not {"source_lon", "source_lat"} & set(init)
                       and (arc_like or not found))  # fmt: skip
        # The compared bins do not depend on the starting values where they are a
        # regular grid (with a PSF, or an image small enough to compare every pixel) or
        # where the image shows the shadow's edge and the hole's image stays where the
        # arcs put it: the model's programs then compile on the second core while the
        # start is searched.
        early = ahead()  # nothing, unless the shapes are known now
        moves = found and bool({"yaw", "pitch"} & set(free))  # the arcs are found again
        centre = (arcs.x_c, arcs.y_c) if found and not moves else (0.0, 0.0)
        edge_seen = arcs.shadow_radius if found else math.nan
        first = setup(start | init, 0.5 * w / math.tan(0.5 * (start | init)["fov"]), centre)
        if first[0].coarse == 0 or not moves and (math.isfinite(prof.shadow_radius)
                                                  or math.isfinite(edge_seen)):  # fmt: skip
            *_, args_, prob_, theta_, solve_ = first
            theta_ = to_device(theta_)
            scans = [(_loss, theta_, args_, prob_)] if scan_d or scan_source else []
            early = ahead(*scans, (_solve, theta_, *solve_))
        # --- starting values from the image where init does not give them.
        ring_free = {"distance", "fov", "sigma", "brightness", "floor"} & set(free)
        ring_init = None
        if scan_d:
            start |= init | _arcs_camera(arcs, w, init.get("sigma", start["sigma"]))
        elif ring_free - set(init) and prof.peak > 8.0 * prof.peak_noise:
            sig = None if "sigma" in free else init.get("sigma", start["sigma"])
            if "distance" in init and "fov" in init:
                ring_init = {n: init[n] for n in ("distance", "fov", "sigma") if n in init}
            elif arc_like and math.isfinite(arcs.shadow_radius):
                # Arcs around a visible shadow: the ratio of their Einstein radius to
                # the shadow's fixes D (a centred ring's candidates can fit arcs at the
                # wrong distance: D 3.0, FOV 143 deg for D 20, FOV 60 deg).
                ring_init = _starts.distance_from_radii(arcs.ring_radius, arcs.shadow_radius, w)
            d_s, fov_s, sig_s, a_s, fl_s, *_ = _starts.ring_start(gray, prof, sig, ring_init, scale)
            guess = {"distance": d_s, "fov": fov_s, "sigma": sig_s, "brightness": a_s,
                     "floor": fl_s}  # fmt: skip
            # The ring start refines what `init` gives of D, FOV and sigma (its own
            # candidates), so those refined values stand; other given values win.
            refined = set(ring_init or ())
            start |= init | {n: v for n, v in guess.items()
                             if n in free and (n not in init or n in refined)}  # fmt: skip
            if ring_init is not None and "distance" not in init:
                # From the arcs' radii: the ring start's centred-ring model, which does
                # not describe arcs, moved the FOV 7 % off (74.6 deg for 70) on the
                # benchmark's first arcs image, and the fit then settled 15 % off in D.
                start |= ring_init
        else:
            start |= init
        if arc_like:
            # The ring start's brightness and floor are the ring's azimuthal mean.
            start |= {n: v for n, v in (("brightness", arcs.amplitude), ("floor", arcs.floor))
                      if n in free and n not in init}  # fmt: skip
        f_px = 0.5 * w / math.tan(0.5 * start["fov"])
        if found and {"yaw", "pitch"} & set(free):
            # A hole off the image centre: its image as a camera turned toward it sees
            # the arcs (the oblique projection moves the ring's centre).
            arcs = find_arcs(masked, focal=f_px)
            found = arcs.score > 10.0
            edge_seen = arcs.shadow_radius if found else math.nan
        # --- the compared bins. Without a PSF: full resolution where the image has
        # structure (the ring, the arcs, the shadow's edge), coarse blocks where it is
        # flat; with one, a regular grid of bins rendered on a margin the PSF reaches.
        centre = (arcs.x_c, arcs.y_c) if found else (0.0, 0.0)
        pix, k, model_scene, args, prob, theta0, solve_args = setup(start, f_px, centre)
        block, data, count = pix.block, pix.data, pix.count
        clipped = math.isfinite(lo) or math.isfinite(hi)
        passes = 2 if kind == "gaussian" and not sigma_known and clipped else 1
        # The solver's program (where not compiled already) compiles on the second core
        # while the starting values' scans below compile and run, and the noise check's
        # where a second pass may need it (its shapes: the model's and the data's, the
        # residuals one longer).
        later = [(_solve, to_device(theta0), *solve_args)]
        if passes == 2:
            shape, nt = args[3].shape, len(theta0)
            n = math.prod(shape) + 1
            placeholders = (to_device(np.zeros(v)) for v in (shape, n, (n, nt), nt))
            model, r, jac, moved = placeholders
            later.append((_renoised, model, *args[3:6], args[5], r, jac, moved))
        with ahead(*later), early:
            # --- the hole's image (yaw, pitch) and the source from the arcs, the offset
            # refined by a scan of the loss along their azimuth.
            for name, c in (("yaw", arcs.x_c), ("pitch", arcs.y_c)):
                if name in free and name not in init and found:
                    theta0[free.index(name)] = math.atan(-c / f_px)  # the view turned away
            if scan_d:
                blur = float(psf) if psf_kind == "gaussian" else 0.0
                theta0 = _arcs_distance_scan(theta0, free, arcs, w, blur, args, prob)
                start |= {n: float(parameter(n).transform.forward(theta0[i]))
                          for i, n in enumerate(free)
                          if n in ("distance", "fov", "sigma")}  # fmt: skip
                f_px = 0.5 * w / math.tan(0.5 * start["fov"])
            if scan_source:
                if found:
                    psi = arcs.psi
                    beta = float(source_offset_from_arcs(arcs, start["distance"], f_px))
                else:
                    psi = _source_start(gray, valid, start.get("floor", 0.0), prof.ring_radius)
                    beta = math.nan
                offsets = [0.0] + list(np.geomspace(0.05, 6.0, 8) * math.pi / 180.0)
                if math.isfinite(beta) and beta > 0:
                    offsets += list(beta * np.asarray([0.6, 0.8, 1.0, 1.25, 1.6]))
                i_lon, i_lat = free.index("source_lon"), free.index("source_lat")
                cands = np.repeat(theta0[None], len(offsets), axis=0)
                cands[:, i_lon] = np.asarray(offsets) * math.cos(psi)
                cands[:, i_lat] = np.asarray(offsets) * math.sin(psi)
                losses = [float(_loss(to_device(c), args, prob)) for c in cands]
                theta0 = cands[int(np.nanargmin(np.where(np.isfinite(losses), losses, np.inf)))]
        steps = 0  # over the passes
        for i in range(passes):
            theta, r, jac, model, result, taken, moved = _solve(to_device(theta0), args,
                                                                 *solve_args[1:])  # fmt: skip
            steps += int(taken)
            if i == 0 and passes == 2:
                # The clipped model's noise, re-estimated from the residuals well inside
                # (lo, hi), for the second pass (same program: the noise is an argument).
                m_np = np.asarray(model)
                inside = (count > 0) & (m_np > lo + 4 * noise_sigma) & (m_np < hi - 4 * noise_sigma)
                if inside.sum() > 50:
                    # Refined within [0.7, 1.5] of the image's own estimate: a model far
                    # from the image (a floor below the sky's, whose clipped mean a
                    # larger noise then explains) must not buy a smaller chi^2 by a
                    # larger noise (seen: noise x 3, floor 0 for 0.05, chi^2/dof 0.1).
                    refit = float(np.std((data - m_np)[inside] * np.sqrt(count[inside])))
                    noise_sigma = min(max(refit, 0.7 * noise_sigma), 1.5 * noise_sigma)
                    clip = to_device([lo, hi, noise_sigma, max(noise_sigma, 1e-12 * scale)])
                    # A second pass only where the new noise moves the optimum (see
                    # `_RENOISED_CHI2`); otherwise the first pass's point stands, with
                    # the residuals and Jacobian of the new noise.
                    r2, jac2, dec = _renoised(model, args[3], args[4], args[5], clip, r, jac,
                                              moved)  # fmt: skip
                    args = args[:5] + (clip,) + args[6:]
                    if float(dec) < _RENOISED_CHI2:
                        r, jac = r2, jac2
                        break
                theta0 = np.asarray(theta)
        theta, r = np.asarray(theta), np.asarray(r).ravel()
        jac = np.asarray(jac).reshape(r.size, -1)
        # The residuals at theta, to first order from the point the solve evaluated last
        # (one settling step before it; its Jacobian stands for theta's).
        r = r + jac @ np.asarray(moved)
        model = np.asarray(model)
        phys = {n: float(parameter(n).transform.forward(theta[i])) for i, n in enumerate(free)}
        fitted = apply(model_scene, {n: v for n, v in phys.items() if in_scene(n)})
    out = _finish(fitted, free, phys, start, theta, r, jac, result, steps, model, data, count,
                  kind, noise_sigma, gain, block, k, prob, t_start,
                  sigma_known, pix, math.isfinite(prof.shadow_radius), noise_seen)  # fmt: skip
    return dataclasses.replace(out, transfer=transfer)


def _finish(scene, free, phys, start, theta, r, jac, result, steps, model, data, count, kind,
            noise_sigma, gain, block, k, prob, t_start, sigma_known, pix, shadow_seen,
            noise_seen):  # fmt: skip
    prior = 1  # the last residual: the ring-flux prior (0 when the flux is held)
    n_data = int((count > 0).sum())
    p = len(free)
    rss = float(np.sum(r[: r.size - prior] ** 2))
    chi2_dof = rss / max(n_data - p, 1)
    jtj = jac.T @ jac
    finite = bool(np.all(np.isfinite(jtj)) and np.all(np.isfinite(theta)))
    cov_int, cond = np.full((p, p), np.nan), math.inf
    if finite:
        ds = np.sqrt(np.diag(jtj))
        if np.all(ds > 0):
            norm = jtj / np.outer(ds, ds)
            ev = np.linalg.eigvalsh(norm)
            cond = float(ev[-1] / max(ev[0], 1e-300))
            cov_int = np.linalg.pinv(norm) / np.outer(ds, ds)
    # Gaussian noise estimated from the image: the residuals set its scale.
    s2 = chi2_dof if kind == "gaussian" and not sigma_known else 1.0
    g = np.diag([parameter(n).transform.slope(phys[n]) for n in free])
    cov = g @ cov_int @ g.T * s2
    err = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(err, err)

    ok = bool(result == optx.RESULTS.successful)
    notes, degenerate = [], False
    if not ok:
        notes.append(f"the solver stopped: {_result_name(result)}")
    at_bound = [n for n in free if parameter(n).transform.at_bound(phys[n])]
    if at_bound:
        notes.append("at the bound of its range: " + ", ".join(at_bound))
    # Parameters the image does not separate: each loose (relative error above 20 %)
    # and mostly explained by the others (variance inflation 1 / (1 - R^2) above 100,
    # R the multiple correlation with the rest); D and FOV, always correlated, are
    # separated by the ring and the shadow as long as their errors are small.
    rel = [err[i] / max(abs(phys[n]), 1e-300) for i, n in enumerate(free)]
    vif = np.full(p, np.nan)
    if np.all(np.isfinite(corr)):
        vif = np.diag(np.linalg.pinv(corr))
    group = [n for i, n in enumerate(free) if rel[i] > 0.2 and vif[i] > 100.0]
    if len(group) >= 2 or not math.isfinite(cond) or cond > 1e14:
        degenerate = True
        if len(group) >= 2:
            names = ", ".join(group[:-1]) + " and " + group[-1]
            worst = max(vif[free.index(n)] for n in group)
            notes.append(f"the image cannot separate {names} (errors above 20 %, variance "
                         f"inflation up to {worst:.3g}): fix one of them")  # fmt: skip
        else:
            notes.append(f"the curvature is singular (condition {cond:.2g})")
    vif_ring = math.nan
    if {"distance", "fov"} <= set(free) and np.all(np.isfinite(corr)):
        # What a ring fixes: D and FOV apart, and with sigma free, what separates them
        # from it (the shadow's edge or the relativistic ring).
        errs = {n: float(e) for n, e in zip(free, err)}
        deg_r, note, vif_ring = _ring_verdict(free, phys, errs, corr, shadow_seen)
        if deg_r:
            degenerate = True
            notes.append(note)
    # Nuisances outside their physical range: a star's peak radiance and the relativistic
    # rings' flux factor are not negative; a fit that needs them so, beyond 3 standard
    # errors, describes something else (seen: the README's ring fitted with a negative
    # ring flux at D = 2.5). Within them (-0.4 +- 0.24 on a point-sampled render, whose
    # thin rings alias) the value is zero within its error: no flag.
    for i, n in enumerate(free):
        base = split_name(n)[0]
        if base in ("brightness", "ring_flux") and phys[n] < 0.0 and not phys[n] >= -3.0 * err[i]:
            what = "a star's brightness" if base == "brightness" else "the rings' flux"
            notes.append(f"{n} = {phys[n]:.3g} +- {err[i]:.2g} is negative, which {what} "
                         "cannot be: the model does not describe the image")  # fmt: skip
    if not noise_seen:
        notes.append("no pixel noise found in the image (a noiseless or smoothed one?): the "
                     "errors measure the misfit, not a noise; give the noise level "
                     "(noise=, --noise SIGMA) for errors that do")  # fmt: skip
    if kind == "gaussian" and chi2_dof > 4.0:
        notes.append(f"residuals {math.sqrt(chi2_dof):.2g} times the image's noise: the model "
                     "does not describe the image")  # fmt: skip
    elif kind == "poisson" and chi2_dof > 2.0:
        notes.append(f"deviance {chi2_dof:.3g} per degree of freedom: the counts are not "
                     "Poisson about the model (gain, background?)")  # fmt: skip
    converged = ok and finite and bool(np.all(np.isfinite(err))) and not at_bound
    values = {**start, **phys}
    values = {
        n: float(v)
        for n, v in values.items()
        if n in free
        or n in ("distance", "fov")
        or split_name(n)[0] in ("source_lon", "source_lat", "sigma")
    }
    errors = {n: float(e) for n, e in zip(free, err)}
    model_c = pix.paint(model)
    resid = pix.paint(np.where(count > 0, data - model, np.nan))
    return Fit(
        scene=scene, names=free, values=values, errors=errors, covariance=cov,
        correlation=corr, start={n: float(v) for n, v in start.items()}, noise=kind,
        noise_sigma=float(noise_sigma), gain=float(gain) if gain is not None else math.nan,
        chi2_dof=float(chi2_dof), model=model_c, residuals=resid, n_pixels=n_data,
        block=block, supersample=k, result=result, result_name=_result_name(result),
        num_steps=int(steps), variance_inflation=float(vif_ring),
        converged=bool(converged), degenerate=degenerate, message="; ".join(notes),
        seconds=time.perf_counter() - t_start,
    )  # fmt: skip
