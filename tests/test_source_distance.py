"""Rays to a sphere at a finite radius (`radius_crossings`): every crossing's azimuth
against mpmath quadrature, the sky at infinity bit for bit, the hard cases (the
sphere inside the photon sphere, through the camera, inside the camera's radius,
grazed by the ray), under `jit`, `vmap` and `grad`, in float32 and float64."""

import math

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest

import jaxlens as jl
from jaxlens._exact import radius_crossings


def reference_crossings(alpha: float, distance: float, radius: float, dps: int = 40):
    """The azimuths (radians) at which a ray from a static camera at `distance` (R_S),
    local angle `alpha`, crosses r = `radius`, in order, by mpmath quadrature of
    du / sqrt(P) at `dps` digits; at a turning point u_t the substitution
    u = u_t -+ s^2 removes the square-root singularity. Shares no code with jaxlens."""
    with mp.workdps(dps):
        return [float(x) for x in mp_crossings(mp.mpf(alpha), mp.mpf(distance), mp.mpf(radius))]


def _paths_outside(to_turn, u0, ur, u2, inward):
    """The integrals along a ray from a camera outside the photon sphere (at u0) to
    each of its crossings of u = `ur`, in order, from `to_turn(u)` (the integral from u
    to the turning root u2): before the turning point, and after it."""
    out = []
    if inward:
        if u0 < ur <= u2:
            out.append(to_turn(u0) - to_turn(ur))
        if ur <= u2:
            out.append(to_turn(u0) + to_turn(ur))
    elif ur < u0:
        out.append(to_turn(ur) - to_turn(u0))
    return out


def mp_crossings(a, d, r):
    """`reference_crossings` at the working precision, for mpf arguments: mpf values."""
    dps = mp.mp.dps
    u0, ur = 1 / d, 1 / r
    b = d * abs(mp.sin(a)) / mp.sqrt(1 - u0)
    c = 1 / b**2
    p = lambda u: c - u**2 + u**3  # noqa: E731
    inward = mp.cos(a) > 0
    roots = mp.polyroots([c, 0, -1, 1], maxsteps=400, extraprec=4 * dps, asc=True)
    real = sorted(mp.re(x) for x in roots if abs(mp.im(x)) < mp.mpf(10) ** (-dps + 5))

    def plain(lo, hi):
        return mp.quad(lambda u: 1 / mp.sqrt(p(u)), [lo, hi])

    if len(real) == 3 and u0 <= real[1]:  # outside the photon sphere: u in [0, u2]
        u1, u2, u3 = real

        def to_turn(u):  # int_u^u2, u = u2 - s^2
            g = lambda s: 2 / mp.sqrt((u2 - s * s - u1) * (u3 - u2 + s * s))  # noqa: E731
            return mp.quad(g, [0, mp.sqrt(u2 - u)])

        return _paths_outside(to_turn, u0, ur, u2, inward)
    if len(real) == 3:  # inside: u in [u3, 1]
        u1, u2, u3 = real

        def to_turn(u):  # int_u3^u, u = u3 + s^2
            g = lambda s: 2 / mp.sqrt((u3 + s * s - u1) * (u3 + s * s - u2))  # noqa: E731
            return mp.quad(g, [0, mp.sqrt(u - u3)])

        out = []
        if not inward:
            if u3 <= ur < u0:
                out.append(to_turn(u0) - to_turn(ur))
            if u3 <= ur < 1:
                out.append(to_turn(u0) + to_turn(ur))
        elif u0 < ur < 1:
            out.append(to_turn(ur) - to_turn(u0))
        return out
    if inward and u0 < ur < 1:
        return [plain(u0, ur)]
    if not inward and ur < u0:
        return [plain(ur, u0)]
    return []


_crossings = jax.jit(radius_crossings)


