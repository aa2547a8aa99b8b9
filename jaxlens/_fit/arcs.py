"""Start values for a star off the axis: the two arcs of its image.

A Gaussian star at angle $\\beta$ from the point behind the hole, at position angle
$\\psi$ on the sky, is seen as two arcs: the primary (escape angle
$\\Phi = \\pi - \\beta$, outside the Einstein ring, on the star's side) and the
secondary ($\\Phi = \\pi + \\beta$, inside the ring, on the opposite side). `find_arcs`
measures them on an image (host-side numpy; one small jitted model for the
least-squares fit) and `offset_from_radii` turns the two arc radii into $\\beta$ with
the exact escape angle of `jaxlens.trace`.

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
samples a pixel. The primary and secondary images then lie on one line through the
centre; their radii along $\\psi$ and $\\psi + \\pi$ solve $s(\\rho) = \\pm b$.
"""

import math
from collections import deque

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

_K = 2  # area samples a pixel side in the model
_EDGE = 0.25  # width of the shadow's edge in the model (pixels)
_C_MIN, _C_MAX = -2.95, -0.6  # range of the shape c (m, n > 0 needs -3 < c < 1)


class ArcGuess(eqx.Module):
    """What `find_arcs` measured on an image (pixels from the image centre, $x$ right,
    $y$ up, as PHYSICS.md; angles in radians; intensities in the image's units).

    **Fields:**
    - `x_c`, `y_c`: centre of the lens (the hole's image), pixels from the image centre.
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
      against a flat image at the floor. Noise alone gives a few; refuse below ~10.
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


# ----------------------------------------------------------------- pixel statistics


def _coords(h: int, w: int):
    """Pixel-centre coordinates (x right, y up, from the image centre) of an (h, w) grid."""
    x = np.arange(w) + 0.5 - 0.5 * w
    y = 0.5 * h - (np.arange(h) + 0.5)
    return np.meshgrid(x, y)


def _noise_estimate(img: np.ndarray) -> float:
    """Per-pixel noise from the median absolute second difference along rows and columns
    (robust to the arcs and to NaN pixels)."""
    parts = [img[:, 2:] - 2.0 * img[:, 1:-1] + img[:, :-2], img[2:] - 2.0 * img[1:-1] + img[:-2]]
    d = np.concatenate([p.ravel() for p in parts])
    d = d[np.isfinite(d)]
    if d.size < 8:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(6.0))


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
    h, w = mask.shape
    seen = ~mask.ravel().copy()
    out = []
    for start in np.flatnonzero(~seen):
        if seen[start]:
            continue
        seen[start] = True
        queue, members = deque([start]), [start]
        while queue:
            k = queue.popleft()
            r, c = divmod(int(k), w)
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    rr, cc = r + dr, c + dc
                    if 0 <= rr < h and 0 <= cc < w:
                        j = rr * w + cc
                        if not seen[j]:
                            seen[j] = True
                            queue.append(j)
                            members.append(j)
        out.append(np.asarray(members))
    return out


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


def _shape_mn(raw):
    c = 0.5 * (_C_MIN + _C_MAX) + 0.5 * (_C_MAX - _C_MIN) * jnp.tanh(raw)
    return c, 0.5 * (3.0 + c), 0.5 * (1.0 - c)


def _shape_raw(c: float) -> float:
    u = (c - 0.5 * (_C_MIN + _C_MAX)) / (0.5 * (_C_MAX - _C_MIN))
    return float(np.arctanh(np.clip(u, -0.999, 0.999)))


def _s_of_rho(rho, r, raw):
    _, m, n = _shape_mn(raw)
    t = jnp.log(rho / r)
    return 0.5 * r * (jnp.exp(m * t) - jnp.exp(-n * t))


def _model_px(p, xs, ys, shadow: bool):
    """Model at the area samples `xs`, `ys` (pixels, shape (P, K*K)), averaged a pixel.

    `p`: x_c, y_c, ln R, b_x, b_y, ln w, shape (raw), A, floor[, R_sh]."""
    dx, dy = xs - p[0], ys - p[1]
    rho = jnp.sqrt(dx * dx + dy * dy + 1e-12)
    r = jnp.exp(p[2])
    s = _s_of_rho(rho, r, p[6])
    ex, ey = s * dx / rho - p[3], s * dy / rho - p[4]
    g = jnp.exp(-0.5 * (ex * ex + ey * ey) * jnp.exp(-2.0 * p[5]))
    val = p[8] + p[7] * g
    if shadow:
        val = val * jax.nn.sigmoid((rho - p[9]) / _EDGE)
    return val.mean(axis=-1)


@eqx.filter_jit
def _residual(p, xs, ys, data, weight, shadow: bool):
    return (_model_px(p, xs, ys, shadow) - data) * weight


@eqx.filter_jit
def _jacobian(p, xs, ys, data, weight, shadow: bool):
    return jax.jacfwd(lambda q: _residual(q, xs, ys, data, weight, shadow))(p)


def _pad(n: int) -> int:
    """Padded length (few distinct sizes, so the compiled model is reused)."""
    return int(2 ** math.ceil(math.log2(max(n, 256))))


class _Data(eqx.Module):
    """Pixels a fit compares: area-sample coordinates (P, K*K, pixels), values, weights
    (padding has weight 0)."""

    xs: np.ndarray
    ys: np.ndarray
    data: np.ndarray
    weight: np.ndarray


def _data(x, y, v, side: float = 1.0, weight=None) -> _Data:
    """Pixels (or bins) of side `side` centred at x, y with values v."""
    n = x.size
    size = _pad(n)
    off = ((np.arange(_K) + 0.5) / _K - 0.5) * side
    ox, oy = np.meshgrid(off, off)
    xp, yp = np.pad(x, (0, size - n)), np.pad(y, (0, size - n))
    wt = np.ones(n) if weight is None else weight
    return _Data(
        xp[:, None] + ox.ravel()[None],
        yp[:, None] - oy.ravel()[None],
        np.pad(v, (0, size - n)),
        np.pad(wt, (0, size - n)),
    )


def _lm(p0, d: _Data, shadow: bool, lower, upper, *, steps: int = 60, rtol: float = 1e-8):
    """Levenberg-Marquardt (Marquardt's diagonal scaling) with the parameters clipped
    to [lower, upper]; stops when a step lowers the cost by less than `rtol` of it.

    **Returns:** the parameters and the residual sum of squares."""
    args = tuple(jnp.asarray(v) for v in (d.xs, d.ys, d.data, d.weight))
    with jax.enable_x64(True):

        def res(p):
            return np.asarray(_residual(jnp.asarray(p), *args, shadow))

        def jac(p):
            return np.asarray(_jacobian(jnp.asarray(p), *args, shadow))

        p = np.clip(np.asarray(p0, float), lower, upper)
        r = res(p)
        cost = float(r @ r)
        lam = 1e-3
        for _ in range(steps):
            j = jac(p)
            jtj, g = j.T @ j, j.T @ r
            dg = np.maximum(np.diag(jtj), 1e-12 * max(np.max(np.diag(jtj)), 1e-300))
            done = True
            for _ in range(10):
                try:
                    step = -np.linalg.solve(jtj + lam * np.diag(dg), g)
                except np.linalg.LinAlgError:
                    lam *= 10.0
                    continue
                q = np.clip(p + step, lower, upper)
                rq = res(q)
                cq = float(rq @ rq)
                if np.isfinite(cq) and cq < cost:
                    done = cost - cq < rtol * cost
                    p, r, cost = q, rq, cq
                    lam = max(lam / 5.0, 1e-9)
                    break
                lam *= 8.0
            if done:
                break
    return p, cost


# ------------------------------------------------------------------- start values


def _bin2(img: np.ndarray) -> np.ndarray:
    """2 x 2 bins (NaN-aware mean; an odd last row or column dropped)."""
    h, w = img.shape[0] // 2 * 2, img.shape[1] // 2 * 2
    a = img[:h, :w].reshape(h // 2, 2, w // 2, 2)
    ok = np.isfinite(a)
    n = ok.sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, np.where(ok, a, 0.0).sum(axis=(1, 3)) / n, np.nan)


def _dilate(mask: np.ndarray, steps: int) -> np.ndarray:
    """Boolean dilation by a (2 steps + 1)-pixel square."""
    out = mask.copy()
    h, w = mask.shape
    for _ in range(steps):
        p = np.pad(out, 1)
        out = np.zeros_like(mask)
        for i in range(3):
            for j in range(3):
                out |= p[i : i + h, j : j + w]
    return out


def _geometry_starts(img, x, y, floor, noise):
    """Starting geometries (x_c, y_c, R, b, psi) from the bright pixels, their
    radial width, the peak above the floor and the dark disc (x, y, radius; None when
    not seen).

    The geometries: a circle through the bright pixels (the ridge, whose centre sits
    $b$ from the lens centre toward the primary) with $b$ from the flux asymmetry
    about it, both ways round; the two brightest pixel groups on a line through the
    centre, split in the ratio of the square roots of their fluxes (a point lens's
    magnification ratio); the dark disc's centre."""
    h, w = img.shape
    sm = _smooth(img)
    v = sm - floor
    ok = np.isfinite(v)
    peak = float(np.nanmax(v)) if ok.any() else 0.0
    # The smoothing averages 9 pixels: its noise is noise / 3.
    thr = max(4.0 * noise / 3.0, 0.12 * peak)
    bright = ok & (v > thr)
    if bright.sum() < 5:
        bright = ok & (v >= np.nanpercentile(v, 99.0))
    wt = v[bright]
    bx, by = x[bright], y[bright]
    shadow = None
    if floor > 0 and floor > 2.0 * noise:
        dark = ok & (sm < 0.5 * floor)
        comps = [c for c in _components(dark) if c.size >= 5]
        if comps:
            c = max(comps, key=lambda c: c.size)
            xr, yr = x.ravel()[c], y.ravel()[c]
            shadow = (float(xr.mean()), float(yr.mean()), math.sqrt(c.size / math.pi))
    width0 = 1.0
    starts = []
    circ = _circle_fit(bx, by, wt) if bx.size >= 5 else None
    if circ is not None and circ[2] < 4.0 * max(h, w):
        cx, cy, rr = circ
        rho = np.hypot(bx - cx, by - cy)
        width0 = float(np.sqrt(np.sum(wt * (rho - rr) ** 2) / np.sum(wt)))
        # Flux asymmetry about the circle's centre, over the pixels whose mirror image
        # through it is in the frame and finite (a frame cut does not bias it).
        mx = np.round(0.5 * w - 0.5 + 2 * cx - bx).astype(int)
        my = np.round(0.5 * h - 0.5 - (2 * cy - by)).astype(int)
        inside = (mx >= 0) & (mx < w) & (my >= 0) & (my < h)
        seen = np.zeros_like(inside)
        seen[inside] = np.isfinite(img[my[inside], mx[inside]])
        if seen.sum() >= 5:
            phi = np.arctan2(by - cy, bx - cx)[seen]
            h1 = np.sum(wt[seen] * np.exp(1j * phi)) / np.sum(wt[seen])
        else:
            h1 = 0.0j
        psi0, a1 = float(np.angle(h1)), float(abs(h1))
        # Point lens: flux ratio ~ 1 + 4 b / R, so the first harmonic ~ 2 b / R.
        b0 = float(np.clip(0.5 * a1 * rr, 0.5, 0.5 * rr))
        for sign in (1.0, -1.0):
            c0x = cx - sign * b0 * math.cos(psi0)
            c0y = cy - sign * b0 * math.sin(psi0)
            rad = math.sqrt(max(rr * rr - b0 * b0, 1.0))
            starts.append((c0x, c0y, rad, b0, psi0 + (0.0 if sign > 0 else math.pi)))
    comps = _components(bright)
    if len(comps) >= 2:
        flat_v = np.where(bright, v, 0.0).ravel()
        ranked = sorted(((flat_v[c].sum(), c) for c in comps), key=lambda t: -t[0])
        (f1, c1), (f2, c2) = ranked[0], ranked[1]
        if f2 > 0.02 * f1:
            xr, yr = x.ravel(), y.ravel()
            p1 = np.array(
                [np.average(xr[c1], weights=flat_v[c1]), np.average(yr[c1], weights=flat_v[c1])]
            )
            p2 = np.array(
                [np.average(xr[c2], weights=flat_v[c2]), np.average(yr[c2], weights=flat_v[c2])]
            )
            sep = float(np.hypot(*(p1 - p2)))
            if sep > 2.0:
                inner = sep / (1.0 + math.sqrt(f1 / f2))
                u = (p1 - p2) / sep
                cen = p2 + inner * u
                psi0 = float(math.atan2(u[1], u[0]))
                rad = math.sqrt(inner * (sep - inner))
                starts.append((float(cen[0]), float(cen[1]), rad, 0.5 * (sep - 2 * inner), psi0))
    if shadow is not None and circ is not None:
        sx, sy, _ = shadow
        cx, cy, rr = circ
        b0 = float(math.hypot(cx - sx, cy - sy))
        psi0 = float(math.atan2(cy - sy, cx - sx)) if b0 > 0 else 0.0
        starts.append((sx, sy, math.sqrt(max(rr * rr - b0 * b0, 1.0)), max(b0, 0.5), psi0))
    width0 = float(np.clip(width0, 0.5, 0.25 * max(h, w)))
    return starts, width0, max(peak, noise), shadow


def _params(start, width, peak, floor, shadow):
    cx, cy, r0, b0, psi0 = start
    p = [cx, cy, math.log(max(r0, 1.0)), b0 * math.cos(psi0), b0 * math.sin(psi0)]
    p += [math.log(width), _shape_raw(-1.0), peak, floor]
    if shadow is not None:
        p.append(shadow[2])
    return np.asarray(p)


def _bounds(h, w, scale, shadow: bool):
    big = 4.0 * max(h, w)
    lo = [-big, -big, math.log(0.5), -big, -big, math.log(0.05), -3.0, -10 * scale, -scale]
    hi = [big, big, math.log(big), big, big, math.log(0.25 * max(h, w)), 3.0, 10 * scale, scale]
    if shadow:
        lo.append(0.0)
        hi.append(big)
    return np.asarray(lo), np.asarray(hi)


def find_arcs(img, *, noise: float | None = None) -> ArcGuess:
    """Measure the arcs of an off-axis star's image: the lens centre, the ring's
    radius and width, the primary's azimuth, the arcs' radii and flux ratio.

    Host-side (numpy with one small jitted model, float64). The model of the module
    docstring is fitted (Levenberg-Marquardt) from several starting geometries on the
    image binned 2 x 2, then the best one again at full resolution on the pixels near
    the arcs and the shadow's edge (the rest, where the model is the floor, enter as
    their mean).

    **Arguments:**
    - `img`: linear intensity `(H, W)` (or `(H, W, C)`, channels averaged); NaN pixels
      are masked out. The arcs may be cut by the frame; the hole need not be at the
      image centre.
    - `noise`: per-pixel noise standard deviation (image units), when known; default a
      robust estimate from second differences.

    **Returns:** an `ArcGuess`; its `score` says whether anything ring-like was found.
    """
    a = np.asarray(img, dtype=np.float64)
    if a.ndim == 3:
        a = a.mean(axis=-1)
    if a.ndim != 2 or min(a.shape) < 8:
        raise ValueError(f"img of shape {np.shape(img)} must be (H, W) with H, W >= 8 pixels")
    ok = np.isfinite(a)
    if ok.sum() < 64:
        raise ValueError(f"img has {int(ok.sum())} finite pixels; at least 64 are needed")
    if noise is not None and not noise >= 0:
        raise ValueError(f"noise={noise!r} must be >= 0 (image units)")
    h, w = a.shape
    x, y = _coords(h, w)
    vals = a[ok]
    floor0 = float(np.median(vals))
    scale = max(float(np.max(np.abs(vals))), 1e-300)
    sigma = max(_noise_estimate(a) if noise is None else float(noise), 1e-9 * scale)
    flat_cost = float(np.sum((vals - vals.mean()) ** 2))
    if flat_cost <= (1e-9 * scale) ** 2 * vals.size:
        return _nothing(floor0, sigma)  # a blank image
    starts, w0, peak, shadow = _geometry_starts(a, x, y, floor0, sigma)
    use_shadow = shadow is not None
    lo, hi = _bounds(h, w, scale, use_shadow)

    # Stage 1: every start on the 2 x 2 bins (a quarter of the pixels).
    coarse = min(h, w) >= 48
    if coarse:
        b2 = _bin2(a)
        xb, yb = _coords(b2.shape[0], b2.shape[1])
        xb, yb = 2.0 * xb - (w % 2) * 0.0, 2.0 * yb
        okb = np.isfinite(b2)
        # Bin centres in full-resolution pixels (the binned grid is the top-left
        # 2*floor(h/2) x 2*floor(w/2) pixels).
        xb = xb + (0.5 * (w // 2 * 2) - 0.5 * w)
        yb = yb - (0.5 * (h // 2 * 2) - 0.5 * h)
        d1 = _data(xb[okb], yb[okb], b2[okb], side=2.0)
    else:
        d1 = _data(x[ok], y[ok], a[ok])
    best = None
    for st in starts:
        p, cost = _lm(_params(st, w0, peak, floor0, shadow), d1, use_shadow, lo, hi, rtol=1e-6)
        if best is None or cost < best[1]:
            best = (p, cost)
    if best is None:
        return _nothing(floor0, sigma)
    p = best[0]

    # Stage 2: full resolution near the arcs (where the model is above 1e-4 of its peak,
    # widened by 3 pixels) and the shadow's edge; the other pixels as their mean.
    with jax.enable_x64(True):
        d_all = _data(x[ok], y[ok], np.zeros(vals.size))
        ring = np.zeros(d_all.data.size)
        pr = p.copy()
        pr[8] = 0.0
        pr[7] = 1.0
        ring = np.asarray(
            _model_px(jnp.asarray(pr[:9]), jnp.asarray(d_all.xs), jnp.asarray(d_all.ys), False)
        )[: vals.size]
    near = np.zeros((h, w), bool)
    near[ok] = ring > 1e-4
    near = _dilate(near, 3)
    if use_shadow:
        rho = np.hypot(x - p[0], y - p[1])
        near |= np.abs(rho - p[9]) < 3.0
        inside = rho < p[9] - 3.0
    else:
        inside = np.zeros((h, w), bool)
    near &= ok
    far = ok & ~near & ~inside
    xs, ys, vs, ws = x[near], y[near], a[near], np.ones(int(near.sum()))
    if far.any():
        xs = np.append(xs, 1e6)
        ys = np.append(ys, 1e6)
        vs = np.append(vs, a[far].mean())
        ws = np.append(ws, math.sqrt(far.sum()))
    d2 = _data(xs, ys, vs, weight=ws)
    p, _ = _lm(p, d2, use_shadow, lo, hi, rtol=1e-9)
    with jax.enable_x64(True):
        full = _data(x[ok], y[ok], vals)
        r = np.asarray(
            _residual(
                jnp.asarray(p),
                *(jnp.asarray(v) for v in (full.xs, full.ys, full.data, full.weight)),
                use_shadow,
            )
        )
    cost = float(r @ r)
    score = math.sqrt(max(flat_cost - cost, 0.0)) / sigma
    return _summary(p, use_shadow, sigma, score)


def _nothing(floor, noise):
    nan = float("nan")
    return ArcGuess(nan, nan, nan, nan, nan, nan, nan, nan, nan, nan, nan, floor, nan, noise, 0.0)


def _solve_s(target, r, raw):
    """rho (pixels) with s(rho) = target, by bisection (s increases with rho)."""
    lo, hi = 1e-6 * r, 1e3 * r
    for _ in range(200):
        mid = math.sqrt(lo * hi)
        if float(_s_of_rho(mid, r, raw)) < target:
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


def _summary(p, shadow, noise, score) -> ArcGuess:
    with jax.enable_x64(True):
        r = math.exp(p[2])
        b = math.hypot(p[3], p[4])
        psi = math.atan2(p[4], p[3])
        c = float(_shape_mn(jnp.asarray(p[6]))[0])
        outer = _solve_s(b, r, p[6])
        inner = _solve_s(-b, r, p[6])
        wid = math.exp(p[5])
        # Model flux on each side of the line through the centre perpendicular to psi.
        rr = np.linspace(max(r - 12 * wid - 2 * b, 0.05 * r), r + 12 * wid + 2 * b, 600)
        ph = np.linspace(-math.pi, math.pi, 720, endpoint=False)
        rg, pg = np.meshgrid(rr, ph)
        s = np.asarray(_s_of_rho(jnp.asarray(rg), r, p[6]))
        ex = s * np.cos(pg) - b
        ey = s * np.sin(pg)
        g = np.exp(-0.5 * (ex * ex + ey * ey) / wid**2) * rg
        side = np.cos(pg) > 0
        ratio = float(g[side].sum() / max(g[~side].sum(), 1e-300))
    return ArcGuess(
        x_c=float(p[0]),
        y_c=float(p[1]),
        ring_radius=r,
        ring_width=wid,
        psi=float(psi % (2 * math.pi)),
        outer_radius=outer,
        inner_radius=inner,
        offset=b,
        shape=c,
        flux_ratio=ratio,
        amplitude=float(p[7]),
        floor=float(p[8]),
        shadow_radius=float(p[9]) if shadow else float("nan"),
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
    - `distance`: camera radius $D$ (units of R_S).
    - `focal`: focal length $f$ (pixels): $(W/2) / \\tan(\\mathrm{FOV}/2)$.

    **Returns:** $\\beta$ (radians), a float or a numpy array of the broadcast shape;
    NaN where the primary's ray is captured.
    """
    import jaxlens

    with jax.enable_x64(True):
        ro, ri, d, f = np.broadcast_arrays(
            *(np.asarray(v, np.float64) for v in (rho_outer, rho_inner, distance, focal))
        )
        alpha = np.arctan2(np.stack([ro, ri]), np.stack([f, f]))
        res = jaxlens.trace(jnp.asarray(alpha), jnp.asarray(np.stack([d, d])), method="exact")
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
