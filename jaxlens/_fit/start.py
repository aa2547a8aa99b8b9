"""A fit's first stages after reading the image: what the image shows (`look`: its
radial profile, arcs, shadow edge), the compared bins and the model's arguments
(`build`), and the starting values (`starting_values`, then `refine` by scans of the
compiled loss)."""

import dataclasses
import math

import equinox as eqx
import jax
import numpy as np

from .._camera import Camera
from .._exact import shadow_angle_with
from .._psf import GaussianPSF
from .._scene import Scene
from .._util import to_device
from . import starts
from .arcs import find_arcs, source_offset_from_arcs
from .model import samples_for
from .noise import noise_estimate
from .objective import Data, Problem, loss, select, source_sphere
from .observation import Observation
from .params import apply, floor_of, in_scene, parameter, values_of
from .pixels import grid_sets, pixel_centres, pixel_edges, pixel_sets

_GEOMETRY = frozenset({"distance", "fov", "source_lon", "source_lat"})
# A ring this few pixels in radius cannot hold the features that separate D from the
# field of view (the shadow's edge, the ring's width, the relativistic rings).
SMALLEST_RING_PX = 6.0


@dataclasses.dataclass(frozen=True)
class Options:
    """The caller's settings of a fit (`fit`'s arguments of the same names; `init` in
    physical units, `fov_deg` already converted)."""

    free: tuple
    init: dict
    block: int | None
    max_pixels: int | None
    supersample: int | None
    knots: int
    rtol: float
    atol: float
    max_steps: int
    # Where the source lies (`SourceDistance`; None: at infinity).
    source: object = None


@dataclasses.dataclass(frozen=True)
class Look:
    """What the image shows, before any model: `grey` (the image, invalid pixels at the
    median), `prof` (its radial profile about the centre, `starts.profile`), `arcs`
    (`find_arcs`), `found` (arcs stand out), `arc_like` (arcs, not a ring: offset by
    more than a pixel and half their width), `level`
    (`noise.noise_estimate`: the per-pixel noise and its relative spread)."""

    grey: np.ndarray
    prof: object
    arcs: object
    found: bool
    arc_like: bool
    level: tuple

    @property
    def edge_seen(self) -> float:
        """The shadow's edge radius (pixels) the arcs' model found, else NaN."""
        return self.arcs.shadow_radius if self.found else math.nan

    @property
    def shadow_seen(self) -> bool:
        return math.isfinite(self.prof.shadow_radius)


def look(obs: Observation) -> Look:
    """The image's radial profile and arcs; a `ValueError` when neither a ring nor arcs
    stand out of the noise, or the ring is under `SMALLEST_RING_PX` in radius."""
    grey = np.where(obs.valid, obs.data, np.nanmedian(obs.data[obs.valid]))
    level = noise_estimate(obs.data)
    prof = starts.radial_profile(grey, noise=level[0])
    arcs = find_arcs(obs.data, noise=level[0])
    found = arcs.found
    arc_like = found and arcs.offset > max(1.0, 0.5 * arcs.ring_width)
    if arc_like:
        # Arcs, not a ring: the radial profile about the image centre mixes the two
        # arcs' radii, so the ring start takes the arcs' Einstein radius and width.
        r, wr = arcs.ring_radius, arcs.ring_width
        prof = eqx.tree_at(lambda q: (q.ring_radius, q.ring_width, q.inner_half, q.outer_half),
                           prof, (r, wr, r - 1.1774 * wr, r + 1.1774 * wr))  # fmt: skip
    if not prof.peak > 8.0 * prof.peak_noise and not found:
        # A shadow with no ring in view: a camera whose ring lies beyond the frame.
        where = (f"; the shadow's edge is seen ({prof.shadow_radius:.3g} px in radius): the "
                 "ring may lie outside the frame, which a wider field of view would show"
                 if math.isfinite(prof.shadow_radius) else "")  # fmt: skip
        raise ValueError(
            f"no ring or arcs found: the radial profile about the image centre peaks "
            f"{prof.peak:.3g} above its floor, within 8 times its noise "
            f"({prof.peak_noise:.3g}), and no arcs stand out of the noise{where}"
        )
    if prof.ring_radius < SMALLEST_RING_PX:
        h, w = obs.shape
        raise ValueError(f"the ring is {prof.ring_radius:.2g} px in radius on a {w} x {h} image: "
                         "too few pixels to separate the distance from the field of view (the "
                         "shadow's edge and the ring's width need more)")  # fmt: skip
    return Look(grey, prof, arcs, found, arc_like, level)


