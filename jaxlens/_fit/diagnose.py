"""A fit's last stage: standard errors from the curvature, and the verdict: the
solver, the bounds, what the image cannot separate, the residuals against the noise
model (with the likely cause where they fail), nuisances out of their range."""

import dataclasses
import math
import time

import numpy as np
import optimistix as optx
import scipy.ndimage

from .fit_result import Fit
from .noise import GOODNESS_SIGMAS, AbstractNoise, clipping_bounds
from .params import parameter, split_name
from .result import result_name, ring_verdict


@dataclasses.dataclass(frozen=True)
class Solution:
    """What the solve leaves: the internal parameters `theta` and their physical
    values `phys`, the residuals `r` there (noise units, the ring-flux prior last) and
    their Jacobian `jac`, the optimistix `result`, the `steps` over every pass, and the
    `model` of the compared bins."""

    theta: np.ndarray
    phys: dict
    r: np.ndarray
    jac: np.ndarray
    result: object
    steps: int
    model: np.ndarray


def _covariance(jac, theta, free, phys, scale2):
    """`(cov, corr, err, cond, finite)` of the free parameters (physical units) from the
    Gauss-Newton curvature $J^T J$ (columns normalised), times `scale2`."""
    p = len(free)
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
    g = np.diag([parameter(n).transform.slope(phys[n]) for n in free])
    cov = g @ cov_int @ g.T * scale2
    err = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(err, err)
    return cov, corr, err, cond, finite


def _separation_notes(free, phys, err, corr, cond, shadow_seen):
    """Notes on parameters the image does not separate, and whether that makes the fit
    degenerate: each loose (relative error above 20 %) and mostly explained by the
    others (variance inflation $1/(1 - R^2)$ above 100); D and FOV, always correlated,
    are separated by the ring and the shadow as long as their errors are small."""
    p, notes, degenerate = len(free), [], False
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
    vif_ring, caveat = math.nan, ""
    if {"distance", "fov"} <= set(free) and np.all(np.isfinite(corr)):
        errs = {n: float(e) for n, e in zip(free, err)}
        deg_r, note, vif_ring, caveat = ring_verdict(free, phys, errs, corr, shadow_seen)
        if deg_r:
            degenerate = True
            notes.append(note)
    return notes, degenerate, vif_ring, caveat


def _nuisance_notes(free, phys, err, psf_given: bool, clipped: bool):
    """A star's peak radiance and the rings' flux factor are not negative: a fit that
    needs them so beyond 3 standard errors describes something else (seen: a ring fitted
    with a negative ring flux at D = 2.5; a ring blurred by 2 px fitted without its PSF,
    whose wider ring a camera twice as far explains, and its sharp relativistic ring a
    flux of -4): a note, which flags the fit. Within them (-0.4 +- 0.24 on a
    point-sampled render, whose thin rings alias) the value is zero within its error:
    an explanation, for the fit's caveat (the fitted value is not clipped at 0, which
    would bias the others and their errors).

    **Returns:** `(notes, explained)`, lists of texts."""
    notes, explained = [], []
    for i, n in enumerate(free):
        base = split_name(n)[0]
        if base not in ("brightness", "ring_flux") or not phys[n] < 0.0:
            continue
        what = "a star's brightness" if base == "brightness" else "the rings' flux"
        if phys[n] >= -3.0 * err[i]:
            seen = "the star's light" if base == "brightness" else "the thin relativistic rings"
            explained.append(f"{n} = {phys[n]:.3g} +- {err[i]:.2g} is negative, which {what} "
                             f"cannot be, but within 3 standard errors of zero: the image "
                             f"does not show {seen} above its noise (the estimate is not "
                             "clipped at 0, which would bias the other values)")  # fmt: skip
            continue
        note = (f"{n} = {phys[n]:.3g} +- {err[i]:.2g} is negative, which {what} cannot "
                "be: the model does not describe the image")  # fmt: skip
        if base == "ring_flux" and not clipped:
            # The thin rings are the sharpest feature: a negative flux takes light
            # from where a blur spreads it (or, in a saturated image, from a ring
            # whose peak was cut: the causes of the residual test say so).
            what = "a wider PSF" if psf_given else "a PSF"
            note += (f"; its sharpest features are sharper than the image's: give {what} "
                     "(psf=, --psf-sigma-px) or fit its width (free psf_sigma, "
                     "--fit-psf)")  # fmt: skip
        notes.append(note)
    return notes, explained