def mp_times(a, d, r):
    """The coordinate times (units of R_S/c) light takes from each crossing of r = `r`
    (`mp_crossings`' order; `r` None: infinity) to the camera, less D + ln(D - 1) +
    R + ln(R - 1) (at infinity less D + ln(D - 1) and the diverging R + ln(R - 1)), by
    mpmath quadrature of dt = du / (b u^2 (1 - u) sqrt(P)) at the working precision,
    for a camera outside the photon sphere; mpf values. Shares no code with jaxlens
    (which sums b Phi and the radial action instead)."""
    u0 = 1 / d
    ur = mp.mpf(0) if r is None else 1 / r
    b = d * abs(mp.sin(a)) / mp.sqrt(1 - u0)
    c = 1 / b**2
    f = lambda u: 1 / (b * u**2 * (1 - u) * mp.sqrt(c - u**2 + u**3))  # noqa: E731
    shared = d + mp.log(d - 1) + (0 if r is None else r + mp.log(r - 1))

    def plain(lo, hi):  # int_lo^hi f; from lo = 0 less the diverging -1/u + ln u
        if lo > 0:
            return mp.quad(f, [lo, hi])
        x, eps = min(hi, 1 / (4 * b)), mp.mpf(10) ** (-mp.mp.dps // 3)
        g = lambda u: f(u) - 1 / u**2 - 1 / u  # noqa: E731
        rest = mp.quad(f, [x, hi]) if hi > x else 0
        return mp.quad(g, [eps, x]) + eps * (1 + b * b / 2) - 1 / x + mp.log(x) + rest

    inward = mp.cos(a) > 0
    roots = mp.polyroots([c, 0, -1, 1], maxsteps=400, extraprec=4 * mp.mp.dps, asc=True)
    real = sorted(mp.re(x) for x in roots if abs(mp.im(x)) < mp.mpf(10) ** (-mp.mp.dps + 5))
    out = []
    if len(real) == 3 and u0 <= real[1]:
        u1, u2, u3 = real

        def to_turn(u):  # int_u^u2 f, v = u2 - w s^2: sqrt(P) = s sqrt(w (v - u1)(u3 - v))
            w = u2 - u
            h = lambda v: 2 * mp.sqrt(w) / (b * v**2 * (1 - v) * mp.sqrt((v - u1) * (u3 - v)))  # noqa: E731
            g = lambda s: h(u2 - w * s * s)  # noqa: E731
            if u == 0:
                return plain(0, u2 - w / 4) + mp.quad(g, [0, mp.mpf(1) / 2])
            return mp.quad(g, [0, 1])

        out = _paths_outside(to_turn, u0, ur, u2, inward)
    elif inward and u0 < ur < 1:
        out.append(plain(u0, ur))
    elif not inward and ur < u0:
        out.append(plain(ur, u0))
    return [mp.re(t) - shared for t in out]


def _check(alpha, distance, radius, rtol, dtype=np.float64):
    a, d, r = (np.asarray(v, dtype) for v in np.broadcast_arrays(alpha, distance, radius))
    got = _crossings(a, d, r)
    assert got.first.dtype == dtype and got.second.dtype == dtype
    worst = 0.0
    for i in np.ndindex(a.shape):
        want = reference_crossings(float(a[i]), float(d[i]), float(r[i]))
        n = int(got.count[i])
        assert n == len(want), (a[i], d[i], r[i], n, want)
        for g, w in zip((float(got.first[i]), float(got.second[i]))[:n], want):
            worst = max(worst, abs(g - w) / abs(w))
        for j, v in enumerate((got.first[i], got.second[i])):
            if j >= n:
                assert v == 0.0  # no crossing: 0, never NaN
    assert worst < rtol, worst
    return worst


# Cameras inside the photon sphere, near it and far; spheres inside the photon sphere,
# at the camera's radius, inside and outside it.
DISTANCES = (1.2, 1.45, 2.0, 3.0, 20.0, 1e4)
RADII = (1.1, 1.3, 1.5, 1.6, 2.5, 3.0, 10.0, 20.0, 50.0, 1e6)


@pytest.mark.parametrize("distance", DISTANCES)
def test_every_crossing_matches_quadrature(distance):
    alpha = np.linspace(0.01, math.pi - 0.01, 7)[:, None]
    _check(alpha, distance, np.asarray(RADII)[None, :], 1e-11)


def test_the_sky_at_infinity_is_escape_angle_bit_for_bit():
    alpha = np.linspace(0.0, math.pi, 257)[:, None]
    distance = np.asarray([1.05, 1.5, 2.0, 3.0, 20.0, 1e12])[None, :]
    phi, status, _ = jax.jit(jl._exact.escape_angle)(alpha, distance)
    got = jax.jit(radius_crossings)(alpha, distance, np.inf)
    escaped = np.asarray(status) == jl.ESCAPED
    np.testing.assert_array_equal(np.asarray(got.first)[escaped], np.asarray(phi)[escaped])
    assert np.all(np.asarray(got.first)[~escaped] == 0.0)
    want = np.where(escaped, 1, np.where(np.asarray(status) == jl.UNRESOLVED, -1, 0))
    np.testing.assert_array_equal(got.count, want)


def test_a_sphere_through_the_camera():
    # R = D: the camera's own position is no crossing; an inward ray outside the
    # photon sphere comes back to D after its periapsis, an outward one inside it
    # after its apoapsis.
    # (alpha = pi/2 is left out: the ray starts at its turning point, tangent to the
    # sphere, where a crossing at an azimuth of order sqrt(eps) is rounding's.)
    for d in (1.3, 3.0, 20.0):
        alpha = np.linspace(0.05, math.pi - 0.05, 10)
        got = _crossings(alpha, d, d)
        assert np.all(np.asarray(got.count) <= 1)
        _check(alpha, d, d, 1e-11)


def test_grazing_rays():
    # A sphere just beyond a ray's periapsis is crossed twice, near the same azimuth;
    # just inside it, never.
    d, alpha = 20.0, 0.3
    r0 = float(jl.periapsis(jl.impact_parameter(alpha, d)))
    for rel in (1e-12, 1e-9, 1e-6, 1e-3):
        got = _crossings(alpha, d, r0 * (1 + rel))
        assert int(got.count) == 2
        want = reference_crossings(alpha, d, r0 * (1 + rel))
        np.testing.assert_allclose([got.first, got.second], want, rtol=1e-9, atol=1e-12)
        assert int(_crossings(alpha, d, r0 * (1 - rel)).count) == 0


def test_near_critical_rays_and_their_windings():
    # alpha within 1e-10 of the shadow's edge: the ray winds near the photon sphere
    # before it reaches R. The azimuth grows as -ln(alpha - alpha_sh), so its
    # condition number in alpha is 1 / ln(...) / 1e-10 ~ 4e8: float64's rounding of
    # the inputs' own arithmetic costs up to ~1e-8 of it there.
    d = 20.0
    a_sh = float(jl.shadow_angle(d))
    radii = np.asarray([3.0, 50.0])[:, None]
    assert _check(a_sh * (1 + np.asarray([1e-10])), d, radii, 3e-8) > 0
    _check(a_sh * (1 + np.asarray([1e-6, 1e-3])), d, radii, 1e-11)


def test_float32_matches_float64():
    alpha = np.linspace(0.02, math.pi - 0.02, 31)[:, None]
    radius = np.asarray([1.3, 3.0, 50.0, 1e6], np.float32)[None, :]
    for d in (2.0, 20.0, 1e4):
        lo = _crossings(alpha.astype(np.float32), np.float32(d), radius)
        hi = _crossings(alpha, d, radius.astype(np.float64))
        np.testing.assert_array_equal(lo.count, hi.count)
        for f, g in ((lo.first, hi.first), (lo.second, hi.second)):
            assert np.all(np.isfinite(f))
            np.testing.assert_allclose(f, g, rtol=2e-4, atol=1e-5)


def test_jit_vmap_and_gradients():
    alpha = jnp.linspace(0.05, math.pi - 0.05, 40)
    radii = jnp.asarray([1.3, 3.0, 20.0, 50.0, jnp.inf])
    d = 20.0

    def total(a, dd, r):
        c = radius_crossings(a, dd, r)
        return c.first + c.second

    eager = radius_crossings(alpha[:, None], d, radii[None, :])
    jitted = jax.jit(jax.vmap(lambda r: radius_crossings(alpha, d, r), out_axes=1))(radii)
    for e, j in zip(eager, jitted):  # the same within rounding (XLA fuses the jitted)
        np.testing.assert_allclose(e, j, rtol=1e-13, atol=1e-15)
    # Gradients with respect to every argument: finite everywhere (no branch's NaN
    # leaks through the masks), and where the ray crosses, equal to central
    # differences.
    grad = jax.vmap(jax.vmap(jax.grad(total, argnums=(0, 1, 2)), (None, None, 0)),
                    (0, None, None))  # fmt: skip
    grads = jax.jit(grad)(alpha, d, radii)
    for g in grads:
        assert np.all(np.isfinite(g))
    total = jax.jit(total)
    k, r0 = 10, 50.0
    a0 = float(alpha[k])
    for i, g in enumerate(grads):
        x = [a0, d, r0]
        h = 1e-6 * max(abs(x[i]), 1.0)
        up, dn = list(x), list(x)
        up[i] += h
        dn[i] -= h
        fd = (float(total(*up)) - float(total(*dn))) / (2 * h)
        assert abs(float(g[k, 3]) - fd) <= 1e-6 * max(abs(fd), 1.0), (i, float(g[k, 3]), fd)


def test_einstein_ring_of_a_source_at_a_finite_distance():
    # Sgr A*'s set-up: M = 2.8e6 M_sun seen from 8.5 kpc, a star as far behind it
    # (D_LS = D_OL). The primary ring, where the ray's crossing of r = D_LS lies
    # exactly behind the hole (azimuth pi), is at 1.158"; the source at infinity's,
    # 1.638". Weak field: theta_E = sqrt(2 D_LS / (D_OL D_OS)) (R_S = 1), to O(theta_E).
    d = 8.5 * 3.0856775814913673e19 / (2.8e6 * 2953.25)  # 8.5 kpc in R_S
    crossing = jax.jit(lambda a, r: radius_crossings(a, d, r).first)

    def ring(r):
        lo, hi = 1e-7, 1e-4  # radians: the first crossing's azimuth falls through pi
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if float(crossing(mid, r)) > math.pi else (lo, mid)
        return 0.5 * (lo + hi)

    arcsec = math.pi / 180 / 3600
    finite, infinite = ring(d), ring(np.inf)
    assert round(finite / arcsec, 3) == 1.158 and round(infinite / arcsec, 3) == 1.638
    np.testing.assert_allclose(finite, math.sqrt(2 * d / (d * 2 * d)), rtol=1e-4)
    np.testing.assert_allclose(infinite, math.sqrt(2 / d), rtol=1e-4)


SGR_A = 8.5 * 3.0856775814913673e19 / (2.8e6 * 2953.25)  # 8.5 kpc in R_S of 2.8e6 M_sun


def mp_image(theta, distance, radius, order, side, alpha, dps=50):
    """An image of a source at angle `theta` from +z on the sphere r = `radius` (inf:
    at infinity), by mpmath, near the local angle `alpha`: the crossing azimuth there
    and its derivative (`mp.diff`) give, by Newton steps in mpmath's precision, the
    angle where it is (2 order + 1) pi -+ theta (`side` 0: the source's side), and the
    signed magnification sin(alpha) / (sin(v) dv/dalpha), v the source's flat-space
    angle from the camera, and the reduced light travel time (`mp_times`). Returns
    (alpha, mu, time) as floats."""
    with mp.workdps(dps):
        d, th = mp.mpf(distance), mp.mpf(theta)
        r = None if math.isinf(radius) else mp.mpf(radius)
        target = (2 * order + 1) * mp.pi + (th if side else -th)

        def which(a):  # the index of the crossing nearest the target
            got = mp_crossings(a, d, mp.mpf(10) ** (dps + 10) if r is None else r)
            return min(range(len(got)), key=lambda i: abs(got[i] - target)), got

        def phi(a):
            i, got = which(a)
            return got[i]

        def flat(p):
            if r is None:
                return mp.atan2(mp.sin(p), -mp.cos(p))
            return mp.atan2(r * mp.sin(p), d - r * mp.cos(p))

        a = mp.mpf(alpha)
        for _ in range(2):  # the derivative at the root itself: it goes as 1/(a - a_sh)
            dphi = mp.diff(phi, a)
            a = a - (phi(a) - target) / dphi
        dphi = mp.diff(phi, a)
        mu = mp.sin(a) / (mp.sin(flat(target)) * mp.diff(flat, target) * dphi)
        return float(a), float(mu), float(mp_times(a, d, r)[which(a)[0]])


@pytest.mark.parametrize(
    ("distance", "radius", "theta", "order"),
    [
        (20.0, 50.0, 0.5, 0),  # the source beyond the camera's radius
        (20.0, 10.0, 0.3, 0),  # inside the camera's radius, outside the photon sphere
        (20.0, 10.0, 0.3, 2),
        (20.0, 1.2, 1.0, 0),  # inside the photon sphere: the captured rays' first crossing
        (20.0, 3.0, 2.8, 0),  # in front of the hole, nearly between it and the camera
        (1e4, 1e4, 1e-3, 0),  # weak field, the source as far behind as the camera before
        (20.0, math.inf, 0.5, 3),
        # Sgr A* (2.8e6 M_sun at 8.5 kpc), a star as far behind: the primary pair, and
        # the fourth relativistic pair 8e-12 of the shadow angle off its edge.
        (SGR_A, SGR_A, 1e-7, 0),
        (SGR_A, SGR_A, 5.6e-7, 4),
    ],
)
def test_point_images_at_a_finite_distance_match_mpmath(distance, radius, theta, order):
    direction = np.array([math.sin(theta), 0.0, math.cos(theta)])
    got = jl.point_source_images_at(direction, distance, radius, order=order)
    # The source's angle enters as (2 order + 1) pi -+ theta: it keeps eps (2 order + 1)
    # pi / theta of its relative accuracy (4e-9 at theta = 1e-7), which bounds the
    # magnification's; the position moves by at most that absolute amount.
    floor = np.spacing((2 * order + 1) * math.pi)
    want_t = []
    for side in (0, 1):
        a = float(got.alpha[side])
        want_a, want_mu, t = mp_image(theta, distance, radius, order, side, a)
        assert abs(a - want_a) <= 1e-12 * want_a + floor, (side, a, want_a)
        mu = float(got.magnification[side])
        tol = 1e-8 + 10.0 * floor / theta
        assert abs(mu - want_mu) <= tol * abs(want_mu), (side, mu, want_mu)
        # The time sums b Phi and the radial action, each of size b: it keeps eps b
        # absolutely (b the impact parameter, 1e-11 R_S/c at Sgr A*'s distance).
        b = distance * math.sin(a) / math.sqrt(1.0 - 1.0 / distance)
        assert abs(float(got.time[side]) - t) <= 1e-12 * abs(t) + 64 * np.spacing(b), (side, t)
        want_t.append(t)
    # The delay between the two images to 1e-6 relative (the Einstein ring's, where
    # it vanishes, to the same absolute floor).
    delay = float(got.time[1] - got.time[0])
    want = want_t[1] - want_t[0]
    assert abs(delay - want) <= 1e-6 * abs(want) + 128 * np.spacing(b), (delay, want)


def test_point_images_at_infinity_agree_with_the_ray_map():
    # The table's images (point_source_images) within its own accuracy, every order
    # the exact solve's.
    d = 20.0
    th = np.array([0.01, 0.1, 0.5, 1.0, 2.0, 3.0])
    direction = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], axis=-1)
    table = jl.RayMap.build(d)
    for order, mu_tol in ((0, 1e-9), (1, 1e-8), (2, 1e-5)):
        exact = jl.point_source_images_at(direction, d, np.inf, order=order)
        tab = jl.point_source_images(direction, table, order=order)
        np.testing.assert_allclose(exact.alpha, tab.alpha, rtol=1e-12)
        np.testing.assert_allclose(exact.beta, tab.beta, rtol=0, atol=0)
        np.testing.assert_allclose(exact.magnification, tab.magnification, rtol=mu_tol)