@dataclasses.dataclass(frozen=True)
class Setup:
    """The compared bins (`pix`, a `pixels` set), the Gauss-Legendre order `k`, the
    model's scene, the residuals' arguments (`data`, an `objective.Data`), the problem
    and the free parameters' internal starting values `theta0`."""

    pix: object
    k: int
    scene: Scene
    data: Data
    prob: Problem
    theta0: np.ndarray


def psf_width(psf) -> float:
    """The Gaussian width (pixels) of a PSF model (`AbstractPSF.width_px`); 0 without
    one."""
    return 0.0 if psf is None else float(psf.width_px)


def gaussian_psf(psf) -> bool:
    """Whether the PSF is a Gaussian, whose width the model takes as a parameter."""
    return isinstance(psf, GaussianPSF)


def _unblurred_width(width_px: float, psf_px: float) -> float:
    """A ring's radial Gaussian width before a PSF of Gaussian width `psf_px` blurred
    it to `width_px` (pixels): the widths in quadrature, at least a quarter of
    `width_px` (where the PSF makes nearly all of it, the difference is noise)."""
    return math.sqrt(max(width_px**2 - psf_px**2, (0.25 * width_px) ** 2))


# With a PSF, the model is rendered on sub-bins no wider than the Gaussian PSF's width,
# blurred there and averaged into the bins: blurring the bins' own averages (aliased
# where the scene is sharper than a bin, the shadow's edge) moved D by 1.8 standard
# errors on the fit benchmark's arcs at D = 40 (bins of 3 px, a PSF of 2 px), and by
# 0.00 with bins of 2 px. The sub-bins of a fit are at most this many (with the margin),
# which bounds its memory and time; a Gaussian PSF narrower than that allows is
# rendered on the finest sub-bins within it.
SUB_BINS = 1 << 18
# A PSF image is applied at its own pixels' scale: its model is rendered on pixels.
PSF_IMAGE_PIXELS = 1 << 21


