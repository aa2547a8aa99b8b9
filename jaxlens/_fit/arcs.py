"""Start values for a star off the axis: the two arcs of its image.

A Gaussian star at angle $\\beta$ from the point behind the hole, at position angle
$\\psi$ on the sky, is seen as two arcs: the primary (escape angle
$\\Phi = \\pi - \\beta$, outside the Einstein ring, on the star's side) and the
secondary ($\\Phi = \\pi + \\beta$, inside the ring, on the opposite side). `find_arcs`
measures them on an image (a least-squares fit with the fit's own solver, from
starting geometries found on the host) and `offset_from_radii` turns the two arc radii into
$\\beta$ with the exact escape angle of `jaxlens.trace`.

The measurement fits a lens-plane model to the pixels. About a centre $(x_c, y_c)$,
a pixel at radius $\\rho$ and azimuth $\\varphi$ is sent to the source-plane point
$s(\\rho)\\,(\\cos\\varphi, \\sin\\varphi)$ (pixels), with
$s(\\rho) = R\\,(e^{m t} - e^{-n t})/2$, $t = \\ln(\\rho/R)$, $m = (3 + c)/2$,
$n = (1 - c)/2$: $s(R) = 0$, $s'(R) = 1$, $R\\,s''(R)/s'(R) = c$; $c = -1$ is the
weak-field point lens $s = (\\rho - R^2/\\rho)/2$. The exact escape angle of a
pinhole camera has $c = -1.14$ at $D = 200$, $-1.37$ at $D = 40$, $-1.73$ at
$D = 15$, $-2.5$ at $D = 5$, so $c$ is fitted. The star is a Gaussian of width $w$
(pixels, the ring's radial width at $R$) about the source-plane point
$b\\,(\\cos\\psi, \\sin\\psi)$; the image is
$\\mathrm{floor} + A\\,e^{-|S - B|^2 / 2 w^2}$, times a dark disc (the shadow) of
radius $R_{sh}$ about the centre when the floor shows one, averaged over $2 \\times 2$
area samples a pixel (more for rings narrower than 0.6 pixel). The primary and
secondary images then lie on one line through the centre; their radii along $\\psi$
and $\\psi + \\pi$ solve $s(\\rho) = \\pm b$.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage

from .._compile import program
from .._units import length
from .._util import host_driver, to_device
from .noise import noise_level
from .pixels import bin_valid, pixel_centres, real_image
from .solve import SETTLED_CHI2, dense_least_squares

_EDGE = 0.25  # width of the shadow's edge in the model (pixels)
# Range of the shape c: m, n > 0 needs -3 < c < 1; the exact map has c <= -1 (c -> -1
# far from the hole), and c > -1 would let a lone arc pass for the other one.
_C_MIN, _C_MAX = -2.95, -0.6
_C_MID, _C_HALF = 0.5 * (_C_MIN + _C_MAX), 0.5 * (_C_MAX - _C_MIN)
# An image of more pixels is measured in s x s bins, s the smallest side that brings
# it to this many or fewer: the arcs of a 4096 x 4096 image are found on 1024 x 1024
# bins, their geometry in pixels of the image (a start value: a quarter of a bin of
# error is a few hundredths of a percent of such a ring's radius).
_MAX_PIXELS = 1 << 20


class ArcGuess(eqx.Module):
    """What `find_arcs` measured on an image (pixels from the image centre, $x$ right,
    $y$ up, as PHYSICS.md; angles in radians; intensities in the image's units).

    **Fields:**
    - `x_c`, `y_c`: centre of the lens, pixels from the image centre: the hole's image
      for a camera pointed at the hole, or when `find_arcs` was given the focal length;
      else the centre of the ring's (oblique) image.
    - `ring_radius`: the Einstein-ring radius $R$ (pixels): where the axis behind the
      hole maps ($\\Phi = \\pi$); for a point lens $\\sqrt{\\rho_+ \\rho_-}$.
    - `ring_width`: the ring's radial Gaussian width at $R$ (pixels), the pixels' own
      area taken out.
    - `psi`: azimuth of the primary (brighter, outer) arc, radians from $+x$ toward $+y$;
      the star's position angle on the sky.
    - `outer_radius`, `inner_radius`: radii (pixels, from the centre) of the brightness
      peak along `psi` (primary) and along `psi + pi` (secondary).
    - `offset`: $b$, the star's offset in the model's source plane (pixels at the
      ring's scale; $(\\rho_+ - \\rho_-)/2$ to first order).
    - `shape`: the fitted $c = R s''(R) / s'(R)$ of the module docstring.
    - `flux_ratio`: integrated flux (above the floor) on the primary's side of the
      line through the centre perpendicular to `psi`, over that on the other side, in
      the model (so arcs cut by the frame count whole).
    - `amplitude`: peak of the star's image above the floor (image units).
    - `floor`: the uniform sky level (image units).
    - `shadow_radius`: radius of the dark disc (pixels); NaN when none is seen.
    - `noise`: per-pixel noise used (image units): the given one, or a robust
      estimate.
    - `score`: signal to noise of the ring feature, $\\sqrt{\\Delta\\chi^2}$ of the fit
      against the best model without the arcs' light (its shadow kept, its floor
      fitted anew: a shadow's edge alone is not a ring; noise alone gives 0-6); below
      ~10 the other fields mean nothing. NaN geometry and 0 for a blank image.
    """

    x_c: float
    y_c: float
    ring_radius: float
    ring_width: float
    psi: float
    outer_radius: float
    inner_radius: float
    offset: float
    shape: float
    flux_ratio: float
    amplitude: float
    floor: float
    shadow_radius: float
    noise: float
    score: float

    @property
    def found(self) -> bool:
        """Whether arcs stand out: a `score` above 10, a peak above twice the noise of a
        pixel, and a ring outside the shadow's edge where one is seen (the Einstein
        ring always is). A ring beyond the frame leaves light at the shadow's edge,
        which a broad arc 0.3 noise sigmas bright explained at a score of 15, and a
        thin ring just inside the edge at 31."""
        inside = self.ring_radius <= self.shadow_radius  # False without a shadow (NaN)
        return bool(self.score > 10.0 and self.amplitude > 2.0 * self.noise and not inside)


# ----------------------------------------------------------------- pixel statistics


def _smooth(img: np.ndarray) -> np.ndarray:
    """3 x 3 box mean over the finite pixels (NaN where none is)."""
    ok = np.isfinite(img)
    v = np.where(ok, img, 0.0)
    pv, pc = np.pad(v, 1), np.pad(ok.astype(float), 1)
    h, w = img.shape
    s = sum(pv[i : i + h, j : j + w] for i in range(3) for j in range(3))
    c = sum(pc[i : i + h, j : j + w] for i in range(3) for j in range(3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(c > 0, s / c, np.nan)


def _components(mask: np.ndarray) -> list[np.ndarray]:
    """8-connected components of a boolean image, as arrays of flat indices."""
    labels, count = ndimage.label(mask, structure=np.ones((3, 3), bool))
    flat = labels.ravel()
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(1, count + 2))
    return [order[bounds[i] : bounds[i + 1]] for i in range(count)]


def _circle_fit(x, y, wt):
    """Weighted algebraic (Kasa) circle through points: centre and radius (pixels), or
    None when the points do not fix one."""
    a = np.stack([x, y, np.ones_like(x)], 1) * np.sqrt(wt)[:, None]
    rhs = (x * x + y * y) * np.sqrt(wt)
    sol, *_ = np.linalg.lstsq(a, rhs, rcond=None)
    cx, cy = 0.5 * sol[0], 0.5 * sol[1]
    r2 = sol[2] + cx * cx + cy * cy
    if not np.isfinite(r2) or r2 <= 0:
        return None
    return float(cx), float(cy), float(math.sqrt(r2))


# ----------------------------------------------------------------------- the model


def _shape_c(raw, xp=np):
    """The shape c of its raw parameter: c in (_C_MIN, _C_MAX) through tanh."""
    return _C_MID + _C_HALF * xp.tanh(raw)


def _shape_raw(c: float) -> float:
    return float(np.arctanh(np.clip((c - _C_MID) / _C_HALF, -0.999, 0.999)))


def _s(rho, r, c, xp=np):
    """$s(\\rho)$ of the module docstring (pixels); `xp`: numpy or jax.numpy."""
    m, n = 0.5 * (3.0 + c), 0.5 * (1.0 - c)
    t = xp.log(rho / r)
    return 0.5 * r * (xp.exp(m * t) - xp.exp(-n * t))


def _values(p, xs, ys, *, jac: bool = False):
    """The model at area samples `xs`, `ys` (pixels, shape (..., k*k)), averaged over
    the last axis, and with `jac` its Jacobian (..., 10) with respect to `p`: x_c, y_c,
    ln R, b_x, b_y, ln w, shape (raw), A, floor, R_sh (pixels, image units; R_sh < -5
    px: no shadow). The Jacobian is written out: forward-mode differentiation of the
    same expressions took 14 times the values' time (160,000 samples, float64)."""
    dx, dy = xs - p[0], ys - p[1]
    rho = jnp.sqrt(dx * dx + dy * dy + 1e-12)
    ux, uy = dx / rho, dy / rho
    r = jnp.exp(p[2])
    c = _shape_c(p[6], jnp)
    m, n = 0.5 * (3.0 + c), 0.5 * (1.0 - c)
    t = jnp.log(rho) - p[2]
    em, en = jnp.exp(m * t), jnp.exp(-n * t)
    s = 0.5 * r * (em - en)
    ex, ey = s * ux - p[3], s * uy - p[4]
    iw2 = jnp.exp(-2.0 * p[5])
    q = 0.5 * (ex * ex + ey * ey) * iw2
    g = jnp.exp(-q)
    sh = 0.5 + 0.5 * jnp.tanh(0.5 * (rho - p[9]) / _EDGE)  # logistic, without overflow
    base = p[8] + p[7] * g
    val = jnp.mean(base * sh, axis=-1)
    if not jac:
        return val
    sp = 0.5 * r * (m * em + n * en) / rho  # ds/drho
    # d(value)/d(e_x, e_y) through g, and d(value)/d(rho) through the shadow's edge
    ag = -p[7] * g * sh * iw2
    vx, vy = ag * ex, ag * ey
    dsh = base * sh * (1.0 - sh) / _EDGE
    radial = vx * ux + vy * uy
    cols = [
        vx * (-sp * ux * ux - s * uy * uy / rho)
        + vy * (-sp * ux * uy + s * ux * uy / rho)
        - dsh * ux,
        vx * (-sp * ux * uy + s * ux * uy / rho)
        + vy * (-sp * uy * uy - s * ux * ux / rho)
        - dsh * uy,
        radial * (s - 0.5 * r * (m * em + n * en)),
        -vx,
        -vy,
        p[7] * g * sh * 2.0 * q,
        radial * 0.5 * s * t * _C_HALF * (1.0 - jnp.tanh(p[6]) ** 2),
        g * sh,
        sh,
        -dsh,
    ]
    return val, jnp.stack([jnp.mean(col, axis=-1) for col in cols], axis=-1)


class _Pixels(eqx.Module):
    """Pixels (or bins) a fit compares, in chunks: centres `x`, `y` (pixels from the
    image centre), values and residual weights, each `(C, n)` (padding: weight 0), and
    their side `side` (pixels)."""

    x: jax.Array
    y: jax.Array
    data: jax.Array
    weight: jax.Array
    side: jax.Array


# Area samples the model is evaluated on at a time (its temporaries, and its Jacobian's:
# ten times as many values).
_CHUNK_SAMPLES = 1 << 16


def _pack(x, y, v, side: float, weight=None, k: int = 2) -> _Pixels:
    """The pixels centred at `x`, `y` with values `v` as a `_Pixels` of k x k samples
    each, padded to whole chunks of `_CHUNK_SAMPLES` samples: every image of up to one
    chunk (the first stage's bins of any image, every pixel of a small one), and noise
    draws of a larger one, share one compiled program."""
    n = int(v.size)
    size = max(1, _CHUNK_SAMPLES // (k * k))
    chunks = -(-n // size)
    pad = chunks * size - n
    wt = np.ones(n) if weight is None else np.asarray(weight, float)

    def arr(a):  # padding repeats the last pixel, at weight 0
        a = np.asarray(a, float)
        return to_device(np.concatenate([a, np.full(pad, a[-1])]).reshape(chunks, size))

    w = to_device(np.concatenate([wt, np.zeros(pad)]).reshape(chunks, size))
    return _Pixels(arr(x), arr(y), arr(v), w, to_device(float(side)))


_NO_VIEW = (1.0, np.eye(3))  # the camera itself: (f, rot) that leave image points as they are


def _model_rows(p, px: _Pixels, k: int, view, *, jac: bool = False):
    """The model `p` on the pixels `px` (k x k area samples each, seen by the turned
    camera `view` = (f, rot): the image point (x, y) is seen at f (v_1, v_2) / v_3,
    v = rot (x, y, f)), chunk by chunk: `(C, n)`, and with `jac` its Jacobian
    `(C, n, 10)`."""
    off = (jnp.arange(k) + 0.5) / k - 0.5
    ox, oy = jnp.tile(off, k) * px.side, jnp.repeat(off, k) * px.side
    f, rot = view

    def chunk(xy):
        xs, ys = xy[0][:, None] + ox, xy[1][:, None] - oy
        v = [rot[i, 0] * xs + rot[i, 1] * ys + rot[i, 2] * f for i in range(3)]
        return _values(p, f * v[0] / v[2], f * v[1] / v[2], jac=jac)

    return jax.lax.map(chunk, (px.x, px.y))


# Parameters kept within their bounds by a logistic map (ln R, ln w, A, floor, R_sh; a
# held one has equal bounds); the others (the centre, the source, the shape's raw
# value, which `_shape_c` bounds) are free.
_BOUNDED = np.array([0, 0, 1, 0, 0, 1, 0, 1, 1, 1], bool)


def _from_internal(u, lo, hi):
    return jnp.where(_BOUNDED, lo + (hi - lo) * jax.nn.sigmoid(u), u)


def _to_internal(p, lo, hi):
    span = np.where(hi > lo, hi - lo, 1.0)
    t = np.clip((np.asarray(p, float) - lo) / span, 1e-9, 1.0 - 1e-9)
    return np.where(_BOUNDED, np.log(t) - np.log1p(-t), p)


@program(profile="legacy_fusion_o1")
def _solve(u0, px: _Pixels, far, bounds, view, sigma, k, max_steps):
    """Levenberg-Marquardt (`solve.dense_least_squares`) of the model on the pixels `px`
    (k x k samples, through `view`) from the internal parameters `u0`, the parameters
    within `bounds` = (lo, hi); `far` = (mean, weight) of the pixels left out, where
    the model is the floor; residuals in units of `sigma` (image units).

    **Returns:** the parameters, their residual sum of squares (image units squared)
    and the solver's steps."""
    lo, hi = bounds

    @jax.custom_jvp
    def rows(p):
        return _model_rows(p, px, k, view)

    @rows.defjvp
    def _rows_jvp(primals, tangents):  # the written-out Jacobian, as J dp
        val, jac = _model_rows(primals[0], px, k, view, jac=True)
        return val, jac @ tangents[0]

    def both(u):
        p = _from_internal(u, lo, hi)
        r = (rows(p) - px.data) * px.weight
        r_far = (p[8] - far[0]) * far[1]
        return jnp.concatenate([r.ravel(), r_far[None]]) / sigma, None

    u, r, jac, _, _, steps, moved = dense_least_squares(both, u0, 1e-6, 1e-9, max_steps)
    r = r + jac @ moved
    return _from_internal(u, lo, hi), sigma * sigma * jnp.sum(r * r), steps


@program(profile="legacy_fusion_o1")
def _evaluate(p, px: _Pixels, k, view):
    """The model `p` on the pixels `px` (`_model_rows`) and its weighted residual sum
    of squares there (image units squared)."""
    rows = _model_rows(p, px, k, view)
    return rows, jnp.sum(((rows - px.data) * px.weight) ** 2)


def _fit(p0, px: _Pixels, lo, hi, sigma: float, k: int, far=(0.0, 0.0), view=_NO_VIEW, *,
         tol: float = 1e-2, max_steps: int):  # fmt: skip
    """`_solve` from the parameters `p0`, until a step would gain less than `tol` in
    chi^2 (pixels of noise `sigma`) or after `max_steps` steps: the fitted parameters
    (numpy), their residual sum of squares on `px` and `far` (image units squared) and
    the steps taken."""
    u0 = _to_internal(p0, lo, hi)
    # The solver settles where its step would gain less than SETTLED_CHI2 in the
    # residuals' units: `tol` in chi^2 where the unit is sigma sqrt(tol / SETTLED_CHI2).
    unit = sigma * math.sqrt(tol / SETTLED_CHI2)
    bounds = (to_device(lo), to_device(hi))
    args = (to_device(u0), px, to_device(np.asarray(far, float)), bounds, _device_view(view),
            to_device(unit), k, max_steps)  # fmt: skip
    p, cost, steps = _solve(*args)
    return np.asarray(p), float(cost), int(steps)


def _device_view(view):
    return to_device(view[0]), to_device(np.asarray(view[1], float))


def _cost(p, px: _Pixels, k: int, view=_NO_VIEW) -> float:
    """The weighted residual sum of squares of the model `p` on the pixels `px` (k x k
    area samples each; image units squared) seen through `view`."""
    return float(_evaluate(to_device(np.asarray(p, float)), px, k, _device_view(view))[1])


def _dilate(mask: np.ndarray, steps: int) -> np.ndarray:
    """Boolean dilation by a (2 steps + 1)-pixel square."""
    return ndimage.binary_dilation(mask, np.ones((2 * steps + 1,) * 2, bool))


def _geometry_starts(img, x, y, side, frame, floor, noise):
    """Starting geometries (x_c, y_c, R, b, psi; pixels, radians) from the bright pixels,
    their radial spread (pixels), the peak above the floor, the dark disc (x, y, radius
    in pixels; None when not seen) and the bright pixels (a boolean image).

    `img`: the image (or its bins of side `side`, pixels), its columns' and rows'
    centres `x`, `y` (pixels from the image centre), the image's size `frame` (H, W;
    pixels), its floor and the noise of one of its pixels (or bins).

    The geometries: a circle through the bright pixels (the ridge, whose centre sits
    $b$ from the lens centre toward the primary) with $b$ from the flux asymmetry
    about it, both ways round; the two brightest pixel groups on a line through the
    centre, split in the ratio of the square roots of their fluxes (a point lens's
    magnification ratio); and about the dark disc, the circle's offset from it and each
    of the two brightest groups taken as the primary or the secondary."""
    h, w = img.shape
    big = max(frame)
    sm = _smooth(img)
    v = sm - floor
    ok = np.isfinite(v)
    peak = float(np.nanmax(v)) if ok.any() else 0.0
    # The smoothing averages 9 pixels: its noise is noise / 3.
    bright = ok & (v > max(4.0 * noise / 3.0, 0.12 * peak))
    if bright.sum() < 5:
        bright = ok & (v >= np.nanpercentile(v, 99.0)) & (v > 0)
    rows, cols = np.nonzero(bright)
    wt, bx, by = v[rows, cols], x[cols], y[rows]
    shadow = None
    if floor > 1.5 * noise:
        # Smoothed floor pixels fall below half the floor with probability
        # Phi(-1.5 floor / noise) < 1.2 %, rarely 9 of them together.
        comps = [c for c in _components(ok & (sm < 0.5 * floor)) if c.size >= 9]
        if comps:
            c = max(comps, key=lambda c: c.size)
            shadow = (float(x[c % w].mean()), float(y[c // w].mean()),
                      side * math.sqrt(c.size / math.pi))  # fmt: skip
    spread, starts = 1.0, []
    circ = _circle_fit(bx, by, wt) if bx.size >= 5 else None
    if circ is not None and circ[2] < 4.0 * big:
        cx, cy, rr = circ
        spread = float(np.sqrt(np.sum(wt * (np.hypot(bx - cx, by - cy) - rr) ** 2) / np.sum(wt)))
        # Flux asymmetry about the circle's centre, over the pixels whose mirror image
        # through it is in the frame and finite (so that a frame cut does not bias it).
        mx = np.round((2 * cx - bx - x[0]) / side).astype(int)
        my = np.round((y[0] - (2 * cy - by)) / side).astype(int)
        seen = (mx >= 0) & (mx < w) & (my >= 0) & (my < h)
        seen[seen] = np.isfinite(img[my[seen], mx[seen]])
        h1 = h2 = 0j
        if seen.sum() >= 5:
            phi = np.arctan2(by - cy, bx - cx)[seen]
            h1 = np.sum(wt[seen] * np.exp(1j * phi)) / np.sum(wt[seen])
            h2 = np.sum(wt[seen] * np.exp(2j * phi)) / np.sum(wt[seen])
        # The arcs' axis from the second harmonic (the arcs lie at psi and psi + pi, and
        # a nearly closed ring is brightest there), each way round; the first harmonic's
        # direction too. Point lens: flux ratio ~ 1 + 4 b / R, first harmonic ~ 2 b / R.
        b0 = float(np.clip(0.5 * abs(h1) * rr, 0.5, 0.5 * rr))
        rad = math.sqrt(max(rr * rr - b0 * b0, 1.0))
        axis = 0.5 * float(np.angle(h2))
        dirs = [axis, axis + math.pi]
        if abs(math.remainder(float(np.angle(h1)) - axis, math.pi)) > math.radians(15.0):
            dirs.append(float(np.angle(h1)))
        for psi0 in dirs:
            u = (math.cos(psi0), math.sin(psi0))
            starts.append((cx - b0 * u[0], cy - b0 * u[1], rad, b0, psi0))
        if shadow is not None:
            sx, sy, _ = shadow
            b0 = float(math.hypot(cx - sx, cy - sy))
            psi0 = float(math.atan2(cy - sy, cx - sx))
            starts.append((sx, sy, math.sqrt(max(rr * rr - b0 * b0, 1.0)), max(b0, 0.5), psi0))
    flat = np.where(bright, v, 0.0).ravel()
    groups = sorted(((flat[c].sum(), c) for c in _components(bright)), key=lambda t: -t[0])
    centroids = [
        (
            f,
            np.array(
                [np.average(x[c % w], weights=flat[c]), np.average(y[c // w], weights=flat[c])]
            ),
        )
        for f, c in groups[:2]
    ]
    if len(centroids) == 2 and centroids[1][0] > 0.02 * centroids[0][0]:
        (f1, p1), (f2, p2) = centroids
        sep = float(np.hypot(*(p1 - p2)))
        if sep > 2.0:
            inner = sep / (1.0 + math.sqrt(f1 / f2))
            u = (p1 - p2) / sep
            cen = p2 + inner * u
            psi0 = float(math.atan2(u[1], u[0]))
            rad = math.sqrt(inner * (sep - inner))
            starts.append((float(cen[0]), float(cen[1]), rad, 0.5 * (sep - 2 * inner), psi0))
    if shadow is not None:
        sx, sy, _ = shadow
        for _, pc in centroids:
            rho1 = float(math.hypot(pc[0] - sx, pc[1] - sy))
            az = float(math.atan2(pc[1] - sy, pc[0] - sx))
            b0 = 0.1 * rho1
            starts.append((sx, sy, math.sqrt(rho1 * (rho1 - 2 * b0)), b0, az))
            starts.append((sx, sy, math.sqrt(rho1 * (rho1 + 2 * b0)), b0, az + math.pi))
    spread = float(np.clip(spread, 0.5, 0.25 * big))
    return starts, spread, max(peak, noise), shadow, bright


_NO_SHADOW = -10.0  # R_sh of a model without a shadow (pixels): its factor is 1 for rho >= 0


def _params(start, width, peak, floor, shadow):
    """Model parameters (see `_model`) of a starting geometry."""
    cx, cy, r0, b0, psi0 = start
    p = [cx, cy, math.log(max(r0, 1.0)), b0 * math.cos(psi0), b0 * math.sin(psi0)]
    p += [math.log(width), _shape_raw(-1.0), peak, floor]
    return np.asarray(p + [_NO_SHADOW if shadow is None else shadow[2]])


def _bounds(h, w, scale, shadow: bool):
    """Parameter bounds: the centre and the source within 4 frame sizes, R from 0.5 px to
    2 frame sizes, w from 0.05 px to a quarter frame, A >= 0, |floor| <= max |img|, R_sh
    from 0 to 4 frame sizes (held at `_NO_SHADOW` without a shadow)."""
    big = 4.0 * max(h, w)
    lo = [-big, -big, math.log(0.5), -big, -big, math.log(0.05), -3.0, 0.0, -scale]
    hi = [big, big, math.log(0.5 * big), big, big, math.log(0.25 * max(h, w)), 3.0, 10 * scale]
    hi.append(scale)
    lo.append(0.0 if shadow else _NO_SHADOW)
    hi.append(big if shadow else _NO_SHADOW)
    return np.asarray(lo), np.asarray(hi)


def _samples_for(width: float) -> int:
    """Area samples a pixel side for a ring of radial width `width` (pixels)."""
    return 2 if width > 0.6 else 3 if width > 0.3 else 4


def _bins(img, x, y, side: float, b: int = 2):
    """The image (of pixels, or bins, of side `side` pixels centred at the columns `x`
    and rows `y`) in b x b bins (the top-left b floor(H/b) x b floor(W/b) of them):
    the bins' column and row centres (pixels) and NaN-aware means."""
    h, w = img.shape
    hh, ww = h // b * b, w // b * b
    a = img[:hh, :ww].reshape(hh // b, b, ww // b, b)
    n = np.isfinite(a).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, np.nansum(a, axis=(1, 3)) / n, np.nan)
    xb = x[:ww:b] + 0.5 * (b - 1) * side
    yb = y[:hh:b] - 0.5 * (b - 1) * side
    return xb, yb, mean


def _binned(img, side: int):
    """The image in `side` x `side` bins (centred crop): the means of their finite
    pixels (NaN where fewer than half are), residual weights $\\sqrt{n} / s$ for
    $n$ finite pixels of $s^2$ (a bin's noise is a full bin's over that), and the bins' column
    and row centres (pixels from the image centre)."""
    h, w = img.shape
    hb, wb = h // side, w // side
    r0, c0 = (h - hb * side) // 2, (w - wb * side) // 2
    mean, count = bin_valid(img, np.isfinite(img), side)
    mean[2 * count < side * side] = np.nan
    x, y = pixel_centres(h, w)
    xb = x[c0 : c0 + wb * side : side] + 0.5 * (side - 1)
    yb = y[r0 : r0 + hb * side : side] - 0.5 * (side - 1)
    return mean, np.sqrt(count / float(side * side)), xb, yb


def _view(f: float, x0: float, y0: float) -> np.ndarray:
    """Rows e1, e2, e3 of a pinhole camera of focal length `f` (pixels) turned to look at
    the image point (x0, y0): e3 along its ray, e1 the nearest to +x."""
    e3 = np.array([x0, y0, f]) / math.sqrt(x0 * x0 + y0 * y0 + f * f)
    e1 = np.array([1.0, 0.0, 0.0]) - e3[0] * e3
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(e3, e1), e3])


def _from_view(x1: float, y1: float, f: float, rot: np.ndarray):
    """The image point (pixels) of the point (x1, y1) of the turned camera `rot`."""
    v = rot.T @ np.array([x1, y1, f])
    return float(f * v[0] / v[2]), float(f * v[1] / v[2])


_STAGE1_BINS = 10_000  # the most bins of the first stage


def find_arcs(img, *, noise: float | None = None, focal: float | None = None) -> ArcGuess:
    """Measure the arcs of an off-axis star's image: the lens centre, the ring's
    radius and width, the primary's azimuth, the arcs' radii and flux ratio.

    Float64. The model of the module docstring is fitted (optimistix's
    Levenberg-Marquardt, the fit's own solver: `solve.dense_least_squares`, compiled)
    from several starting geometries, found on the host from the bright pixels, on the
    image in 2 x 2 bins (larger on images over 40,000 pixels);
    the best one is fitted again at full resolution on the pixels near the arcs and the
    shadow's edge (the others, where the model is the floor, enter as their mean).
    An image of more than 2^20 pixels is measured on its s x s bins, s the smallest
    that brings it to 2^20 or fewer (a bin's value: the mean of its finite pixels, NaN
    where fewer than half are): its memory is that of 2^20 values, and what it reports
    is in pixels of the image all the same.

    A camera not pointed at the hole sees the ring through an oblique pinhole
    projection, centred about $d\\,(R/f)^2$ pixels farther out than the hole's image at
    $d$ pixels from the image centre (1 px for $d = 17$, $R/f = 0.25$). With `focal`
    the last fit runs on the pixels as a camera turned toward the hole sees them, so
    that `x_c`, `y_c` are the hole's image and the radii are $f \\tan\\alpha$
    exactly; without it they are those of the ring's image.

    **Arguments:**
    - `img`: linear intensity `(H, W)` (or `(H, W, C)`, channels averaged); NaN pixels
      are masked out. The arcs may be cut by the frame; the hole need not be at the
      image centre.
    - `noise`: per-pixel noise standard deviation (image units), when known; default a
      robust estimate from second differences (`noise_level`).
    - `focal`: the camera's focal length (pixels, $(W/2)/\\tan(\\mathrm{FOV}/2)$), when
      known.

    **Returns:** an `ArcGuess`; its `score` says whether anything ring-like was found.
    Raises `ValueError` for an image that is not 2-D, smaller than 8 x 8 pixels or with
    fewer than 64 finite pixels, or a negative `noise` or `focal`, and a `TypeError`
    under `jit`, `vmap` or `grad` (it runs on the host).
    """
    host_driver("find_arcs", "call it on the image's values, outside the trace", img)
    a = real_image(img, "img")
    if a.ndim == 3:
        a = a.mean(axis=-1)
    if a.ndim != 2 or min(a.shape) < 8:
        raise ValueError(f"img of shape {np.shape(img)} must be (H, W) with H, W >= 8 pixels")
    n_ok = int(np.count_nonzero(np.isfinite(a)))
    if n_ok < 64:
        raise ValueError(f"img has {n_ok} finite pixels; at least 64 are needed")
    if noise is not None and not noise >= 0:
        raise ValueError(f"noise={noise!r} must be >= 0 (image units)")
    if focal is not None and not (0 < focal < math.inf):
        raise ValueError(f"focal={focal!r} must be a positive focal length (pixels)")
    h, w = a.shape
    # The noise of one pixel, then (a large image) the image in bins of `side` pixels,
    # whose noise is that over `side` (white noise).
    sigma_px = noise_level(a) if noise is None else float(noise)
    side = math.ceil(math.sqrt(h * w / _MAX_PIXELS)) if h * w > _MAX_PIXELS else 1
    with jax.enable_x64(True):
        if side == 1:
            x, y = pixel_centres(h, w)
            return _measure(a, None, x, y, 1.0, (h, w), sigma_px, focal)
        work, weight, x, y = _binned(a, side)
        return _measure(work, weight, x, y, float(side), (h, w), sigma_px, focal)


def _measure(a, wt, x, y, side: float, frame, sigma_px: float, focal) -> ArcGuess:
    """`find_arcs` on the image's pixels, or its bins: `a` their values (NaN: none),
    `wt` their residual weights (None: all 1), `x`, `y` their column and row centres
    and `side` their side (pixels), `frame` the image's (H, W), `sigma_px` the noise of
    one pixel, `focal` the focal length (pixels) or None."""
    h, w = a.shape
    ok = np.isfinite(a)
    rows, cols = np.nonzero(ok)
    xo, yo, vals = x[cols], y[rows], a[rows, cols]
    wo = np.ones(vals.size) if wt is None else wt[rows, cols]
    floor0 = float(np.median(vals))
    scale = max(float(np.max(np.abs(vals))), 1e-300)
    sigma = max(sigma_px / side, 1e-9 * scale)  # of one pixel or bin
    mean = vals.mean() if wt is None else np.average(vals, weights=wo * wo)
    flat_cost = float(np.sum(((vals - mean) * wo) ** 2))
    if flat_cost <= (1e-9 * scale) ** 2 * vals.size:
        return _nothing(floor0, sigma * side)  # a blank image
    starts, w0, peak, shadow, bright = _geometry_starts(a, x, y, side, frame, floor0, sigma)
    if not starts:
        return _nothing(floor0, sigma * side)
    lo, hi = _bounds(*frame, scale, shadow is not None)
    packed = {}

    def every(k: int) -> _Pixels:  # every pixel, k x k samples each
        if k not in packed:
            packed[k] = _pack(xo, yo, vals, side, wo, k)
        return packed[k]

    # Stage 1: every start on b x b bins (b = 2, more on images over 40,000 pixels,
    # so at most ~10,000 bins; bin noise sigma / b).
    if min(h, w) >= 48:
        b = max(2, math.ceil(math.sqrt(h * w / _STAGE1_BINS)))
        xb, yb, mb = _bins(a, x, y, side, b)
        rb, cb = np.nonzero(np.isfinite(mb))
        v1, w1 = mb[rb, cb], np.ones(rb.size)
        d1, sigma1 = _pack(xb[cb], yb[rb], v1, side * b), sigma / b
    else:
        v1, w1 = vals, wo
        d1, sigma1 = every(2), sigma
    flat1 = float(np.sum(((v1 - v1.mean()) * w1) ** 2))
    # Each start until a step gains less than 1 in chi^2, or for 16 steps: they are
    # compared, and the best one is refined below. (A start that has not settled in
    # 16 steps has crept along a valley away from the ring: on the fit benchmark's
    # ring such starts stood at 1700 times the best one's cost.)
    fits = [_fit(_params(st, w0, peak, floor0, shadow), d1, lo, hi, sigma1, 2, tol=1.0,
                 max_steps=16) for st in starts]  # fmt: skip
    p, cost1, _ = min(fits, key=lambda fit: fit[1])
    if flat1 - cost1 < 36.0 * sigma1**2:
        # Below 6 sigma on the bins (noise alone gains chi^2 ~ 10 with these 9
        # parameters): nothing ring-like, and no full-resolution fit.
        return _summary(p, shadow is not None, sigma * side, _score(p, every(2), 2, sigma))

    # Stage 2: full resolution where the ring's model is above 1e-4 of its peak or the
    # image is bright, widened by 3 pixels (bins), and on the shadow's edge; the other
    # pixels as their mean.
    ring = np.zeros((h, w))
    ring[rows, cols] = _ring_profile(p, every(2))[: rows.size]
    near = _dilate((ring > 1e-4) | bright, 3) & ok
    del ring
    inside = np.zeros((h, w), bool)
    if shadow is not None:
        rho = np.hypot(x[None, :] - p[0], y[:, None] - p[1])
        near |= ok & (np.abs(rho - p[9]) < 3.0 * side)
        inside = rho < p[9] - 3.0 * side
        del rho
    far = ok & ~near & ~inside
    k = _samples_for(math.exp(p[5]) / side)
    nr, nc = np.nonzero(near)
    d2 = _pack(x[nc], y[nr], a[nr, nc], side, None if wt is None else wt[nr, nc], k)
    far_row = (0.0, 0.0)
    if far.any():  # the pixels far away, where the model is the floor, as their mean
        fv = a[far]
        fw2 = np.ones(fv.size) if wt is None else wt[far] ** 2
        far_row = (float(np.average(fv, weights=fw2)), math.sqrt(fw2.sum()))
    p, cost = _best_way_round(p, d2, far_row, every(k), k, _NO_VIEW, lo, hi, sigma)
    view = _NO_VIEW
    if focal is not None:
        # Stage 3: the same pixels seen by a camera turned toward the hole's image,
        # first placed by the oblique projection's offset d (R/f)^2.
        f = float(focal)
        x0, y0 = (float(v) / (1.0 + (math.exp(p[2]) / f) ** 2) for v in p[:2])
        view = (f, _view(f, x0, y0))
        p = p.copy()
        p[:2] = 0.0
        p, cost = _best_way_round(p, d2, far_row, every(k), k, view, lo, hi, sigma)
    guess = _summary(p, shadow is not None, sigma * side, _score(p, every(k), k, sigma, view, cost))
    if focal is not None:
        xc, yc = _from_view(float(p[0]), float(p[1]), *view)
        guess = eqx.tree_at(lambda g: (g.x_c, g.y_c), guess, (xc, yc))
    return guess


def _score(p, px: _Pixels, k: int, sigma: float, view=_NO_VIEW, cost: float | None = None):
    """$\\sqrt{\\Delta\\chi^2}$ of the model `p` against the best model without the
    arcs' light: its shadow's edge kept (which a camera whose ring lies outside the
    frame also shows) and its floor fitted anew (a faint arc broad enough to cover the
    frame is a floor: on pure noise one 0.3 noise sigmas bright, under a floor 0.24
    sigmas low, scored 27 against the model's own floor), on the pixels `px` (k x k
    area samples, seen through `view`), of noise `sigma`; `cost`: `p`'s own there,
    when known."""
    cost = _cost(p, px, k, view) if cost is None else cost
    unit = np.asarray(p, float).copy()
    unit[7], unit[8] = 0.0, 1.0  # the shadow's factor alone
    rows, _ = _evaluate(to_device(unit), px, k, _device_view(view))
    shade, d, w2 = (np.asarray(v).ravel() for v in (rows, px.data, px.weight**2))
    a, b = float(np.sum(w2 * shade * shade)), float(np.sum(w2 * d * shade))
    dark = float(np.sum(w2 * d * d)) - (b * b / a if a > 0 else 0.0)
    return math.sqrt(max(dark - cost, 0.0)) / sigma


# Below this offset (pixels) the ring turned round is the same ring (its centre moved by
# twice the offset): the turned fit is left out.
_ROUND_MIN = 0.25
# The steps of a fit before it is compared, and the most a winner is then fitted on for.
# On the fit benchmark's arcs and the tests' images the fits from the ring's start took
# 1-8 steps (29 on a noise-free image); a turned start that is not the ring's creeps
# along a valley (55 steps, at 10 times the other's cost, on the benchmark's first arcs).
_STEPS, _MORE_STEPS = 30, 90


def _best_way_round(p, d: _Pixels, far, every: _Pixels, k: int, view, lo, hi, sigma: float):
    """The better fit, on the pixels `d` (and the mean `far` of the others), from `p`
    and from `p` turned round: the same ridge with the primary and secondary swapped
    (centre moved by 2 b along psi, b reversed), which an arc offset of a pixel or two,
    or a frame cut, can leave nearly as good. Compared on all the pixels `every` (k x k
    area samples, seen through `view`): a fit may move an arc off the pixels `d`, where
    it would cost nothing. Each fit runs for at most `_STEPS` steps; the winner, where
    it has not settled, for up to `_MORE_STEPS` more.

    **Returns:** the parameters and their residual sum of squares on `every`."""
    starts = [p]
    if math.hypot(p[3], p[4]) > _ROUND_MIN:
        q = np.asarray(p, float).copy()
        q[:2] += 2.0 * q[3:5]
        q[3:5] *= -1.0
        q[6] = _shape_raw(-1.0)
        starts.append(q)
    fits = [_fit(q, d, lo, hi, sigma, k, far, view, max_steps=_STEPS) for q in starts]
    costs = [_cost(f[0], every, k, view) for f in fits]
    best, _, steps = fits[int(np.argmin(costs))]
    for _ in range(_MORE_STEPS // _STEPS):
        if steps < _STEPS:
            break
        best, _, steps = _fit(best, d, lo, hi, sigma, k, far, view, max_steps=_STEPS)
    return best, _cost(best, every, k, view)


def _ring_profile(p, px: _Pixels):
    """The ring's model (amplitude 1, floor 0, no shadow) on the pixels `px` (2 x 2
    area samples each: the program that scores the first stage's fits), flat (padding
    at the end)."""
    q = np.asarray(p, float).copy()
    q[7], q[8], q[9] = 1.0, 0.0, _NO_SHADOW
    rows, _ = _evaluate(to_device(q), px, 2, _device_view(_NO_VIEW))
    return np.asarray(rows).ravel()


def _nothing(floor: float, noise: float) -> ArcGuess:
    """The `ArcGuess` of an image with nothing to fit: NaN geometry, score 0."""
    nan = math.nan
    return ArcGuess(nan, nan, nan, nan, nan, nan, nan, nan, nan, nan, nan, floor, nan, noise, 0.0)


def _solve_s(target, r, c):
    """rho (pixels) with s(rho) = target, by bisection in log rho (s increases)."""
    lo, hi = math.log(1e-6 * r), math.log(1e3 * r)
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _s(math.exp(mid), r, c) < target else (lo, mid)
    return math.exp(0.5 * (lo + hi))


def _summary(p, shadow: bool, noise: float, score: float) -> ArcGuess:
    """The `ArcGuess` of fitted parameters `p`."""
    r, b, wid = math.exp(p[2]), math.hypot(p[3], p[4]), math.exp(p[5])
    c = float(_shape_c(p[6]))
    # Model flux on each side of the line through the centre perpendicular to psi
    # (frame psi = 0), on a polar grid covering both images.
    rr = np.linspace(max(r - 12 * wid - 2 * b, 0.02 * r), r + 12 * wid + 2 * b, 600)
    rg, pg = np.meshgrid(rr, np.linspace(-math.pi, math.pi, 720, endpoint=False))
    s = _s(rg, r, c)
    g = np.exp(-0.5 * ((s * np.cos(pg) - b) ** 2 + (s * np.sin(pg)) ** 2) / wid**2) * rg
    side = np.cos(pg) > 0
    return ArcGuess(
        x_c=float(p[0]),
        y_c=float(p[1]),
        ring_radius=r,
        ring_width=wid,
        psi=math.atan2(p[4], p[3]) % (2 * math.pi),
        outer_radius=_solve_s(b, r, c),
        inner_radius=_solve_s(-b, r, c),
        offset=b,
        shape=c,
        flux_ratio=float(g[side].sum() / max(g[~side].sum(), 1e-300)),
        amplitude=float(p[7]),
        floor=float(p[8]),
        shadow_radius=float(p[9]) if shadow else math.nan,
        noise=noise,
        score=float(score),
    )


# ------------------------------------------------------------- the star's offset


def offset_from_radii(rho_outer, rho_inner, distance, focal):
    """The star's angular offset $\\beta$ from the axis behind the hole, from the radii
    of its two images (exact escape angle, `jaxlens.trace`).

    A pinhole camera pointed at the hole sees a ray of local angle $\\alpha$ at
    $\\rho = f \\tan\\alpha$ pixels from the hole's image. The primary image lies where
    $\\Phi(\\alpha) = \\pi - \\beta$, the secondary where $\\Phi(\\alpha) = \\pi + \\beta$,
    so $\\beta = (\\Phi(\\alpha_-) - \\Phi(\\alpha_+)) / 2$; where the secondary's ray is
    captured (inside the shadow), $\\beta = \\pi - \\Phi(\\alpha_+)$ alone. (Weak field:
    $\\theta_\\pm = (\\beta \\pm \\sqrt{\\beta^2 + 4\\theta_E^2})/2$, so
    $\\beta = \\theta_+ - |\\theta_-|$.) A centre error $\\delta$ along $\\psi$ moves both
    radii and $\\beta$ by about $\\delta\\,|d\\Phi/d\\rho|$; it does not cancel.

    **Arguments:**
    - `rho_outer`, `rho_inner`: radii (pixels from the hole's image) of the primary
      (outer) and secondary (inner) images; arrays broadcast.
    - `distance`: camera radius $D$ (units of R_S, or a dimensionless astropy
      Quantity).
    - `focal`: focal length $f$ (pixels): $(W/2) / \\tan(\\mathrm{FOV}/2)$.

    **Returns:** $\\beta$ (radians), a float or a numpy array of the broadcast shape;
    NaN where the primary's ray is captured.
    """
    import jaxlens

    distance = length(distance, "distance")
    with jax.enable_x64(True):
        ro, ri, d, f = np.broadcast_arrays(
            *(np.asarray(v, np.float64) for v in (rho_outer, rho_inner, distance, focal))
        )
        alpha = np.arctan2(np.stack([ro, ri]), np.stack([f, f]))
        # Host arrays: padded on the host, no eager device operation to compile.
        res = jaxlens.trace(alpha, np.stack([d, d]), accuracy=1e-12, method="exact")
        phi = np.asarray(res.phi)
        esc = np.asarray(res.escaped)
    two = 0.5 * (phi[1] - phi[0])
    one = math.pi - phi[0]
    beta = np.where(esc[1], two, one)
    beta = np.where(esc[0], beta, np.nan)
    return float(beta) if beta.ndim == 0 else beta


def source_offset_from_arcs(guess: ArcGuess, distance, focal):
    """$\\beta$ (radians) from the arcs' radii in `guess` (`offset_from_radii`), for a
    camera at `distance` (units of R_S) with focal length `focal` (pixels)."""
    return offset_from_radii(guess.outer_radius, guess.inner_radius, distance, focal)
