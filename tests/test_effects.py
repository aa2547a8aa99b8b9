"""Moving observers, aberration, frequency shifts and blackbody colours against closed forms."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl

EPS = np.finfo(np.float64).eps
DISTANCES = [1.6, 2.0, 3.0, 10.0, 1e4]


# ------------------------------------------------------------------ observers


@pytest.mark.parametrize("d", DISTANCES)
def test_circular_orbit_speed_from_the_geodesic(d):
    # Independent derivation (M = 1/2): a circular geodesic has E = (1 - 2M/r) /
    # sqrt(1 - 3M/r), L = sqrt(M r^2 / (r - 3M)); the static observer measures
    # v = (L / r) / (E / sqrt(1 - 2M/r)).
    m = 0.5
    e = (1 - 2 * m / d) / math.sqrt(1 - 3 * m / d)
    ell = math.sqrt(m * d * d / (d - 3 * m))
    v = (ell / d) / (e / math.sqrt(1 - 2 * m / d))
    # tolerance: a few roundings of O(1) quantities
    assert float(jl.orbital_speed(d)) == pytest.approx(v, rel=10 * EPS)
    assert float(jl.orbital_speed(d)) == pytest.approx(1 / math.sqrt(2 * (d - 1)), rel=10 * EPS)
    # u^t = gamma / sqrt(1 - 1/D) = 1 / sqrt(1 - 3/(2D))
    ut = float(jl.lorentz_factor(jl.orbital_speed(d))) / math.sqrt(1 - 1 / d)
    assert ut == pytest.approx(1 / math.sqrt(1 - 1.5 / d), rel=10 * EPS)


@pytest.mark.parametrize("d", DISTANCES)
def test_infall_speed_from_energy(d):
    # E = 1 (rest at infinity): the static observer measures gamma = E / sqrt(1 - 1/D).
    gamma = 1 / math.sqrt(1 - 1 / d)
    v = math.sqrt(1 - 1 / gamma**2)
    assert float(jl.infall_speed(d)) == pytest.approx(v, rel=1e-12)  # 1 - 1/gamma^2 cancels


def test_static_blueshift():
    # PHYSICS.md: frequency x 1/sqrt(1 - 1/D); D = 2 gives sqrt(2) exactly
    assert float(jl.static_blueshift(2.0)) == pytest.approx(math.sqrt(2), rel=2 * EPS)
    assert float(jl.frequency_ratio(5.0, 0.3, 0.0)) == pytest.approx(math.sqrt(1.25), rel=4 * EPS)


def _lorentz(v, e):
    """4x4 boost to the frame moving with velocity v e (NumPy, independent of jaxlens)."""
    g = 1 / math.sqrt(1 - v * v)
    e = np.asarray(e, float)
    lam = np.eye(4)
    lam[0, 0] = g
    lam[0, 1:] = lam[1:, 0] = -g * v * e
    lam[1:, 1:] += (g - 1) * np.outer(e, e)
    return lam


@pytest.mark.parametrize("v", [0.1, 0.5, 0.9, 0.999])
def test_aberration_and_doppler_against_a_lorentz_matrix(v):
    rng = np.random.default_rng(1)
    e = rng.normal(size=3)
    e /= np.linalg.norm(e)
    ns = rng.normal(size=(200, 3))
    ns /= np.linalg.norm(ns, axis=1, keepdims=True)  # static-frame look directions
    k = np.concatenate([np.ones((200, 1)), -ns], axis=1)  # photon 4-momentum, E = 1
    kp = k @ _lorentz(v, e).T
    n_moving = -kp[:, 1:] / kp[:, :1]
    got = np.asarray(jl.aberrate(jnp.asarray(n_moving), v, jnp.asarray(e)))
    # conditioning: (1 - v p) ~ 1e-3 at v = 0.999 amplifies rounding ~1/(1 - v)
    tol = 50 * EPS / (1 - v)
    np.testing.assert_allclose(got, ns, atol=tol)
    cos_a = n_moving @ e
    np.testing.assert_allclose(jl.doppler_factor(cos_a, v), kp[:, 0], rtol=tol)
    # along the motion the 3-vector form is the scalar formula
    np.testing.assert_allclose(got @ e, jl.aberrate_cos(cos_a, v), atol=tol)
    # and the inverse boost is the boost with -v
    back = np.asarray(jl.aberrate(jnp.asarray(got), -v, jnp.asarray(e)))
    np.testing.assert_allclose(back, n_moving, atol=tol)


@pytest.mark.parametrize("d", [1.6, 3.0, 30.0])
def test_orbiting_camera_frequency_ratio_is_u_dot_p(d):
    # Covariant check: g = -p.u / E = u^t (1 - Omega L_z), with L_z the photon's angular
    # momentum about the orbit's axis (from its static-frame direction).
    v = float(jl.orbital_speed(d))
    e = np.array([1.0, 0.0, 0.0])
    rng = np.random.default_rng(2)
    n = rng.normal(size=(100, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)  # moving-frame look directions
    ns = np.asarray(jl.aberrate(jnp.asarray(n), v, jnp.asarray(e)))
    lz = -d * (ns @ e) / math.sqrt(1 - 1 / d)  # photon moves along -ns, local energy E/sqrt
    omega = math.sqrt(1 / (2 * d**3))
    ut = 1 / math.sqrt(1 - 1.5 / d)
    g = np.asarray(jl.frequency_ratio(d, n @ e, v))
    np.testing.assert_allclose(g, ut * (1 - omega * lz), rtol=1e-12)  # rounding only


def test_infalling_observer_looking_back():
    # Looking straight away from the hole, a camera falling from rest at infinity sees
    # the sky at g = 1 / (1 + sqrt(1/D)): exactly.
    for d in [2.0, 10.0, 1e3]:
        v = jl.infall_speed(d)
        g = jl.frequency_ratio(d, -1.0, v)
        assert float(g) == pytest.approx(1 / (1 + math.sqrt(1 / d)), rel=10 * EPS)


# ------------------------------------------------------------------ colours

# CIE 1931 2-degree observer (CIE 15:2004 table), wavelength nm: (x, y, z).
CIE = {
    450: (0.3362, 0.0380, 1.7721),
    500: (0.0049, 0.3230, 0.2720),
    555: (0.5121, 1.0000, 0.0057),
    600: (1.0622, 0.6310, 0.0008),
    650: (0.2835, 0.1070, 0.0000),
}
# Planckian locus chromaticities (x, y), CIE 1931 (illuminant A at 2856 K).
LOCUS = {
    2856.0: (0.44757, 0.40745),
    4000.0: (0.38045, 0.37676),
    6504.0: (0.31352, 0.32363),
    10000.0: (0.28070, 0.28840),
}


def test_colour_matching_functions_fit():
    lam = np.array(list(CIE))
    got = np.asarray(jl.cie_cmf(lam))
    # Wyman-Sloan-Shirley quote the multi-lobe fit to ~1% of the peak; 0.02 absolute
    np.testing.assert_allclose(got, np.array(list(CIE.values())), atol=0.02)


def test_planckian_locus():
    t = np.array(list(LOCUS))
    xyz = jl.blackbody_xyz_quadrature(t)
    xy = xyz[:, :2] / xyz.sum(axis=1, keepdims=True)
    # the CMF fit moves chromaticities by at most ~0.002
    np.testing.assert_allclose(xy, np.array(list(LOCUS.values())), atol=0.003)


def test_table_matches_quadrature():
    rng = np.random.default_rng(3)
    t = np.exp(rng.uniform(math.log(400.0), math.log(9e5), 400))
    xyz = jl.blackbody_xyz_quadrature(t)
    ref_rgb = xyz @ jl.XYZ_TO_SRGB.T / xyz[:, 1:2]
    ref_y = xyz[:, 1] / jl.blackbody_xyz_quadrature(np.array([6500.0]))[0, 1]
    # linear interpolation in ln T, spacing 0.002: error h^2/8 |f"| < 1e-4 (|f"| < 60 in Wien)
    np.testing.assert_allclose(jl.blackbody_color(t), ref_rgb, atol=2e-4 * np.abs(ref_rgb).max())
    np.testing.assert_allclose(jl.blackbody_luminance(t), ref_y, rtol=2e-4)
    # 6500 K is near the D65 white: equal channels to ~3%
    np.testing.assert_allclose(jl.blackbody_color(6500.0), [1, 1, 1], atol=0.05)
    assert float(jl.blackbody_luminance(6500.0)) == pytest.approx(1.0, abs=1e-4)


@pytest.mark.parametrize("g", [0.3, 0.8, 1.0, 1.7, 4.0])
@pytest.mark.parametrize("t", [3000.0, 5800.0, 20000.0])
def test_spectral_shift_from_invariance(g, t):
    # I_nu / nu^3 invariant: I_lambda,obs(lambda) = g^5 I_lambda,emit(g lambda). Integrate
    # that spectrum directly against the CMFs: must equal the "blackbody of gT" shortcut.
    lam = np.arange(360.0, 831.0, 0.5)
    cmf = np.asarray(jl.cie_cmf(lam, xp=np))
    with np.errstate(over="ignore"):  # exp overflow in Wien's tail is the intended 0
        obs = g**5 * np.asarray(jl.planck(g * lam, t, xp=np))
        emit = np.asarray(jl.planck(lam, t, xp=np))
    xyz = np.trapezoid(obs[:, None] * cmf, lam, axis=0)
    y0 = np.trapezoid(emit * cmf[:, 1], lam)
    want = jl.XYZ_TO_SRGB @ xyz / y0
    got = np.asarray(jl.shifted_blackbody(t, g, "spectral"))
    # quadrature grids differ (0.5 vs 1 nm) plus the table: 1e-3 relative
    np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-3 * np.abs(want).max())
    # bolometric: the whole-spectrum integral of the shifted spectrum is g^4 times
    lam_all = np.geomspace(10.0, 1e7, 20000)
    with np.errstate(over="ignore"):
        ratio = np.trapezoid(g**5 * np.asarray(jl.planck(g * lam_all, t, xp=np)), lam_all) / (
            np.trapezoid(np.asarray(jl.planck(lam_all, t, xp=np)), lam_all)
        )
    bol = np.asarray(jl.shifted_blackbody(t, g, "bolometric"))
    np.testing.assert_allclose(bol, ratio * np.asarray(jl.blackbody_color(t)), rtol=1e-4)


def test_temperature_gradient():
    f = jax.grad(lambda t: jnp.sum(jl.shifted_blackbody(t, 1.3, "spectral")))
    t = 5000.0
    h = 1e-3
    fd = (
        float(jnp.sum(jl.shifted_blackbody(t + h, 1.3, "spectral")))
        - float(jnp.sum(jl.shifted_blackbody(t - h, 1.3, "spectral")))
    ) / (2 * h)
    # piecewise-linear table: the derivative is the secant of one interval, which the
    # central difference (step << interval) reproduces to ~1e-6
    assert float(f(t)) == pytest.approx(fd, rel=1e-5)


# ------------------------------------------------------------------ skies


def test_blackbody_stars_and_shifted_sky():
    stars = jl.BlackbodyStars.from_angles([0.0, 0.5], [0.0, 0.2], 0.05, [2.0, 1.0], [3000.0, 9e3])
    n = jl.direction_from_angles(jnp.array([0.0, 0.5, 1.5]), jnp.array([0.0, 0.2, -1.0]))
    rest = np.asarray(stars(n))
    # at a star's centre: its colour, luminance = brightness (other star ~e^-50 away)
    np.testing.assert_allclose(rest[0], 2.0 * np.asarray(jl.blackbody_color(3000.0)), rtol=1e-9)
    np.testing.assert_allclose(rest[1], np.asarray(jl.blackbody_color(9e3)), rtol=1e-9)
    g = jnp.array([1.5, 0.7, 2.0])
    np.testing.assert_allclose(stars.shifted(n, jnp.ones(3), "spectral"), rest, rtol=1e-12)
    np.testing.assert_allclose(
        stars.shifted(n, g, "bolometric"), np.asarray(g)[:, None] ** 4 * rest, rtol=1e-12
    )
    spec = np.asarray(stars.shifted(n, g, "spectral"))
    np.testing.assert_allclose(spec[0], 2.0 * np.asarray(jl.shifted_blackbody(3000.0, 1.5)), 1e-9)
    # a plain RGB sky: flat spectrum, g^3 (spectral) or g^4 (bolometric); sums part by part
    sky = stars + jl.Uniform(0.1)
    got = np.asarray(sky.shifted(n, g, "spectral"))
    np.testing.assert_allclose(got, spec + 0.1 * np.asarray(g)[:, None] ** 3, rtol=1e-12)
    got = np.asarray(sky.shifted(n, g, "bolometric"))
    np.testing.assert_allclose(got, np.asarray(g)[:, None] ** 4 * (rest + 0.1), rtol=1e-12)


def test_bad_options():
    with pytest.raises(ValueError, match="mode"):
        jl.Redshift("thermal")
    with pytest.raises(ValueError, match="temperature"):
        jl.BlackbodyStars([[0, 0, 1.0]], 0.01, 1.0, -5.0)
    with pytest.raises(ValueError, match="D > 1.5"):
        jl.Scene(jl.Camera(1.4, 1.0, 8, 8), jl.Uniform(1.0), motion=jl.CircularOrbit())


# ------------------------------------------------------------------ in an image

D = 12.0
CAM = jl.Camera(D, math.radians(120), 48, 48)


def _camera_angles(camera):
    a, cb, sb = camera.rays()
    return np.asarray(a[..., 0]), np.asarray(cb[..., 0]), np.asarray(sb[..., 0])


def test_static_camera_sees_the_sky_blueshifted():
    scene = jl.Scene(CAM, jl.Uniform(0.5), redshift=jl.Redshift("bolometric"))
    img = jl.render(scene)
    a, _, _ = _camera_angles(CAM)
    sky = a > float(jl.shadow_angle(D)) + 0.05
    # g^4 = (1 - 1/D)^-2 on every escaping ray; float32 output
    np.testing.assert_allclose(img[sky], 0.5 * (1 - 1 / D) ** -2, rtol=1e-6)
    assert np.all(img[a < float(jl.shadow_angle(D)) - 0.05] == 0)


def test_infalling_camera_shadow_and_doppler():
    scene = jl.Scene(CAM, jl.Uniform(1.0), motion=jl.RadialInfall(),
                     redshift=jl.Redshift("bolometric"))  # fmt: skip
    img = jl.render(scene)[..., 1]
    a, _, _ = _camera_angles(CAM)
    v = math.sqrt(1 / D)
    ash = float(jl.shadow_angle(D))
    # the shadow seen in the moving frame: cos a' = (cos a_sh + v) / (1 + v cos a_sh)
    ash_moving = math.acos((math.cos(ash) + v) / (1 + v * math.cos(ash)))
    assert ash_moving < ash
    pix = math.radians(120) / 48 * 1.5  # a pixel and a half, in angle (upper bound)
    assert np.all(img[a < ash_moving - pix] == 0)
    out = a > ash_moving + pix
    assert np.all(img[out] > 0)
    g = np.asarray(jl.frequency_ratio(D, np.cos(a[out]), v))
    np.testing.assert_allclose(img[out], g**4, rtol=1e-5)  # float32 output


def test_orbiting_camera_shadow_against_a_lorentz_matrix():
    v = float(jl.orbital_speed(D))
    scene = jl.Scene(CAM, jl.Uniform(1.0), motion=jl.CircularOrbit(0.0))
    img = jl.render(scene)[..., 1]
    a, cb, sb = _camera_angles(CAM)
    n = np.stack([np.sin(a) * cb, np.sin(a) * sb, np.cos(a)], -1).reshape(-1, 3)
    # photon 4-momentum in the moving frame -> static frame with the inverse boost
    k = np.concatenate([np.ones((n.shape[0], 1)), -n], axis=1) @ _lorentz(-v, [1, 0, 0]).T
    ns = -k[:, 1:] / k[:, :1]
    a_static = np.arctan2(np.hypot(ns[:, 0], ns[:, 1]), ns[:, 2]).reshape(a.shape)
    ash = float(jl.shadow_angle(D))
    # Samples within half a sample of the edge (in static-frame alpha: the pixel's 2.5
    # degrees times the aberration's local scale, < 1.3 here) are area-weighted.
    margin = math.radians(120) / 48 * 1.5
    assert np.all(img[a_static < ash - margin] == 0)
    assert np.all(img[a_static > ash + margin] > 0)
    # the shadow is displaced toward the motion (+x): more black pixels on the right
    black = img == 0
    assert black[:, 24:].sum() > black[:, :24].sum()


def test_weak_field_series_is_bounded():
    rng = np.random.default_rng(4)
    f = jax.jit(jl.weak_field_escape_angle)
    for d in [20.0, 1e3, 1e6]:
        a = np.concatenate(
            [rng.uniform(0, math.pi, 4000), math.pi / 2 + 1e-6 * rng.normal(size=500)]
        )
        phi, bound = f(a, d)
        exact = jl.trace(a, d, method=jl.Exact(iterations=12)).phi
        ok = np.isfinite(np.asarray(bound))
        err = np.abs(np.asarray(phi - exact))[ok]
        assert ok.sum() > 3000
        assert np.all(err <= np.asarray(bound)[ok])  # the bound is rigorous
        # and not loose: within a factor 3 of the worst error where truncation dominates
        big = np.asarray(bound)[ok] > 1e-10
        if big.any():
            assert np.max(err[big] / np.asarray(bound)[ok][big]) > 1 / 3
    # camera at infinity: the deflection series (PHYSICS.md reference values)
    b = np.array([10.0, 100.0])
    d = 1e12
    a = np.arcsin(b * math.sqrt(1 - 1 / d) / d)
    phi, bound = jl.weak_field_escape_angle(a, d)
    np.testing.assert_allclose(np.asarray(phi) - (math.pi - a), [0.2361359954, 0.0202999662],
                               atol=float(np.max(bound)) + 1e-10)  # fmt: skip