def _derivatives_match_differences(fn, d, r, rtol):
    """`jax.jacfwd` of `fn(d, r)` (a tuple of scalars) against central differences."""
    jac = jax.jit(jax.jacfwd(fn, argnums=(0, 1)))(d, r)
    f = jax.jit(fn)
    for i, (hd, hr) in enumerate(((1e-5, 0.0), (0.0, 1e-5))):
        up, dn = f(d + hd, r + hr), f(d - hd, r - hr)
        for k in range(len(up)):
            fd = (float(up[k]) - float(dn[k])) / 2e-5
            assert abs(float(jac[k][i]) - fd) <= rtol * abs(fd), (k, i, float(jac[k][i]), fd)


def test_point_images_at_gradients_and_bad_values():
    direction = jnp.array([0.3, 0.1, 0.9])
    # The images' positions: first derivatives through the root (implicit function).
    _derivatives_match_differences(
        lambda d, r: tuple(jl.point_source_images_at(direction, d, r, order=1).alpha),
        20.0, 10.0, 1e-6,
    )  # fmt: skip
    # Refused by name eagerly, and under jit (one program for the three).
    jitted = jax.jit(jl.point_source_images_at)
    for kwargs, name in (
        (dict(distance=1.2), "distance"),
        (dict(source_distance=1.0), "source_distance"),
        (dict(source_distance=np.nan), "source_distance"),
    ):
        args = dict(distance=20.0, source_distance=10.0) | kwargs
        with pytest.raises(ValueError, match=name):
            jl.point_source_images_at(direction, args["distance"], args["source_distance"])
        with pytest.raises(Exception, match=name):
            jitted(direction, args["distance"], args["source_distance"]).alpha.block_until_ready()
    with pytest.raises(ValueError, match="direction"):
        jl.point_source_images_at(np.zeros(3), 20.0, 10.0)