def blur_excess(model_img, resid_img, block: int) -> float:
    """How much more blurred the image is than the model (pixels, a Gaussian width in
    quadrature): the width $s$ whose blur of the model, $G_s * m - m$, best explains
    the residuals (widths 0.3-5 bins); NaN where even that one does not follow them
    (correlation below 0.3)."""
    m = np.asarray(model_img, np.float64)
    r = np.asarray(resid_img, np.float64)
    ok = np.isfinite(m) & np.isfinite(r)
    if ok.sum() < 16:
        return math.nan
    filled = np.where(np.isfinite(m), m, np.nanmedian(m))
    rv = r[ok]
    best, best_corr = math.nan, 0.3
    for width in np.geomspace(0.3, 5.0, 19):
        change = (scipy.ndimage.gaussian_filter(filled, width, mode="nearest") - filled)[ok]
        norm = math.sqrt(float(change @ change) * float(rv @ rv))
        corr = float(change @ rv) / norm if norm > 0 else 0.0
        if corr > best_corr:
            best, best_corr = float(width), corr
    return block * best


def blur_mismatch(sol: Solution, pix, data, noise: AbstractNoise, scale2: float):
    """A score test of the model's blur: `(v, z)`, the extra Gaussian blur variance
    (pixels squared; negative: the image is sharper than the model) that one
    Gauss-Newton step would add to the fitted model, and its size in standard errors,
    with the free parameters' own columns projected out (a blur they take up is not
    counted). About N(0, 1) where the model describes the image; `(nan, nan)` where no
    compared bin has full-resolution neighbours. The blur's direction is
    $\\partial m / \\partial v = \\nabla^2 m / 2$ on the bins of full resolution whose
    neighbours are too; each bin's residual slope is the noise model's own."""
    n = sol.model.size
    model = np.asarray(sol.model, np.float64)
    fine = pix.paint((pix.side == pix.block).astype(float), fill=0.0) > 0
    fine = scipy.ndimage.minimum_filter(fine.astype(np.uint8), 3, mode="constant") > 0
    img = pix.paint(model)
    lap = scipy.ndimage.laplace(np.where(np.isfinite(img), img, 0.0), mode="nearest")
    lap = np.where(fine, 0.5 * lap / pix.block**2, 0.0)
    rr, cc = pix.bin_index()
    rr, cc = np.clip(rr, 0, lap.shape[0] - 1), np.clip(cc, 0, lap.shape[1] - 1)
    c = np.where((pix.side == pix.block) & (pix.count > 0), lap[rr, cc], 0.0)
    if not np.any(c):
        return math.nan, math.nan
    slope = noise.residual_slope(model, data.data, data.weight).ravel()
    col = slope * c
    jac = np.asarray(sol.jac)[:n]
    coef = np.linalg.lstsq(jac, col, rcond=None)[0]
    perp = col - jac @ coef
    norm2 = float(perp @ perp)
    if not norm2 > 0.0:
        return math.nan, math.nan
    v = -float(perp @ np.asarray(sol.r)[:n]) / norm2
    return v, v / math.sqrt(scale2 / norm2)


def blur_note(v: float, z: float, psf_given: bool) -> str:
    """The note when the blur's score test (`blur_mismatch`) is beyond
    `GOODNESS_SIGMAS` standard errors; "" else."""
    if not abs(z) > GOODNESS_SIGMAS:
        return ""
    width = math.sqrt(abs(v))
    if v > 0:
        what = "a wider PSF" if psf_given else "a PSF"
        return (f"the image is more blurred than the model, as by a further Gaussian of "
                f"{width:.2g} px ({z:.3g} standard errors; the fitted values take up part "
                f"of it): give {what} (psf=, --psf-sigma-px) or fit its width (free "
                "psf_sigma, --fit-psf)")  # fmt: skip
    return (f"the image is sharper than the model, by a Gaussian of {width:.2g} px "
            f"({-z:.3g} standard errors): a PSF narrower than given, or pixels that are "
            "point samples (one ray a pixel; pixels='point', --pixels point); give the "
            "PSF the image has or fit its width (free psf_sigma, --fit-psf)")  # fmt: skip


