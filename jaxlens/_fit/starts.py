"""Starting values: the radial profile of the image, the table of the exact ring
relation, candidates along it (or from `init`) and their profile losses on a binned
image."""

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._area import rect_in_disc
from .._compile import program
from .._exact import R_PHOTON
from .._util import to_device
from . import ring_table_data
from .noise import clipped_mean, clipped_slope, clipping_bounds, noise_clipped, noise_level
from .pixels import bin_means, pixel_centres, pixel_edges
from .spd import solve_spd
from .table import escape_table, solve_with_slope, source_table


def compute_ring_table(source: tuple | None = None):
    """$D$, $\\alpha_E$, $\\alpha_{sh}$ and $d\\Phi/d\\alpha$ at $\\alpha_E$ on 49 camera
    distances $1.9 \\dots 10^5$ (those whose ring lies inside 88 deg), computed: what
    `ring_table_data` stores (numpy arrays; R_S, radians, radians, per radian). With
    `source`, `(slope, offset)` of a source sphere's radius $R = s D + R_0$
    (`SourceDistance.linear`), the ring of a source on it (`source_table`), at the
    distances with $R \\ge D$."""
    with jax.enable_x64(True):
        d = np.geomspace(1.9, 1e5, 49)
        s, r0 = (0.0, math.inf) if source is None else source
        out = _ring_relation(jnp.asarray(d), jnp.asarray(s), jnp.asarray(r0), source is not None)
        a, sh, slope = (np.asarray(v) for v in out)
    ok = np.isfinite(a) & (a < math.radians(88.0)) & (s * d + r0 > R_PHOTON)
    return d[ok], a[ok], sh[ok], slope[ok]


@functools.partial(jax.jit, static_argnums=3)
def _ring_relation(d, s, r0, finite: bool):
    """`compute_ring_table`'s values at the distances `d`: one program for every
    source sphere (`s`, `r0` arguments; `finite`: `source_table`'s map, else
    `escape_table`'s)."""

    def one(d):
        if finite:
            rr = s * d + r0  # (inside the photon sphere: filtered out after)
            table = source_table(d, jnp.where(rr > R_PHOTON, rr, 2.0 * R_PHOTON), knots=2048)
        else:
            table = escape_table(d, knots=2048)
        a, slope = solve_with_slope(table, jnp.pi)
        ok = table.escape_angle(0.5 * jnp.pi) < jnp.pi
        return jnp.where(ok, a, jnp.nan), table.alpha_sh, slope

    return jax.vmap(one)(d)


@functools.cache
def ring_table(source: tuple | None = None):
    """The stored `compute_ring_table()` (`ring_table_data`), as numpy arrays; with
    `source` (`(slope, offset)` of the source sphere's radius), computed for it."""
    if source is not None:
        return compute_ring_table(source)
    t = ring_table_data
    return tuple(np.asarray(v) for v in (t.DISTANCE, t.ALPHA_E, t.ALPHA_SH, t.SLOPE))


class _Setup(eqx.Module):
    """Static description of the start search's model: half the full image's width
    (pixels) and the escape table's knots."""

    half_width: float = eqx.field(static=True)
    knots: int = eqx.field(static=True)
    # A source on a sphere (`args`' last entry its radius' slope and offset): the
    # model's table is `source_table`'s (else `escape_table`'s, for a source at infinity).
    finite: bool = eqx.field(static=True, default=False)


# The start search's model is radial (a camera pointed at the hole, the star behind
# it): its values are taken on a grid of radii, at least `_RADII` knots out to the
# farthest bin corner and at least `_PER_WIDTH` to the ring's Gaussian width: on the
# benchmark ring's 8-pixel bins the primary image's bin averages lie within 7e-5 of its
# peak of the renderer's area-exact ones (the linear interpolation in radius), the
# shadow's shares within 2e-5 of the exact ones (linear in radius too; 1e-3 where its
# edge is tangent to a bin's side).
_RADII = 4096
_PER_WIDTH = 32