@pytest.mark.benchmark  # ~60 s: the second derivatives of the closed form compile slowly
def test_point_images_at_magnification_derivatives():
    direction = jnp.array([0.3, 0.1, 0.9])
    _derivatives_match_differences(
        lambda d, r: tuple(jl.point_source_images_at(direction, d, r, order=1).magnification),
        20.0, 10.0, 1e-5,
    )  # fmt: skip


def test_time_delays_between_orders_and_in_the_weak_field():
    # Each further winding near the photon sphere takes 2 pi b_c (its circumference over
    # the local speed of light); the relativistic images' delays approach it (Bozza and
    # Mancini 2004), within 4e-7 here from order 2 to 3.
    th = 0.3
    n = np.array([math.sin(th), 0.0, math.cos(th)])
    t2, t3 = (jl.point_source_images_at(n, 20.0, order=m).time for m in (2, 3))
    np.testing.assert_allclose(t3 - t2, 2 * math.pi * 1.5 * math.sqrt(3), rtol=1e-6)
    # The weak field: a point lens's delay between its two images, 4GM/c^3 [y sqrt(y^2 +
    # 4) / 2 + ln((sqrt(y^2 + 4) + y) / (sqrt(y^2 + 4) - y))] at the source offset y in
    # Einstein angles, is the limit; at D = R = 1e8 R_S (Einstein angle 1e-4) to 1e-4.
    d = r = 1e8
    y = 0.5
    theta = y * math.sqrt(2.0 / d * r / (d + r)) * (d + r) / r  # seen from the hole
    got = jl.point_source_images_at(np.array([math.sin(theta), 0.0, math.cos(theta)]), d, r)
    s = math.sqrt(y * y + 4.0)
    want = 2.0 * (y * s / 2.0 + math.log((s + y) / (s - y)))
    np.testing.assert_allclose(float(got.time[1] - got.time[0]), want, rtol=1e-4)
    # Seconds for a mass: 2 G M / c^3 per R_S / c.
    np.testing.assert_allclose(got.delay_seconds(4.0e6)[0], got.time[0] * 4.0e6 * 9.85e-6,
                               rtol=1e-3)  # fmt: skip


def test_reverse_mode_gradients_are_finite_on_a_grid_through_the_turning_point():
    # A ray that starts at its turning point (alpha = pi/2 exactly, a knot of a uniform
    # grid) once gave NaN in reverse mode: the factor it does not use had an infinite
    # derivative, which `where` multiplied by zero.
    a = jnp.linspace(0.0, math.pi, 65)
    assert float(a[32]) == math.pi / 2
    for r in (40.0, 10.0):
        g = jax.grad(lambda d, r=r: jl.radius_crossings(a, d, r).first.sum())(20.0)
        ga = jax.vmap(jax.grad(lambda x, r=r: jl.radius_crossings(x, 20.0, r).first))(a)
        assert np.isfinite(float(g)) and bool(jnp.all(jnp.isfinite(ga))), r