def likely_causes(obs, grey, model_img, resid_img, block: int, psf_given: bool,
                  hi: float, blur: str = "") -> list[str]:  # fmt: skip
    """What most likely makes residuals exceed the noise, each as advice: pixels stored
    at the format's range (saturated or cut at black), an image more blurred than the
    model (a PSF missing or too narrow), a file whose decoding was assumed. `hi`: the
    image's upper clipping bound (`clipping_bounds`; inf where it is not clipped);
    `blur`: the blur's score-test note (`blur_note`), the blur's cause where given."""
    causes = []
    if math.isfinite(hi):
        share = float(np.mean(grey[obs.valid] >= hi))
        causes.append(f"{100 * share:.2g} % of the pixels are clipped at the format's "
                      "maximum (saturated): mask them (mask=, --mask) or use an unsaturated "
                      "exposure")  # fmt: skip
    s = math.nan if blur else blur_excess(model_img, resid_img, block)
    if blur:
        causes.append(blur)
    elif math.isfinite(s):
        what = "a wider PSF" if psf_given else "a PSF"
        causes.append(f"the image is smoother than the model, as if blurred by a further "
                      f"{s:.2g} px: give {what} (psf=, --psf-sigma-px) or fit its width "
                      "(free psf_sigma, --fit-psf)")  # fmt: skip
    if not obs.transfer_tagged and obs.transfer is not None:
        causes.append(f"the file does not say how its values are encoded and was read as "
                      f"{obs.transfer}: give transfer= (--transfer srgb or linear)")  # fmt: skip
    return causes


def noise_trend(r, model, lo, hi, sigma) -> float:
    """How the residuals' scatter changes with the model's level, in standard
    deviations: the log ratio of their variance over the brightest third of the
    compared bins to that over the faintest third, over its standard error
    $\\sqrt{2/n_1 + 2/n_2}$ (about N(0, 1) where the noise model holds; a wrong decoding
    of the values makes the noise grow or shrink with brightness). Bins within 3 noise
    sigmas of a clipping bound, whose noise the clipping shrinks, are left out; NaN
    with fewer than 30 bins a third."""
    r, model = np.asarray(r, np.float64), np.asarray(model, np.float64)
    ok = np.isfinite(r) & np.isfinite(model) & (r != 0.0)
    ok &= (model > lo + 3.0 * sigma) & (model < hi - 3.0 * sigma)
    if ok.sum() < 90:
        return math.nan
    m, v = model[ok], r[ok]
    faint, bright = np.quantile(m, [1.0 / 3.0, 2.0 / 3.0])
    lo_r, hi_r = v[m <= faint], v[m >= bright]
    if min(lo_r.size, hi_r.size) < 30 or not (np.var(lo_r) > 0 and np.var(hi_r) > 0):
        return math.nan
    ratio = math.log(float(np.mean(hi_r**2)) / float(np.mean(lo_r**2)))
    return ratio / math.sqrt(2.0 / hi_r.size + 2.0 / lo_r.size)


def goodness_note(noise: AbstractNoise, chi2: float, dof: int, causes) -> str:
    """The note when the residuals exceed the noise model by more than
    `GOODNESS_SIGMAS` of the statistic's spread, with the likely causes; "" else."""
    z = noise.excess(chi2, dof)
    if not z > GOODNESS_SIGMAS:
        return ""
    what = noise.statistic
    why = "; ".join(causes) if causes else "a model that does not describe the image"
    return (f"the {what} exceed the noise: chi2/dof {chi2 / max(dof, 1):.4g} over {dof} "
            f"degrees of freedom, {z:.3g} standard deviations above 1 (limit "
            f"{GOODNESS_SIGMAS:g}); likely: {why}")  # fmt: skip