def psf_sub_bins(psf, block: int, shape: tuple, sigma_px: float) -> int:
    """How many sub-bins a side each bin of side `block` (pixels) is rendered as under
    `psf` on an image of `shape` (rows, columns): for a Gaussian of width `sigma_px`
    (pixels), the fewest whose side is at most that width, within `SUB_BINS`; for a PSF
    image, `block` (sub-bins of one pixel), a `ValueError` beyond `PSF_IMAGE_PIXELS`."""
    n_bins = (shape[0] // block) * (shape[1] // block)
    if not gaussian_psf(psf):
        if n_bins * block * block > PSF_IMAGE_PIXELS:
            raise ValueError(f"a PSF image is applied at the image's pixels, and this image "
                             f"({shape[1]} x {shape[0]}) has more than {PSF_IMAGE_PIXELS} of "
                             "them: crop it, or give a Gaussian PSF of its width "
                             "(psf=<width in px>)")  # fmt: skip
        return block
    sub = math.ceil(block / max(sigma_px, 1e-3))
    return max(1, min(sub, math.isqrt(SUB_BINS // max(n_bins, 1))))


def _psf_grid(obs: Observation, values, b: int, sub: int):
    """With a PSF: the grid of sub-bins (`sub` x `sub` a bin) on a margin the PSF
    reaches (its side in bins a multiple of 4, so PSFs of similar widths share
    programs) and the OTF of a PSF image: `(grid, otf, pad)`, `pad` in bins."""
    h, w = obs.shape
    if gaussian_psf(obs.psf):
        pad = -(-math.ceil(4.0 * max(values["psf_sigma"], 0.5) * 1.5) // b)
    else:
        pad = -(-(max(np.shape(obs.psf.image)) // 2 + 1) // b)
    pad = -(-pad // 4) * 4
    x0, y0 = (np.asarray(v) for v in pixel_edges(w, h, b, np.float64))
    side = b / sub
    xs = x0[0, 0] + side * np.arange(-pad * sub, (x0.shape[1] + pad) * sub)
    ys = y0[0, 0] - side * np.arange(-pad * sub, (y0.shape[0] + pad) * sub)
    grid = tuple(to_device(v) for v in np.meshgrid(xs, ys))
    otf = None if gaussian_psf(obs.psf) else obs.psf.otf(grid[0].shape)
    return grid, otf, pad


def build(obs: Observation, seen: Look, noise, scene: Scene, opts: Options, values: dict,
          f_px: float, centre) -> Setup:  # fmt: skip
    """The compared bins and the model's arguments for the starting `values` (every
    parameter's, physical), a focal length `f_px` (pixels) and the hole's image at
    `centre` (pixels from the image centre, y up), under the estimated `noise`."""
    h, w = obs.shape
    prof = seen.prof
    point = obs.pixels == "point"
    if obs.psf is None:
        # The shadow's edge where the image shows it (its radial profile's, which
        # `pixel_sets` takes itself, else the arcs' model's), else where the starting
        # distance puts it.
        if seen.shadow_seen:
            rho_sh = math.nan
        elif math.isfinite(seen.edge_seen):
            rho_sh = seen.edge_seen
        else:
            rho_sh = f_px * math.tan(shadow_angle_with(max(values["distance"], 1.6), np))
        level = float(noise.sigma) if hasattr(noise, "sigma") else prof.noise
        block = opts.block
        if point:  # point samples are compared one by one, each its own centre's
            if block not in (None, 1):
                raise ValueError(f"block={block} averages pixels that are point samples "
                                 "(pixels='point'): leave it out or give 1")  # fmt: skip
            block = 1
        pix = pixel_sets(seen.grey, prof, rho_sh, opts.max_pixels or 40_000, block,
                         valid=obs.valid, centre=centre,
                         structure=prof.floor + 3.0 * level)  # fmt: skip
    else:
        b = opts.block
        if b is None:
            b = 1
            while (h // b) * (w // b) > (opts.max_pixels or 65_536):
                b += 1
        pix = grid_sets(seen.grey, obs.valid, int(b))
    b = pix.block
    sub = 1 if obs.psf is None else psf_sub_bins(obs.psf, b, obs.shape, values["psf_sigma"])
    # The rendered ring's width: the image's, less the PSF's in quadrature (a narrow
    # ring under a wide PSF needs a higher order than its image shows). Under a PSF
    # on whole bins order 2 is not used: the measured width's error grows as the
    # PSF's share does (sub-bins are no wider than the PSF).
    k = (int(opts.supersample) if opts.supersample is not None
         else samples_for(_unblurred_width(prof.ring_width, psf_width(obs.psf)), b / sub,
                          3 if obs.psf is not None and sub == 1 else 2))  # fmt: skip
    if point and obs.psf is None:
        k = 1  # the node at the pixel's centre
    cam0 = scene.camera
    yaw, pitch, roll = (np.asarray(v) for v in (cam0.yaw, cam0.pitch, cam0.roll))
    cam = Camera(values["distance"], values["fov"], w, h, yaw=yaw, pitch=pitch, roll=roll,
                 supersample=k, sampling="gauss", dtype=np.float64)  # fmt: skip
    sky = jax.tree.map(lambda a: to_device(a, np.float64), scene.sky)
    # Values given for parameters held fixed are the model's.
    held = {n: v for n, v in opts.init.items() if n not in opts.free}
    model_scene = apply(Scene(cam, sky), {n: v for n, v in held.items() if in_scene(n)})
    pad, otf = 0, None
    if obs.psf is None:
        grid = tuple(to_device(np.concatenate(v)) for v in zip(pix.fine, pix.coarse_edges))
        grid += (to_device(pix.side, np.float64),)
    else:
        grid, otf, pad = _psf_grid(obs, values, b, sub)
    # Every parameter of the model: the scene's own, then the PSF's width and the
    # rings' flux factor.
    given = values_of(model_scene)
    names = tuple(given) + ("psf_sigma",) * gaussian_psf(obs.psf) + ("ring_flux",)
    for n in opts.free:
        if n not in names:  # a floor the sky does not have: say so
            floor_of(model_scene.sky)
    given |= {n: values[n] for n in ("psf_sigma", "ring_flux")}
    sel = select(names, opts.free, {n: values[n] if n in opts.free else given[n] for n in names})
    turned = (
        bool({"yaw", "pitch"} & set(opts.free))
        or bool(np.any(roll))
        or any(given.get(n, 0.0) != 0.0 for n in ("yaw", "pitch"))
    )
    psf_kind = None if obs.psf is None else ("gaussian" if gaussian_psf(obs.psf) else "image")
    prob = Problem(names, b, k, pad, psf_kind, int(opts.knots), sub, point, centred=not turned)
    data = Data(model_scene, grid, otf, to_device(pix.data), to_device(pix.weight),
                jax.tree.map(to_device, noise), sel, source_sphere(opts.source))  # fmt: skip
    theta0 = np.asarray([parameter(n).transform.inverse(values[n]) for n in opts.free])
    return Setup(pix, k, model_scene, data, prob, theta0)


def focal(fov: float, width: int) -> float:
    """The focal length (pixels) of a pinhole camera `width` pixels wide."""
    return 0.5 * width / math.tan(0.5 * fov)


def scans(seen: Look, opts: Options) -> tuple[bool, bool]:
    """Whether the start scans the distance along the ring relation (arcs with no
    shadow in view: nothing in a ring's profile fixes D; a centred ring's candidates
    fit the arcs' azimuthal mean, D 3300 for the benchmark's D 150 arcs) and the
    source's offset (free, not given, and the image shows arcs or nothing the arcs'
    model took for a ring: a ring offset by less than a pixel or half its width starts
    behind the hole, where the scan put it on 13 of the fit benchmark's 14 rings)."""
    free, init = set(opts.free), set(opts.init)
    scan_d = (seen.arc_like and not math.isfinite(seen.arcs.shadow_radius)
              and _GEOMETRY <= free and not _GEOMETRY & init)  # fmt: skip
    source = {"source_lon", "source_lat"}
    scan_source = source <= free and not source & init and (seen.arc_like or not seen.found)
    return scan_d, scan_source


def starting_values(seen: Look, obs: Observation, scene: Scene, opts: Options, scale: float,
                    scan_d: bool) -> dict:  # fmt: skip
    """Every parameter's starting value (physical): the scene's, what `init` gives, and
    where it does not, the ring start (`starts.ring_start`: the radial profile through
    the exact ring relation) or, for arcs, the arcs' radii and amplitude."""
    prof, arcs, free, init = seen.prof, seen.arcs, opts.free, opts.init
    w = obs.shape[1]
    values = starting_values_given(scene, obs, Options(**{**vars(opts), "init": {}}))
    ring_free = {"distance", "fov", "sigma", "brightness", "floor"} & set(free)
    if scan_d:
        values |= init | _arcs_camera(arcs, w, init.get("sigma", values["sigma"]),
                                      relation(opts))  # fmt: skip
    elif ring_free - set(init) and prof.peak > 8.0 * prof.peak_noise:
        sig = None if "sigma" in free else init.get("sigma", values["sigma"])
        ring_init = None
        if "distance" in init and "fov" in init:
            ring_init = {n: init[n] for n in ("distance", "fov", "sigma") if n in init}
        elif seen.arc_like and math.isfinite(arcs.shadow_radius):
            # Arcs around a visible shadow: the ratio of their Einstein radius to the
            # shadow's fixes D (a centred ring's candidates can fit arcs at the wrong
            # distance: D 3.0, FOV 143 deg for D 20, FOV 60 deg).
            ring_init = starts.distance_from_radii(arcs.ring_radius, arcs.shadow_radius, w,
                                                   relation(opts))  # fmt: skip
        d_s, fov_s, sig_s, a_s, fl_s, *_ = starts.ring_start(seen.grey, prof, sig, ring_init,
                                                             scale, relation(opts))  # fmt: skip
        guess = {"distance": d_s, "fov": fov_s, "sigma": sig_s, "brightness": a_s, "floor": fl_s}
        # The ring start refines what `init` gives of D, FOV and sigma (its own
        # candidates), so those refined values stand; other given values win.
        refined = set(ring_init or ())
        values |= init | {n: v for n, v in guess.items()
                          if n in free and (n not in init or n in refined)}  # fmt: skip
        if ring_init is not None and "distance" not in init:
            # From the arcs' radii: the ring start's centred-ring model, which does not
            # describe arcs, moved the FOV 7 % off (74.6 deg for 70) on the benchmark's
            # first arcs image, and the fit then settled 15 % off in D.
            values |= ring_init
    else:
        values |= init
    if seen.arc_like:
        # The ring start's brightness and floor are the ring's azimuthal mean.
        values |= {n: v for n, v in (("brightness", arcs.amplitude), ("floor", arcs.floor))
                   if n in free and n not in init}  # fmt: skip
    return values


def starting_values_given(scene: Scene, obs: Observation, opts: Options) -> dict:
    """Every parameter's value from the scene, the PSF's width (1 px without one), the
    rings' flux factor 1, and what `init` gives."""
    width = float(obs.psf.sigma_px) if gaussian_psf(obs.psf) else 1.0
    extra = {"psf_sigma": width, "ring_flux": 1.0}
    return values_of(scene) | extra | opts.init


def relation(opts: Options) -> tuple | None:
    """The ring relation's source: `(slope, offset)` of the source sphere's radius
    (`SourceDistance.linear`), None for a source at infinity (`starts.ring_table`)."""
    return None if opts.source is None else opts.source.linear()


def _arcs_candidates(arcs, width: int, blur_px: float = 0.0, source=None):
    """Cameras along the exact ring relation that put the Einstein ring at the arcs'
    radius: `(distance, fov, focal, sigma)` arrays (R_S, radians, pixels, radians),
    sigma the star width the arcs' radial width implies (radial magnification 1/2 at
    the Einstein ring, the blur `blur_px` and the pixel removed in quadrature)."""
    d, a_e, _, _ = starts.ring_table(source)
    f = arcs.ring_radius / np.tan(a_e)
    fov = 2.0 * np.arctan(0.5 * width / f)
    ok = (fov > math.radians(0.05)) & (fov < math.radians(179.0))
    intrinsic = math.sqrt(max(arcs.ring_width**2 - blur_px**2 - 1.0 / 12.0, 0.25))
    return d[ok], fov[ok], f[ok], 2.0 * intrinsic / f[ok]


def _arcs_camera(arcs, width: int, sigma: float, source=None):
    """A first `{"distance", "fov"}` for arcs with no shadow in view: the camera whose
    ring relation and radial magnification give arcs of the measured radius and width
    for a star of width `sigma` (radians); refined by `refine`'s distance scan."""
    d, fov, _, sig = _arcs_candidates(arcs, width, source=source)
    i = int(np.argmin(np.abs(np.log(sig / sigma))))
    return {"distance": float(d[i]), "fov": float(fov[i])}


def _best(theta0, cands, s: Setup, report=None, what: str = "candidates"):
    """The candidate (internal parameters, one a row) of lowest loss, else `theta0`;
    `report` (a `Progress`) told the search and its best loss."""
    if report is not None:
        report(f"start: searching {len(cands)} {what}")
    losses = [float(loss(to_device(c), s.data, s.prob)) for c in cands]
    losses = np.where(np.isfinite(losses), losses, np.inf)
    if not np.isfinite(losses).any():
        return theta0
    if report is not None:
        report(f"start: best of {len(cands)} {what}, loss (chi2) {np.min(losses):.4g}")
    return cands[int(np.argmin(losses))]


def _distance_scan(theta0, seen: Look, obs: Observation, s: Setup, opts: Options,
                   report=None):  # fmt: skip
    """`theta0` with D, FOV, the source (and sigma, when free) set to the candidate
    along the ring relation whose full-model loss is lowest: the source offset at each
    D from the arcs' radii, along their azimuth."""
    free, arcs = opts.free, seen.arcs
    blur = float(obs.psf.sigma_px) if gaussian_psf(obs.psf) else 0.0
    d, fov, f, sig = _arcs_candidates(arcs, obs.shape[1], blur, relation(opts))
    beta = np.asarray(source_offset_from_arcs(arcs, d, f), float)
    values = {"distance": d, "fov": fov, "source_lon": beta * math.cos(arcs.psi),
              "source_lat": beta * math.sin(arcs.psi), "sigma": sig}  # fmt: skip
    cands = []
    for j in np.flatnonzero(np.isfinite(beta)):
        cand = np.array(theta0, float)
        for n, v in values.items():
            if n in free:
                cand[free.index(n)] = parameter(n).transform.inverse(float(v[j]))
        cands.append(cand)
    if not cands:
        return theta0
    return _best(theta0, np.asarray(cands), s, report, "distances along the ring relation")


def _source_azimuth(seen: Look, obs: Observation, floor: float) -> float:
    """Azimuth (radians, image plane, 0 = +x toward +y) of the brighter arc: the first
    moment of the light above the floor in an annulus about the ring radius."""
    h, w = obs.shape
    x, y = pixel_centres(h, w)
    x, y = x[None, :], y[:, None]
    rho = np.hypot(x, y)
    ring = seen.prof.ring_radius
    band = obs.valid & (np.abs(rho - ring) < max(3.0, 0.3 * ring))
    wgt = np.clip(seen.grey - floor, 0.0, None) * band
    if wgt.sum() <= 0:
        return 0.0
    rho = np.maximum(rho, 1e-9)
    return math.atan2((wgt * y / rho).sum(), (wgt * x / rho).sum())


def refine(theta0, seen: Look, obs: Observation, s: Setup, opts: Options, values: dict,
           scan_d: bool, scan_source: bool, report=None):  # fmt: skip
    """The internal starting values after the scans of the compiled loss: the hole's
    image (yaw, pitch) from the arcs, the distance along the ring relation (`scan_d`)
    and the source's offset along the arcs' azimuth (`scan_source`); each scan told
    to `report` (a `Progress`) where given."""
    free, arcs = opts.free, seen.arcs
    theta0 = np.array(theta0, float)
    f_px = focal(values["fov"], obs.shape[1])
    for name, c in (("yaw", arcs.x_c), ("pitch", arcs.y_c)):
        if name in free and name not in opts.init and seen.found:
            theta0[free.index(name)] = math.atan(-c / f_px)  # the view turned away
    if scan_d:
        theta0 = _distance_scan(theta0, seen, obs, s, opts, report)
        scanned = ("distance", "fov", "sigma")
        values = values | {n: float(parameter(n).transform.forward(theta0[i]))
                           for i, n in enumerate(free) if n in scanned}  # fmt: skip
        f_px = focal(values["fov"], obs.shape[1])
    if scan_source:
        if seen.found:
            psi = arcs.psi
            beta = float(source_offset_from_arcs(arcs, values["distance"], f_px))
        else:
            psi = _source_azimuth(seen, obs, values.get("floor", 0.0))
            beta = math.nan
        offsets = [0.0] + list(np.geomspace(0.05, 6.0, 8) * math.pi / 180.0)
        if math.isfinite(beta) and beta > 0:
            offsets += list(beta * np.asarray([0.6, 0.8, 1.0, 1.25, 1.6]))
        cands = np.repeat(theta0[None], len(offsets), axis=0)
        cands[:, free.index("source_lon")] = np.asarray(offsets) * math.cos(psi)
        cands[:, free.index("source_lat")] = np.asarray(offsets) * math.sin(psi)
        theta0 = _best(theta0, cands, s, report, "source offsets along the arcs' azimuth")
    return theta0