@functools.lru_cache(maxsize=4)
def _radial_weights(width: int, height: int, block: int, ring_width: float):
    """How a radial profile on a grid of radii averages over square bins (host-side
    numpy, once an image).

    The bins: `block` x `block` pixels of a `width` x `height` image (`pixel_edges`);
    `ring_width`: the ring's radial Gaussian width (pixels), which sets the grid's
    spacing $h$. Bins that are mirror images of each other about the centre's axes or
    diagonals see the same radial profile: one of each set is kept (a quarter of the
    bins of a centred grid, an eighth where the diagonals map bins onto bins). Kept
    for the next call with the same arguments.

    **Returns:** `((rho, first, inside, weights), group, count)`: the radii
    $\rho_j = j h$ (pixels); for each kept bin its first radius index $j_0$ (the grid
    point at or below its nearest point), its share within $\rho_{j_0 + l}$ (exact,
    `(kept, L)`; 0 at $l = 0$, 1 at $l = L - 1$) and the weights of a profile's values
    at those radii in its average (linear interpolation in $\rho$ across the exact area
    between neighbouring radii; each row sums to 1): device arrays. Then for each bin
    (row-major) the kept bin it mirrors, and the number of bins each kept one stands
    for (numpy).
    """
    x0, y0 = pixel_edges(width, height, block, np.float64)
    # Twice the centres' distances from the axes, whole numbers: exact keys.
    cx = np.rint(np.abs(2.0 * np.ravel(x0) + block)).astype(np.int64)
    cy = np.rint(np.abs(2.0 * np.ravel(y0) - block)).astype(np.int64)
    keys = np.stack([np.minimum(cx, cy), np.maximum(cx, cy)], axis=1)
    kept, group, count = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    x1 = 0.5 * (kept[:, 0] - block)
    y2 = 0.5 * (kept[:, 1] + block)
    x2, y1 = x1 + block, y2 - block
    reach = float(np.max(np.hypot(x2, y2)))
    n = _RADII
    while reach / n > ring_width / _PER_WIDTH and n < 8 * _RADII:
        n *= 2
    h = reach / n
    first = np.floor(np.hypot(np.clip(0.0, x1, x2), np.clip(0.0, y1, y2)) / h).astype(np.int32)
    # A bin spans at most its diagonal in radius; the span padded to a multiple of 16
    # (fewer shapes, so fewer programs).
    span = -(-(math.ceil(math.sqrt(2.0) * block / h) + 2) // 16) * 16
    r = (first[:, None] + np.arange(span)) * h
    col = (slice(None), None)
    inside = rect_in_disc(x1[col], x2[col], y1[col], y2[col], r) / float(block) ** 2
    inside = np.clip(inside, 0.0, 1.0)
    da = np.diff(inside, axis=1)
    weights = 0.5 * (np.pad(da, ((0, 0), (1, 0))) + np.pad(da, ((0, 0), (0, 1))))
    rho = h * np.arange(int(first.max()) + span)
    radial = tuple(to_device(v) for v in (rho, first, inside, weights))
    return radial, np.ravel(group), count


def _radial_basis(table, focal, sigma, radial):
    """The start search's two basis images on the kept bins of `_radial_weights`: the
    primary image of a star exactly behind the hole (unit peak brightness, Gaussian
    width `sigma` radians; no relativistic rings) and the floor's coverage (the share
    of each bin outside the shadow, exact), for a camera of focal length `focal`
    (pixels) at the distance of `table` (its `escape_table`)."""
    rho, first, inside, weights = radial
    span = weights.shape[1]
    alpha = jnp.arctan(rho / focal)
    phi = table.escape_angle(jnp.maximum(alpha, table.alpha_sh))
    star = jnp.exp(-0.5 * ((phi - jnp.pi) / sigma) ** 2)
    # Order 0 only (Phi < 2 pi), none inside the shadow: as the renderer's primary image.
    profile = jnp.where((alpha > table.alpha_sh) & (phi < 2.0 * jnp.pi), star, 0.0)
    g = jnp.sum(weights * profile[first[:, None] + jnp.arange(span)], axis=1)
    # The shadow's share of each bin, interpolated in the exact shares at the radii.
    t = focal * jnp.tan(table.alpha_sh) / rho[1] - first
    i = jnp.clip(jnp.floor(t), 0, span - 2).astype(first.dtype)[:, None]
    u = jnp.clip(t - i[:, 0], 0.0, 1.0)
    a0 = jnp.take_along_axis(inside, i, axis=1)[:, 0]
    a1 = jnp.take_along_axis(inside, i + 1, axis=1)[:, 0]
    shadow = jnp.where(t <= 0.0, 0.0, jnp.where(t >= span - 1, 1.0, a0 + u * (a1 - a0)))
    return g, 1.0 - shadow


_PROFILE_STEPS = 4  # Gauss-Newton steps on (log focal, log sigma) for each candidate
# The candidates are first refined by one step each, and the best `_SHORTLIST` of those
# by all `_PROFILE_STEPS`: half the model evaluations of refining all of them fully.
_SHORTLIST = 8


@program(profile="legacy_fusion_o1")
def _candidate_losses(cands, halves, args, setup: _Setup, steps):
    r"""Profile loss of each candidate distance.

    For each (D, fov, sigma) the distance is held fixed while `steps` Gauss-Newton steps
    (A and floor linear, steps on log focal length and log sigma clipped) fit the rest:
    candidates along the ring relation then differ by what D alone changes, not by the
    sub-pixel error of the measured ring radius. A NaN sigma is first taken from the
    half-maximum radii `halves` (inner, outer, pixels; inner NaN when the ring runs
    into the shadow): the Gaussian in $|\Phi - \pi|$ is at half its peak where
    $|\Phi - \pi| = \sqrt{2 \ln 2}\,\sigma$.

    `args`: the radial grid and weights of the binned image's kept bins
    (`_radial_weights`); for each kept bin the number of bins it stands for and the sum
    of their values and of their squares (over the scale); the scale; the clipping
    `(lo, hi, noise)`; 1.0 to fit sigma (0.0: sigma held at the candidate's; an
    argument, so both kinds of fit share this program); the source sphere's radius'
    `(slope, offset)` (read where `setup.finite`). `steps` (at least 1) is an
    argument too (one program for the short and the full refinement).

    **Returns:** loss (after the last step), fov, sigma, A and floor of each candidate.
    """
    radial, (count, s1, s2), scale, clip, fit_sigma, source = args
    lo, hi, noise = clip[0], clip[1], clip[2]
    hwhm = math.sqrt(2.0 * math.log(2.0))

    def one(c):
        d, fov = c[0], c[1]
        if setup.finite:
            table = source_table(d, source[0] * d + source[1], knots=setup.knots)
        else:
            table = escape_table(d, knots=setup.knots)
        focal = setup.half_width / jnp.tan(0.5 * fov)
        phi_in = table.escape_angle(jnp.arctan(jnp.nan_to_num(halves[0], nan=1.0) / focal))
        phi_out = table.escape_angle(jnp.arctan(halves[1] / focal))
        width = jnp.where(
            jnp.isnan(halves[0]), (jnp.pi - phi_out) / hwhm, 0.5 * (phi_in - phi_out) / hwhm
        )
        sigma = jnp.where(jnp.isnan(c[2]), jnp.clip(width, 1e-5, 0.5), c[2])
        q0 = jnp.stack([jnp.log(focal), jnp.log(sigma)])

        def basis(q):
            g, cov = _radial_basis(table, jnp.exp(q[0]), jnp.exp(q[1]), radial)
            return g, (g, cov)

        # A and floor by linear least squares at the first step, then Gauss-Newton on
        # all four (through the expected clipped value where the stored values were
        # clipped). The first step's pass gives the basis at the start: no pass of its
        # own (a candidate of the first round ran in 2/3 of the time).
        def step(i, carry):
            q, a, fl = carry
            jg, (g, cov) = jax.jacfwd(basis, has_aux=True)(q)
            # Least squares over the bins, each kept bin standing for `count` of them
            # (`s1`, `s2`: the sums of their values and of their squares).
            xm = jnp.stack([g, cov], axis=1)
            mm = xm.T @ (count[:, None] * xm)
            a0, f0 = solve_spd(mm + 1e-10 * jnp.diag(jnp.diag(mm)), xm.T @ s1)
            a, fl = jnp.where(i == 0, a0, a), jnp.where(i == 0, f0, fl)
            m = a * g + fl * cov
            res = s1 - count * clipped_mean(m, lo, hi, noise)  # summed over each set
            # sigma held: its column zero and a unit diagonal, so its step is 0 and the
            # others' are those of the system without it.
            held = jnp.asarray([0.0, 0.0, 0.0, 1.0], q.dtype) * (1.0 - fit_sigma)
            x = (
                clipped_slope(m, lo, hi, noise)[:, None]
                * jnp.concatenate([g[:, None], cov[:, None], a * jg], axis=1)
                * (1.0 - held)
            )
            mm = x.T @ (count[:, None] * x)
            delta = solve_spd(mm + 1e-10 * jnp.diag(jnp.diag(mm)) + jnp.diag(held), x.T @ res)
            delta = jnp.nan_to_num(delta)
            limit = jnp.asarray([0.05, 0.3], q.dtype)
            q = q + jnp.clip(delta[2:], -limit, limit)
            return q, a + delta[0], fl + delta[1]

        nan = jnp.asarray(jnp.nan, q0.dtype)
        q, a, fl = jax.lax.fori_loop(0, steps, step, (q0, nan, nan))
        g, (_, cov) = basis(q)
        c_ = clipped_mean(a * g + fl * cov, lo, hi, noise)
        rss = jnp.sum(s2 - 2.0 * c_ * s1 + count * c_ * c_)
        f = jnp.exp(q[0])
        fov = 2.0 * jnp.arctan(setup.half_width / f)
        s_ = jnp.exp(q[1])
        loss = jnp.where(jnp.isfinite(rss), rss, jnp.inf)
        return loss, fov, s_, a * scale, fl * scale

    def skip(c):  # rows with D = NaN are placeholders: not evaluated
        inf = jnp.asarray(jnp.inf, s1.dtype)
        return inf, c[1], jnp.nan_to_num(c[2], nan=1.0), inf, inf

    return jax.lax.map(lambda c: jax.lax.cond(jnp.isfinite(c[0]), one, skip, c), cands)


class _Profile(eqx.Module):
    """What the radial profile about the image centre shows (pixels, data units)."""

    ring_radius: float
    ring_width: float  # radial Gaussian sigma of the ring, pixels
    inner_half: float  # radius of half maximum inside the ring (nan: cut by the shadow)
    outer_half: float  # radius of half maximum outside the ring
    peak: float  # ring peak above the floor
    peak_noise: float  # noise of the profile at the peak (the mean of its pixels)
    floor: float
    noise: float  # per-pixel noise, robust estimate
    shadow_radius: float  # nan when no dark disc against a floor is seen


# Pixels of a strip of rows the radial profile sums at a time (its temporaries).
_STRIP_PIXELS = 1 << 20


def radial_profile(img, noise: float | None = None) -> _Profile:
    """The radial profile of an image about its centre, in 0.5-pixel rings of radius,
    and what it shows of a ring (`_Profile`: pixels, data units). Summed strip by
    strip of rows: no temporary the image's size. `noise`: the noise of one pixel
    (data units) when known; default `noise_level(img)` (the one step that takes
    temporaries of the image's size: give it where the caller has it)."""
    h, w = img.shape
    x, y = pixel_centres(h, w)
    dr = 0.5
    n = int(math.hypot(x[-1], y[0]) / dr) + 2  # past the farthest pixel centre's ring
    cnt = np.zeros(n, np.int64)
    tot = np.zeros(n)
    last = 0
    rows = max(1, _STRIP_PIXELS // w)
    for r in range(0, h, rows):
        idx = np.floor(np.hypot(x[None, :], y[r : r + rows, None]) / dr).astype(np.intp).ravel()
        last = max(last, int(idx.max()))
        cnt += np.bincount(idx, minlength=n)
        tot += np.bincount(idx, weights=img[r : r + rows].ravel(), minlength=n)
    cnt, tot = cnt[: last + 1], tot[: last + 1]
    ok = cnt > 0
    r_mid = (np.arange(cnt.size) + 0.5) * dr
    prof = np.interp(r_mid, r_mid[ok], tot[ok] / np.maximum(cnt[ok], 1))
    smooth = np.convolve(prof, np.ones(3) / 3.0, mode="same")
    smooth[0], smooth[-1] = prof[0], prof[-1]
    noise = noise_level(img) if noise is None else float(noise)
    i_pk = int(np.argmax(smooth[1:-1])) + 1 if smooth.size > 2 else int(np.argmax(smooth))
    # Sub-bin peak position (parabola through the three bins about the maximum).
    if 0 < i_pk < smooth.size - 1:
        a, b, c = smooth[i_pk - 1 : i_pk + 2]
        den = a - 2 * b + c
        shift = 0.5 * (a - c) / den if den < 0 else 0.0
        ring_radius = float(r_mid[i_pk] + np.clip(shift, -1, 1) * dr)
    else:
        ring_radius = float(r_mid[i_pk])
    outside = smooth[i_pk:]
    floor = float(np.min(outside)) if outside.size else 0.0
    peak = float(smooth[i_pk] - floor)
    half = floor + 0.5 * peak
    # Half-maximum radii, interpolated between bins and corrected for the blur of the
    # pixels, the bins and the smoothing (variance 1/12 + dr^2/12 + 2 dr^2/3 pixels^2).
    blur = 1.0 / 12.0 + dr**2 / 12.0 + 2.0 * dr**2 / 3.0
    j = i_pk
    while j + 1 < smooth.size and smooth[j] > half:
        j += 1
    f = (smooth[j - 1] - half) / max(smooth[j - 1] - smooth[j], 1e-300)
    outer = max(r_mid[j - 1] + np.clip(f, 0, 1) * dr - ring_radius, 0.25)
    j = i_pk
    while j > 0 and smooth[j] > half:
        j -= 1
    if j == 0 or prof[j] < 0.25 * peak + 0.5 * floor and prof[max(j - 1, 0)] < 0.5 * floor:
        inner = float("nan")  # the ring runs into the shadow (or the centre)
    else:
        f = (smooth[j + 1] - half) / max(smooth[j + 1] - smooth[j], 1e-300)
        inner = max(ring_radius - (r_mid[j + 1] - np.clip(f, 0, 1) * dr), 0.25)

    def unblur(hw):
        return 1.1774 * math.sqrt(max((hw / 1.1774) ** 2 - blur, 0.04))

    outer = unblur(outer)
    inner = unblur(inner) if math.isfinite(inner) else inner
    hw = outer if not math.isfinite(inner) else 0.5 * (outer + inner)
    ring_width = hw / 1.1774
    # The dark disc: the profile is ~0 at the centre and jumps to the floor at the edge.
    shadow_radius = float("nan")
    if floor > 5.0 * noise and prof[0] < 0.5 * floor:
        above = np.nonzero(prof[: i_pk + 1] > 0.5 * floor)[0]
        if above.size:
            shadow_radius = float(r_mid[above[0]] - 0.5 * dr)
    n_peak = float(cnt[max(i_pk - 1, 0) : i_pk + 2].sum())
    return _Profile(
        ring_radius,
        ring_width,
        ring_radius - inner,
        ring_radius + outer,
        peak,
        noise / math.sqrt(max(n_peak, 1.0)),
        floor,
        noise,
        shadow_radius,
    )


def _ring_candidates(prof: _Profile, width: int, sigma, source=None):
    """(D, fov, sigma) along the exact ring relation: for each D of the table, the FOV
    that puts the ring at the measured radius; sigma is the known one, or NaN for the
    candidate program to take from the half-maximum radii."""
    d, a_e, _, _ = ring_table(source)
    focal = prof.ring_radius / np.tan(a_e)
    fov = 2.0 * np.arctan(0.5 * width / focal)
    sig = np.full_like(d, np.nan if sigma is None else sigma)
    ok = (fov > math.radians(0.05)) & (fov < math.radians(179.0))
    # Invalid rows are kept with D = NaN (infinite loss): one candidate count, one program.
    return np.stack([np.where(ok, d, np.nan), np.where(ok, fov, 1.0), sig], -1)


def _from_init(init, prof: _Profile, width: int, sigma, source=None):
    """Candidates from the starting values `init`: as given, and moved along one
    parameter onto the measured ring radius (ring relation interpolated in the table)."""
    try:
        d0 = float(init["distance"])
        fov0 = float(init["fov"]) if "fov" in init else math.radians(float(init["fov_deg"]))
    except (KeyError, TypeError) as e:
        raise ValueError(
            f"init={init!r} must be a dict with 'distance' (R_S) and 'fov' (radians) or 'fov_deg'"
        ) from e
    s0 = sigma if sigma is not None else init.get("sigma", np.nan)
    d, a_e, _, _ = ring_table(source)
    if not (d[0] <= d0 <= d[-1]) or not (0 < fov0 < math.pi):
        raise ValueError(
            f"init distance={d0!r} R_S must be in [{d[0]:.3g}, {d[-1]:.3g}] and fov={fov0!r} "
            "radians in (0, pi)"
        )
    ld = np.log(d)
    focal0 = 0.5 * width / math.tan(0.5 * fov0)
    a0 = float(np.interp(math.log(d0), ld, a_e))
    focal1 = prof.ring_radius / math.tan(a0)
    out = [(d0, fov0, s0), (d0, 2.0 * math.atan(0.5 * width / focal1), s0)]
    target = math.atan(prof.ring_radius / focal0)
    if a_e.min() < target < a_e.max():
        out.append((float(np.exp(np.interp(-target, -a_e, ld))), fov0, s0))
    return np.asarray(out, float)


def distance_from_radii(ring_px: float, shadow_px: float, width: int, source=None):
    """Starting `{"distance", "fov"}` from the Einstein ring's and the shadow's radii in
    pixels (a camera pointed at the hole): their ratio $\tan\alpha_E / \tan\alpha_{sh}$
    depends on D alone (it grows as ~0.54 sqrt(D)), and the ring's radius then fixes the
    focal length. `None` when the ratio lies outside the table ($D$ 1.9 ... 1e5)."""
    d, a_e, sh, _ = ring_table(source)
    ratio = np.tan(a_e) / np.tan(sh)
    if not shadow_px > 0:  # a shadow found with no extent (a stretched image)
        return None
    q = ring_px / shadow_px
    if not (math.isfinite(q) and ratio.min() < q < ratio.max()):
        return None
    order = np.argsort(ratio)
    ld = float(np.interp(q, ratio[order], np.log(d)[order]))
    a = float(np.interp(ld, np.log(d), a_e))
    return {"distance": math.exp(ld), "fov": 2.0 * math.atan(0.5 * width * math.tan(a) / ring_px)}


def _search_inputs(img, prof: _Profile, star_sigma, scale, source=None):
    """The start search's model on the binned image: `(halves, args, setup, noise)` for
    `_candidate_losses` (`noise`: `(lo, hi, noise)`, the clipping bounds and the noise
    of one original pixel)."""
    h, w = img.shape
    coarse = max(1, round(min(h, w) / 40))
    cimg = bin_means(img, coarse)
    setup0 = _Setup(0.5 * w, 1024, source is not None)
    radial, group, count = _radial_weights(w, h, coarse, prof.ring_width)
    y = cimg.ravel() / scale
    sums = (count, np.bincount(group, y), np.bincount(group, y * y))
    # Values stored clipped at 0 (or 1) where the noise crossed them: the model is
    # then the expected clipped value, with the noise of one original pixel.
    lo, hi = clipping_bounds(img)
    noise = noise_clipped(img, prof, lo, hi)
    clip0 = to_device(np.asarray([lo, hi, noise]) / scale)  # clipping acts per original pixel
    args0 = (radial, tuple(to_device(v, np.float64) for v in sums), to_device(scale), clip0,
             to_device(float(star_sigma is None)),
             to_device((0.0, 0.0) if source is None else source, np.float64))  # fmt: skip
    halves = to_device([prof.inner_half, prof.outer_half])
    return halves, args0, setup0, (lo, hi, noise)


def _rows(cands):
    """The candidates of the ring relation and three rows for those from `init`."""
    extra = np.full((3, 3), np.nan)
    extra[:, 1] = 1.0
    return np.concatenate([extra, cands], axis=0)


def ring_start(img, prof: _Profile, star_sigma, init, scale, source=None):
    """Starting values of an Einstein-ring fit: candidates along the exact ring relation
    (and from `init`), each refined on a binned image with D held, the best by loss.

    **Returns:** `(distance, fov, sigma, brightness, floor, lo, hi, noise)`: R_S,
    radians, radians, data units; the clipping bounds of the stored values and the
    noise of one original pixel (data units). `source`: `(slope, offset)` of the
    radius of the sphere the star lies on (`SourceDistance.linear`; None: at infinity).
    """
    w = img.shape[1]
    halves, args0, setup0, (lo, hi, noise) = _search_inputs(img, prof, star_sigma, scale,
                                                            source)  # fmt: skip
    cands = _rows(_ring_candidates(prof, w, star_sigma, source))
    if init is not None:
        # Starting values in `init`: their own candidates only (the grid rows are skipped).
        given = _from_init(init, prof, w, star_sigma, source)
        cands[3:, 0] = np.nan
        cands[: len(given)] = given
    if not np.any(np.isfinite(cands[:, 0])):
        sphere = ""
        if source is not None:
            d = ring_table()[0]
            sphere = (f" of a source on the sphere R = {source[0]:.6g} D + {source[1]:.6g} "
                      f"R_S (the model holds R > 1.5, and searches D from {d[0]:g} to "
                      f"{d[-1]:g})")  # fmt: skip
        raise ValueError(
            f"no camera distance puts an Einstein ring{sphere} at {prof.ring_radius:.3g} "
            f"pixels from the centre of a {w}-pixel-wide image"
        )

    def losses(c, steps):
        out = _candidate_losses(to_device(c), halves, args0, setup0, to_device(steps))
        return [np.asarray(v) for v in out]

    # One step each, then the shortlist by all the steps (the other rows skipped: NaN D,
    # the same shape, so the same program).
    loss = losses(cands, 1)[0]
    loss = np.where(np.isfinite(loss), loss, np.inf)
    short = np.argsort(loss, kind="stable")[:_SHORTLIST]
    short = short[np.isfinite(loss[short])]
    cands = np.where(np.isin(np.arange(len(cands)), short)[:, None], cands,
                     np.asarray([np.nan, 1.0, 1.0]))  # fmt: skip
    loss, fovs, sig, amp, flo = losses(cands, _PROFILE_STEPS)
    loss = np.where(np.isfinite(loss), loss, np.inf)
    best = int(np.argmin(loss))
    d_s, fov_s, sig_s = float(cands[best][0]), float(fovs[best]), float(sig[best])
    return d_s, fov_s, sig_s, float(amp[best]), float(flo[best]), lo, hi, noise


# Former name, kept while modules outside this one still import it by it.