def diagnose(scene, obs, seen, setup, noise: AbstractNoise, sol: Solution, values: dict,
             free: tuple, noise_seen: bool, t_start: float) -> Fit:  # fmt: skip
    """The `Fit` of a solution: errors from the curvature (Gaussian noise estimated from
    the image: scaled by the residuals' variance) and every check that failed in its
    `message`."""
    prior = 1  # the last residual: the ring-flux prior (0 when the flux is held)
    pix = setup.pix
    n_data = int((pix.count > 0).sum())
    rss = float(np.sum(sol.r[: sol.r.size - prior] ** 2))
    dof = max(n_data - len(free), 1)
    chi2_dof = rss / dof
    scale2 = noise.error_scale(chi2_dof)
    cov, corr, err, cond, finite = _covariance(sol.jac, sol.theta, free, sol.phys, scale2)
    ok = bool(sol.result == optx.RESULTS.successful)
    notes = [] if ok else [f"the solver stopped: {result_name(sol.result)}"]
    at_bound = [n for n in free if parameter(n).transform.at_bound(sol.phys[n])]
    if at_bound:
        notes.append("at the bound of its range: " + ", ".join(at_bound))
    more, degenerate, vif_ring, caveat = _separation_notes(free, sol.phys, err, corr, cond,
                                                           seen.shadow_seen)  # fmt: skip
    top = clipping_bounds(seen.grey)[1]
    flux_notes, explained = _nuisance_notes(free, sol.phys, err, obs.psf is not None,
                                            math.isfinite(top))  # fmt: skip
    notes += more + flux_notes
    caveat = "; ".join(c for c in (caveat, *explained) if c)
    model_img = pix.paint(sol.model)
    resid_img = pix.paint(np.where(pix.count > 0, pix.data - sol.model, np.nan))
    goodness = blur_v = blur_z = math.nan
    lo, hi = (float(getattr(noise, n, b)) for n, b in (("lo", -math.inf), ("hi", math.inf)))
    trend = noise_trend(sol.r[: sol.r.size - prior], sol.model, lo, hi, seen.level[0])
    if not noise_seen:
        notes.append("no pixel noise found in the image (a noiseless or smoothed one?): the "
                     "errors measure the misfit, not a noise; give the noise level "
                     "(noise=, --noise SIGMA) for errors that do")  # fmt: skip
    else:
        goodness = noise.excess(rss, dof)
        # A blur the fitted values take up passes the residuals' test; its own
        # direction does not.
        blur_v, blur_z = blur_mismatch(sol, pix, setup.data, noise, scale2)
        blur = blur_note(blur_v, blur_z, obs.psf is not None)
        causes = []
        if goodness > GOODNESS_SIGMAS:  # the causes are searched for only where needed
            causes = likely_causes(obs, seen.grey, model_img, resid_img, pix.block,
                                   obs.psf is not None, top, blur)  # fmt: skip
        note = goodness_note(noise, rss, dof, causes) or blur
        if note:
            notes.append(note)
    converged = ok and finite and bool(np.all(np.isfinite(err))) and not at_bound
    kept = {**values, **sol.phys}
    kept = {n: float(v) for n, v in kept.items()
            if n in free or n in ("distance", "fov")
            or split_name(n)[0] in ("source_lon", "source_lat", "sigma")}  # fmt: skip
    sigma, gain = noise.levels()
    sigma = sigma if math.isfinite(sigma) else seen.level[0]
    return Fit(
        scene=scene, names=free, values=kept, errors={n: float(e) for n, e in zip(free, err)},
        covariance=cov, correlation=corr, start={n: float(v) for n, v in values.items()},
        noise=noise.name, noise_sigma=sigma, gain=gain, chi2_dof=float(chi2_dof),
        model=model_img, residuals=resid_img, n_pixels=n_data, block=pix.block,
        supersample=setup.k, result=sol.result, result_name=result_name(sol.result),
        num_steps=int(sol.steps), variance_inflation=float(vif_ring),
        converged=bool(converged), degenerate=degenerate, message="; ".join(notes),
        seconds=time.perf_counter() - t_start, transfer=obs.transfer,
        transfer_reason=obs.transfer_reason, goodness=float(goodness), noise_trend=trend,
        pixels=obs.pixels, pixels_reason=obs.pixels_reason, blur_variance=float(blur_v),
        blur_z=float(blur_z), caveat=caveat, noise_seen=bool(noise_seen),
    )  # fmt: skip
