"""`fit_ring`: starting values, the fit and its standard errors."""

import math
import time

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._exact import shadow_angle
from .model import _samples_for
from .pixels import _as_gray, _pixel_sets
from .result import RingFit, _diagnose, _result_name
from .solve import _model, _pack, _Setup, _solve, _unpack
from .starts import _profile, ring_start
from .table import _D_MIN


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

    The observation model is that of the `jaxlens._fit` package docstring; the fit runs in float64
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
    - `knots`: knots of the escape-angle table (`escape_table`, a `RayMap`).
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
        d_s, fov_s, sig_s, a_s, fl_s, lo, hi, noise = ring_start(img, prof, star_sigma, init, scale)

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
