"""`fit`: any parameter of a scene fitted to an image through the renderer's area-exact
sampling, with a point-spread function, Gaussian or Poisson noise and a mask. The
stages: `observation.observe` reads the image, `start` finds the starting values,
`objective.solve_passes` solves, `diagnose` gives the errors and the verdict."""

import dataclasses
import math
import time

import jax
import numpy as np

from .._compile import ahead
from .._exact import R_PHOTON
from .._psf import AbstractPSF, GaussianPSF
from .._scene import Scene
from .._util import host_driver, to_device
from . import start as st
from .arcs import find_arcs
from .diagnose import Solution, diagnose
from .fit_result import Fit
from .noise import white_noise_found
from .objective import loss, renoise_placeholders, solve, solve_passes
from .observation import Observation, observe
from .params import apply, in_scene, init_value, parameter, split_name, star_of
from .progress import Progress, progress_of
from .source import SourceDistance

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


def fit(
    scene: Scene,
    image,
    *,
    free=DEFAULT_FREE,
    transfer: str = "auto",
    pixels: str = "auto",
    psf=None,
    noise=None,
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
    source_distance: SourceDistance | None = None,
    progress=None,
) -> Fit:
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
    - `image`: an `Observation` (`observe`), a path (FITS through astropy: the WCS
      pixel scale fixes the FOV; any format OpenImageIO reads) or an array `(H, W)` /
      `(H, W, C)` of linear values (NaN: masked).
    - `transfer`: how an 8/16-bit file's values are decoded: `"auto"` (as the file
      says; a file that says nothing is fitted under both sRGB and linear decodings,
      and the one whose residuals fit the noise is kept, `Fit.transfer_reason` saying
      why, or the result flagged naming `transfer=`), `"srgb"` or `"linear"`
      (`observe`).
    - `pixels`: `"area"` (pixels average the light, as a camera's), `"point"` (the
      light at each pixel's centre, as a render with one ray a pixel) or `"auto"` (a
      file jaxlens wrote says which, else area) (`observe`).
    - `free`: names of the parameters to fit: `distance`, `fov`, `yaw`, `pitch`,
      `source_lon`, `source_lat`, `sigma`, `brightness`, `floor`, `psf_sigma`,
      `ring_flux` (the thin rings' flux factor, with a prior N(1, 1), for images of
      renderers that alias them).
    - `psf`: `None`; a number (a Gaussian PSF of that width, pixels; fitted when
      `psf_sigma` is in `free`, starting there); or a PSF image (array).
    - `noise`: `"gaussian"` (sigma estimated from the image and the residuals), a
      number (Gaussian of that sigma, data units), `"poisson"` (counts = `gain` x
      value; `gain` estimated from the image when not given), or a noise model
      (`jaxlens.Gaussian`, `jaxlens.Poisson`). `None` (default): an `Observation`'s
      own, else Gaussian.
    - `mask`: bool array (True = bad pixel) or a mask image path (> 0.5 = bad).
    - `init`: starting values by parameter name (physical units; `fov_deg` allowed;
      an astropy Quantity is converted: a dimensionless one for `distance`, an angle
      for `fov`, `sigma`, ...; a length in metres is refused, as by `Camera`).
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
    - `source_distance`: where the source lies, a `SourceDistance`: its radius $R$
      (R_S), or its distance behind the hole with the observer's distance (then $R$
      follows the fitted $D$ and `Fit.mass` is measured) or with the mass (then
      `Fit.observer_distance` is measured). `None` (default): the scene's own
      `source_distance` where it has one (a fixed radius), else at infinity. The model
      and the start's ring relation then read the ray map of the crossings of that
      sphere after each ray's periapsis (`source_table`: a source behind the hole,
      beyond the camera's radius or inside it); a fit that ends with the sphere inside
      the photon sphere ($R \\le 1.5$, which that map does not describe) is flagged in
      `message`.
    - `progress`: lines on stderr saying what the fit does (`fit: solving, pass 1: 4
      steps, chi2 6208 | 17.8 s`): the start's search, each solver pass with its
      steps and chi^2, the checks. `None` (default): on where stderr is a terminal or
      in a notebook, off elsewhere (a test run, a pipe, a batch job's log); `True`,
      `False`; or a callable that takes each stage's text instead of the line
      (`jaxlens fit` shows it on its status line).

    **Returns:** a `Fit`; its `message` names every check that failed, among them
    residuals beyond the noise model (with the likely cause: a missing PSF, clipped
    pixels, the file's decoding). A host driver: under `jit`, `vmap` or `grad` it raises a
    `TypeError` (differentiate the model, `ring_image` or `render_array`, instead).
    """
    host_driver("fit", "differentiate the model (jaxlens.ring_image, "
                "jaxlens.render_array) instead", scene, image, init)  # fmt: skip
    t_start = time.perf_counter()
    report = progress_of(progress)
    free = _checked_free(scene, free, psf)
    source_distance = _checked_source(scene, source_distance)
    obs = observe(image, transfer=transfer, mask=mask, psf=psf, noise=noise, gain=gain,
                  pixels=pixels)  # fmt: skip
    opts = _options(obs, free, init, block=block, max_pixels=max_pixels,
                    supersample=supersample, knots=knots, rtol=rtol,
                    atol=1e-6 if atol is None else atol, max_steps=max_steps,
                    source=source_distance)  # fmt: skip
    if obs.transfer_tagged:
        return _done(_fit_observed(scene, obs, opts, t_start, report), report)
    # A file that does not say how its values are encoded: both decodings are fitted.
    fits, errors = [], []
    for t, shown in (("srgb", "sRGB"), ("linear", "linear")):
        report.prefix = f"{shown} decoding: "
        try:
            fits.append(_fit_observed(scene, obs.decoded(t), opts, t_start, report))
        except ValueError as e:  # e.g. no ring stands out under one decoding
            report(f"no fit: {e}")
            errors.append(e)
    report.prefix = ""
    if not fits:
        raise errors[0]
    return _done(_decoding_chosen(fits, time.perf_counter() - t_start), report)


def _done(f: Fit, report: Progress) -> Fit:
    """`f`, its verdict reported."""
    verdict = "valid" if f.valid else "converged, FLAGGED" if f.converged else "NOT converged"
    report(f"done: {verdict}, {f.num_steps} steps (summary(): the values and checks)")
    return f


def _checked_free(scene, free, psf) -> tuple:
    """`free` as a tuple, every name known (and its star in the sky), `psf_sigma` only
    with a Gaussian PSF."""
    free = tuple(free)
    for n in free:
        star_index = split_name(n)[1]  # an unknown name is refused here
        if star_index > 1:
            star_of(scene.sky, star_index)  # ... and a star the sky does not have
    gaussian = (
        isinstance(psf, GaussianPSF) or not isinstance(psf, AbstractPSF) and np.ndim(psf) == 0
    )
    if "psf_sigma" in free and (psf is None or not gaussian):
        raise ValueError("psf_sigma is fitted only for a Gaussian PSF: give psf=<width in px>")
    return free


def _checked_source(scene, source) -> SourceDistance | None:
    """The fit's `SourceDistance`: the one given, else the scene's fixed radius (None
    for a source at infinity)."""
    if source is not None and not isinstance(source, SourceDistance):
        raise ValueError(f"source_distance={source!r} must be a SourceDistance (e.g. "
                         "jl.SourceDistance(radius=1e4)) or None (at infinity)")  # fmt: skip
    own = getattr(scene, "source_distance", None)
    if source is None and own is not None:
        r = float(np.max(np.asarray(own)))
        return None if math.isinf(r) else SourceDistance(radius=r)
    return source


def _options(obs: Observation, free: tuple, init, **settings) -> st.Options:
    """The fit's settings: `fov_deg` in `init` converted, the FOV held where a FITS
    WCS fixes it."""
    init = {name: init_value(name, v) for name, v in (init or {}).items()}
    if "fov_deg" in init:
        init["fov"] = math.radians(init.pop("fov_deg"))
    if obs.fov is not None and "fov" not in init:
        init["fov"] = obs.fov
        free = tuple(n for n in free if n != "fov")  # the WCS fixes it
    return st.Options(free, init, **settings)


def _fit_observed(scene, obs: Observation, opts: st.Options, t_start: float,
                  report: Progress) -> Fit:  # fmt: skip
    """One fit of an observation: look, start, solve, diagnose."""
    free, w = opts.free, obs.shape[1]
    with jax.enable_x64(True):
        report(f"looking for a ring or arcs in the {w} x {obs.shape[0]} image (compiling "
               "on first use)")  # fmt: skip
        seen = st.look(obs)
        noise = obs.noise.estimated(obs.data, obs.valid, profile=seen.prof, level=seen.level)
        # An estimated noise must be the image's own: a noiseless (rendered, averaged)
        # image gives errors that measure the misfit, not a measurement's scatter.
        noise_seen = not noise.checked_for_white_noise or white_noise_found(seen.grey)[0]
        scan_d, scan_source = st.scans(seen, opts)
        report(f"found {'arcs' if seen.arc_like else 'a ring'}: tracing the model and the solver")
        early = _compile_early(obs, seen, noise, scene, opts, scan_d or scan_source)
        try:
            report("start: the starting values (compiling on first use)")
            scale = max(seen.prof.peak + seen.prof.floor, 1e-12)
            values = st.starting_values(seen, obs, scene, opts, scale, scan_d)
            if seen.found and {"yaw", "pitch"} & set(free):
                # A hole off the image centre: its image as a camera turned toward it
                # sees the arcs (the oblique projection moves the ring's centre).
                arcs = find_arcs(obs.data, noise=seen.level[0],
                                 focal=st.focal(values["fov"], w))  # fmt: skip
                seen = dataclasses.replace(seen, arcs=arcs, found=arcs.found)
            centre = (seen.arcs.x_c, seen.arcs.y_c) if seen.found else (0.0, 0.0)
            s = st.build(obs, seen, noise, scene, opts, values, st.focal(values["fov"], w),
                         centre)  # fmt: skip
        except BaseException:
            # The early compiles finish before the error leaves: a compile thread still
            # running when the interpreter exits aborts it ("terminate called after
            # throwing ...": a fit refused by its start, exit code 134 for 2).
            early.wait()
            raise
        settings = dict(rtol=opts.rtol, atol=opts.atol, max_steps=opts.max_steps)
        # The solver (where not compiled already) compiles on the second core while
        # the start's scans compile and run, and the noise check where a second pass
        # may need it.
        later = [_solve_call(s, settings)]
        if s.data.noise.reestimated:
            later.append(renoise_placeholders(s.data, len(s.theta0)))
        report(f"start: {len(free)} free parameters, {s.data.data.size} bins compared "
               "(compiling the model and its Jacobian on first use)")  # fmt: skip
        with ahead(*later), early:
            theta0 = st.refine(s.theta0, seen, obs, s, opts, values, scan_d, scan_source,
                               report)  # fmt: skip
        theta, r, jac, model, result, steps, noise = solve_passes(theta0, s.data, s.prob, free,
                                                                  report=report,
                                                                  **settings)  # fmt: skip
        report("checking the residuals")
        phys = {n: float(parameter(n).transform.forward(theta[i])) for i, n in enumerate(free)}
        fitted = apply(s.scene, {n: v for n, v in phys.items() if in_scene(n)})
    sol = Solution(theta, phys, r, jac, result, steps, model)
    f = diagnose(fitted, obs, seen, s, noise, sol, values, free, noise_seen, t_start)
    f = dataclasses.replace(f, source_distance=opts.source)
    if opts.source is not None and not f.source_radius > R_PHOTON:
        note = (f"the source sphere (R = {f.source_radius:.6g} R_S) lies inside the photon "
                "sphere (R <= 1.5 R_S), which the model does not describe: a source behind "
                "the hole there is seen only inside the shadow")  # fmt: skip
        f = dataclasses.replace(f, message="; ".join(m for m in (f.message, note) if m))
    return f


def _solve_call(s: st.Setup, settings: dict):
    """`solve`'s call for a setup, as `ahead` takes it."""
    return (solve, to_device(s.theta0), s.data, s.prob, to_device(settings["rtol"]),
            to_device(settings["atol"]), int(settings["max_steps"]))  # fmt: skip


def _compile_early(obs, seen, noise, scene, opts, scanned: bool) -> ahead:
    """The model's programs compiled on the second core while the start is searched,
    where the compared bins do not depend on the starting values: a regular grid (with
    a PSF, or an image small enough to compare every pixel), or an image that shows the
    shadow's edge with the hole's image staying where the arcs put it."""
    moves = seen.found and bool({"yaw", "pitch"} & set(opts.free))
    centre = (seen.arcs.x_c, seen.arcs.y_c) if seen.found and not moves else (0.0, 0.0)
    values = st.starting_values_given(scene, obs, opts)
    first = st.build(obs, seen, noise, scene, opts, values,
                     st.focal(values["fov"], obs.shape[1]), centre)  # fmt: skip
    shapes_known = not moves and (seen.shadow_seen or math.isfinite(seen.edge_seen))
    if first.pix.coarse != 0 and not shapes_known:
        return ahead()  # nothing, unless the shapes are known now
    settings = dict(rtol=opts.rtol, atol=opts.atol, max_steps=opts.max_steps)
    theta = to_device(first.theta0)
    scans = [(loss, theta, first.data, first.prob)] if scanned else []
    return ahead(*scans, _solve_call(first, settings))


def _agree(a: Fit, b: Fit) -> bool:
    """Whether two fits' values agree within 3 of their combined standard errors."""
    for n in a.names:
        e = math.hypot(a.errors.get(n, math.nan), b.errors.get(n, math.nan))
        if not abs(a.values[n] - b.values[n]) <= 3.0 * e:
            return False
    return True


def _decoding_chosen(fits: list, seconds: float) -> Fit:
    """Of the fits of an untagged file under its sRGB and linear decodings, the one
    whose residuals fit the noise (`Fit.goodness`), or where both do and disagree, the
    one whose residuals' scatter does not change with brightness (`Fit.noise_trend`);
    where that cannot decide, the better one flagged with a message naming
    `transfer=`."""
    best = min(fits, key=lambda f: (not f.converged, f.goodness if math.isfinite(f.goodness)
                                    else f.chi2_dof))  # fmt: skip
    others = [f for f in fits if f is not best]
    passing = [f for f in fits if f.fits_noise]
    name = {"srgb": "sRGB", "linear": "linear"}
    note = ""
    if len(fits) == 1:
        reason = f"untagged file: only the {name[best.transfer]} decoding shows a ring"
    elif len(passing) == 1 and best.fits_noise:
        reason = (f"untagged file: the {name[best.transfer]} decoding's residuals fit the "
                  f"noise, the {name[others[0].transfer]} decoding's do not "
                  f"({others[0].goodness:.3g} standard deviations over)")  # fmt: skip
    elif len(passing) == 2 and _agree(*fits):
        reason = ("untagged file: its sRGB and linear decodings both fit the noise and agree; "
                  f"kept the {name[best.transfer]} one (the lower chi2)")  # fmt: skip
    elif len(passing) == 2 and len(flat := [f for f in fits if abs(f.noise_trend) <= 5.0]) == 1:
        # Both fit the noise's level, to different values: the right decoding leaves a
        # noise that does not change with brightness.
        best, other = flat[0], next(f for f in fits if f is not flat[0])
        reason = (f"untagged file: both decodings fit the noise's level, but the "
                  f"{name[other.transfer]} one's residuals change with brightness "
                  f"({other.noise_trend:+.3g} standard deviations), the "
                  f"{name[best.transfer]} one's do not ({best.noise_trend:+.2g})")  # fmt: skip
    else:
        what = "both fit the noise, to different values" if passing else "neither fits the noise"
        d = ", ".join(f"D = {f.values['distance']:.5g} ({name[f.transfer]})" for f in fits)
        reason = f"untagged file: of its sRGB and linear decodings {what}"
        note = (
            f"the file does not say how its values are encoded, and of its sRGB and "
            f"linear decodings {what} ({d}): give transfer= (--transfer srgb or linear)"
        )
    message = "; ".join(m for m in (best.message, note) if m)
    return dataclasses.replace(best, transfer_reason=reason, message=message, seconds=seconds)
