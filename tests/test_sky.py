"""Skies: star profiles and positions, star fields, panoramas (seam, poles, rotation),
the flat background image, the checker sphere, the procedural sky."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl


@eqx.filter_jit
def evaluate(sky, n):
    return sky(n)


def test_angular_distance_tiny_and_antipodal():
    # 1e-9 rad apart: atan2(|n x s|, n.s) keeps full relative accuracy (a dot
    # product alone would round to 0). Relative 1e-6 allows for the vector round-off.
    s = np.array([0.0, 0.0, 1.0])
    for d in (1e-9, 1e-4, 1.0, math.pi - 1e-6):
        n = np.array([math.sin(d), 0.0, math.cos(d)])
        assert float(jl.angular_distance(jnp.asarray(n), s)) == pytest.approx(d, rel=1e-6)


def test_angles_round_trip():
    rng = np.random.default_rng(1)
    lon = rng.uniform(-math.pi, math.pi, 200)
    lat = rng.uniform(-1.5, 1.5, 200)
    lo, la = jl.angles_from_direction(jl.direction_from_angles(lon, lat))
    np.testing.assert_allclose(lo, lon, atol=1e-13)  # float64 round-off
    np.testing.assert_allclose(la, lat, atol=1e-13)
    # (0, 0) is +z behind the hole; +lon toward +x; +lat toward +y.
    np.testing.assert_allclose(jl.direction_from_angles(0.0, 0.0), [0, 0, 1], atol=1e-16)
    np.testing.assert_allclose(jl.direction_from_angles(math.pi / 2, 0.0), [1, 0, 0], atol=1e-16)
    np.testing.assert_allclose(jl.direction_from_angles(0.0, math.pi / 2), [0, 1, 0], atol=1e-16)


def test_gaussian_star_profile_and_position():
    sigma, peak = math.radians(2.0), 3.0
    star = jl.GaussianStar(sigma, peak, lon=0.4, lat=-0.2, color=(1.0, 0.5, 0.25))
    centre = jl.direction_from_angles(0.4, -0.2)
    np.testing.assert_allclose(star(centre), peak * np.array([1.0, 0.5, 0.25]), rtol=1e-12)
    # One sigma away along any great circle: exp(-1/2) of the peak.
    away = jl.rotation_matrix(0.4, -0.2, 0.0) @ np.asarray(jl.direction_from_angles(sigma, 0.0))
    assert float(star(jnp.asarray(away))[0]) == pytest.approx(peak * math.exp(-0.5), rel=1e-9)
    # Default: exactly behind the hole, +z.
    np.testing.assert_allclose(jl.GaussianStar(0.1).direction, [0, 0, 1])


def test_star_field_is_a_sum_of_stars():
    rng = np.random.default_rng(2)
    lon, lat = rng.uniform(-3, 3, 37), rng.uniform(-1.4, 1.4, 37)
    sig, bright = rng.uniform(0.05, 0.2, 37), rng.uniform(0.5, 2, 37)
    field = jl.StarField.from_angles(lon, lat, sig, bright)  # 37 stars: 3 padded blocks of 16
    n = jl.direction_from_angles(rng.uniform(-3, 3, 500), rng.uniform(-1.5, 1.5, 500))
    total = sum(jl.GaussianStar(s, b, lon=lo, lat=la)(n) for lo, la, s, b in
                zip(lon, lat, sig, bright))  # fmt: skip
    # The tangent-plane form and atan2(|n x s|, n.s) agree to float64 round-off.
    np.testing.assert_allclose(evaluate(field, n), total, rtol=1e-9, atol=1e-12)


def test_uniform_floor():
    n = jl.direction_from_angles(jnp.zeros(4), jnp.linspace(-1, 1, 4))
    np.testing.assert_array_equal(jl.Uniform(0.25)(n), np.full((4, 3), 0.25))
    np.testing.assert_array_equal(jl.Uniform([0.1, 0.2, 0.3])(n)[2], [0.1, 0.2, 0.3])


def _pano(h=8, w=16, seed=0):
    return np.random.default_rng(seed).random((h, w, 3)).astype(np.float32)


def test_panorama_texel_centres_and_bilinear():
    img = _pano()
    h, w = img.shape[:2]
    sky = jl.Panorama(img)
    j, i = np.meshgrid(np.arange(1, h - 1), np.arange(w), indexing="ij")
    lon = 2 * np.pi * (i + 0.5) / w - np.pi
    lat = np.pi / 2 - np.pi * (j + 0.5) / h
    # Texel centres give the texel (float32 image, float64 weights: 1e-6).
    np.testing.assert_allclose(
        evaluate(sky, jl.direction_from_angles(lon, lat)), img[1:-1], atol=1e-6
    )
    # Half-way between two texels in longitude: their mean.
    mid = evaluate(sky, jl.direction_from_angles(lon + np.pi / w, lat))
    np.testing.assert_allclose(mid, 0.5 * (img[1:-1] + np.roll(img[1:-1], -1, axis=1)), atol=1e-6)


def test_panorama_seam_is_seamless():
    # Walk across lon = +-pi in steps of 1/100 texel: neighbouring samples differ by
    # at most (step / texel) * (largest jump between adjacent texels), as for any
    # interior point; a seam would show a jump of the order of a texel difference.
    img = _pano()
    h, w = img.shape[:2]
    sky = jl.Panorama(img)
    step = (2 * np.pi / w) / 100
    lon = np.pi - 150 * step + step * np.arange(300)
    lon = np.where(lon > np.pi, lon - 2 * np.pi, lon)
    lat = np.full_like(lon, 0.3)
    v = np.asarray(evaluate(sky, jl.direction_from_angles(lon, lat)))
    bound = np.abs(np.diff(np.concatenate([img, img[:, :1]], axis=1), axis=1)).max() / 100
    assert np.abs(np.diff(v, axis=0)).max() <= 1.0001 * bound + 1e-7
    # At the seam itself: the wrapped neighbours (last and first column) are blended.
    at = evaluate(
        sky, jl.direction_from_angles(np.array([np.pi]), np.array([np.pi / 2 - np.pi * 3.5 / h]))
    )
    np.testing.assert_allclose(at[0], 0.5 * (img[3, -1] + img[3, 0]), atol=1e-6)


def test_panorama_poles_have_one_value():
    # On circles ever closer to the pole the value tends to the mean of the top
    # row whatever the longitude (no pinch), linearly in the distance to the pole.
    img = _pano()
    h = img.shape[0]
    sky = jl.Panorama(img)
    lon = np.linspace(-np.pi, np.pi, 64, endpoint=False)
    spread = []
    for eps in (1e-1, 1e-2, 1e-3):
        vals = np.asarray(
            evaluate(sky, jl.direction_from_angles(lon, np.full_like(lon, np.pi / 2 - eps)))
        )
        spread.append(np.abs(vals - img[0].mean(axis=0)).max())
    cap = (np.pi / h) / 2  # angular size of the cap above the first row's centre
    assert spread[1] <= spread[0] * 0.1 + 1e-6 and spread[2] <= spread[1] * 0.1 + 1e-6
    assert spread[2] <= (1e-3 / cap) * np.abs(img[0] - img[0].mean(axis=0)).max() + 1e-6
    south = evaluate(sky, jl.direction_from_angles(lon, np.full_like(lon, -np.pi / 2)))
    np.testing.assert_allclose(south, np.broadcast_to(img[-1].mean(axis=0), south.shape),
                               atol=1e-6)  # fmt: skip
    # Continuous across the first row's centre latitude (where the cap starts).
    lat0 = np.pi / 2 - np.pi * 0.5 / h
    a = evaluate(sky, jl.direction_from_angles(lon, np.full_like(lon, lat0 - 1e-7)))
    b = evaluate(sky, jl.direction_from_angles(lon, np.full_like(lon, lat0 + 1e-7)))
    np.testing.assert_allclose(a, b, atol=1e-5)


def test_panorama_rotation_is_the_sky_turned():
    img = _pano()
    yaw, pitch, roll = 0.5, -0.3, 0.2
    base = jl.Panorama(img)
    turned = jl.Panorama(img, yaw=yaw, pitch=pitch, roll=roll)
    rng = np.random.default_rng(3)
    n = np.asarray(jl.direction_from_angles(rng.uniform(-3, 3, 50), rng.uniform(-1.4, 1.4, 50)))
    r = np.asarray(jl.rotation_matrix(yaw, pitch, roll))
    # What was at n appears at R n.
    np.testing.assert_allclose(
        evaluate(turned, jnp.asarray(n @ r.T)), evaluate(base, jnp.asarray(n)), atol=1e-6
    )
    np.testing.assert_allclose(jl.Rotated(base, yaw, pitch, roll)(jnp.asarray(n @ r.T)),
                               evaluate(base, jnp.asarray(n)), atol=1e-6)  # fmt: skip


def test_equirectangular_round_trip():
    # A smooth sky sampled onto a grid and read back through jl.Panorama: the bilinear
    # error of a Gaussian of sigma 20 degrees on a 1 degree grid is below 1e-3.
    star = jl.GaussianStar(math.radians(20.0), 1.0, lon=0.5, lat=0.3)
    img = jl.equirectangular(star, 360, 180, dtype=jnp.float64)
    rng = np.random.default_rng(4)
    n = jl.direction_from_angles(rng.uniform(-3, 3, 300), rng.uniform(-1.5, 1.5, 300))
    np.testing.assert_allclose(jl.Panorama(img)(n), star(n), atol=1e-3)


def test_plane_image_geometry():
    img = _pano(6, 10)
    width = math.radians(40.0)
    sky = jl.PlaneImage(img, width)
    t = math.tan(width / 2)
    scale = 5 / t  # pixels per unit tangent: half width (5 px) at tan(width/2)
    # Texel (row 2, col 7) centre: X = (7.5 - 5)/scale, Y = (3 - 2.5)/scale.
    x, y = (7.5 - 5) / scale, (3 - 2.5) / scale
    n = np.array([x, y, 1.0]) / math.sqrt(x * x + y * y + 1)
    np.testing.assert_allclose(evaluate(sky, jnp.asarray(n)), img[2, 7], atol=1e-6)
    # Outside the picture and in front of the camera: nothing.
    assert float(jnp.abs(evaluate(sky, jnp.asarray([0.0, 0.0, -1.0]))).max()) == 0.0
    far = np.array([2 * t, 0.0, 1.0]) / math.hypot(2 * t, 1.0)
    assert float(jnp.abs(evaluate(sky, jnp.asarray(far))).max()) == 0.0
    # A plane of size S at distance L: width 2 atan(S / 2L).
    p = jl.PlaneImage.at_distance(img, 10.0, 20.0)
    assert float(p.width) == pytest.approx(2 * math.atan(0.25), rel=1e-15)


def test_checker_colours_by_quadrant():
    sky = jl.Checker(4, 2)
    lons = (0.2, math.pi / 2 + 0.2, math.pi - 0.2, -math.pi / 2 + 0.2)
    behind, right, front, left = (jl.direction_from_angles(lo, 0.3) for lo in lons)
    reds = [
        float(evaluate(sky, n)[0]) / float(evaluate(sky, n).max())
        for n in (behind, right, front, left)
    ]
    assert reds[0] == 1.0 and reds[3] == 1.0 and reds[1] < 0.5 and reds[2] < 0.5
    # Adjacent squares differ in brightness (parity).
    a = evaluate(sky, jl.direction_from_angles(0.2, 0.3))
    b = evaluate(sky, jl.direction_from_angles(0.2, -0.3))
    assert float(a.max()) != float(b.max())


def test_default_sky_is_finite_deterministic_and_continuous():
    sky = jl.DefaultSky(stars=False)
    rng = np.random.default_rng(5)
    n = jl.direction_from_angles(rng.uniform(-3.2, 3.2, 4000), rng.uniform(-1.57, 1.57, 4000))
    # Pairs 1e-6 rad apart: across the lon = +-pi seam, across the pole, elsewhere.
    d = 1e-6
    a = jl.direction_from_angles(
        jnp.array([math.pi - d / 2, 0.3, 1.0]), jnp.array([0.1, 1.5708, 0.0])
    )
    b = jl.direction_from_angles(
        jnp.array([-math.pi + d / 2, 0.3 + math.pi, 1.0 + d]), jnp.array([0.1, 1.5708, 0.0])
    )
    centre, _, pole = sky.galactic_frame()
    probe = jnp.concatenate([n, a, b, jnp.asarray(np.stack([centre, pole]))])
    v = np.asarray(evaluate(sky, probe))
    assert np.all(np.isfinite(v)) and np.all(v >= 0)
    np.testing.assert_array_equal(v, np.asarray(evaluate(sky, probe)))
    # The glow is a smooth function of direction: no seam at lon = +-pi and no pole
    # artefact. 1e-6 rad apart the values differ by < 1e-3 (its gradient is O(10)).
    va, vb = v[4000:4003], v[4003:4006]
    assert np.abs(va - vb).max() < 1e-3
    # The band's centre is far brighter than the sky at the galactic pole.
    assert v[-2].sum() > 20 * v[-1].sum()
    with_stars = np.asarray(evaluate(jl.DefaultSky(), probe))
    assert (with_stars - v).max() > 0.05  # the star layers add point sources


def test_skies_are_differentiable():
    n = jl.direction_from_angles(jnp.linspace(-0.2, 0.2, 9), jnp.zeros(9))
    img = jnp.asarray(_pano())

    def loss(star_lon, yaw, pano):
        s = jl.GaussianStar(0.1, 1.0, lon=star_lon) + jl.Panorama(pano, yaw=yaw)
        return jnp.sum(s(n))

    g = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(0.05, 0.1, img)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in g)
    eps = 1e-6  # central differences: truncation ~ eps^2, round-off ~ 1e-16 / eps
    f = jax.jit(loss)
    fd = (f(0.05 + eps, 0.1, img) - f(0.05 - eps, 0.1, img)) / (2 * eps)
    assert float(g[0]) == pytest.approx(float(fd), rel=1e-6)


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_to_rgb_channels(channels):
    a = np.random.default_rng(6).random((3, 4, channels)).astype(np.float32)
    rgb = jl.to_rgb(a)
    assert rgb.shape == (3, 4, 3)
    if channels <= 2:
        np.testing.assert_array_equal(rgb, np.repeat(a[..., :1], 3, axis=-1))
    else:
        np.testing.assert_array_equal(rgb, a[..., :3])


def test_bad_skies_raise():
    with pytest.raises(ValueError, match="5 channels"):
        jl.to_rgb(np.zeros((2, 2, 5)))
    with pytest.raises(ValueError, match="non-finite"):
        jl.Panorama(np.full((2, 4, 3), np.nan))
    with pytest.raises(ValueError, match="sigma"):
        jl.GaussianStar(0.0)
    with pytest.raises(ValueError, match="width"):
        jl.PlaneImage(np.zeros((2, 2, 3)), math.pi)
    with pytest.raises(ValueError, match="direction"):
        jl.GaussianStar(0.1, direction=(0.0, 0.0, 0.0))


# ------------------------------------------------------------------ the sky family

CAM = jl.Camera(12.0, math.radians(100.0), 12, 8, supersample=1)


def test_the_bases_are_abstract():
    with pytest.raises(TypeError):
        jl.AbstractSky()
    with pytest.raises(TypeError):
        jl.AbstractRGBSky()

    class NoShift(jl.AbstractSky):  # a sky of its own must say how it shifts
        def __call__(self, n):
            return n

    with pytest.raises(TypeError):
        NoShift()


class Glow(jl.AbstractRGBSky):
    """A user's sky: a Gaussian glow around `direction`, written with the public
    helpers; the same radiance as `GaussianStar(sigma, brightness, direction)`."""

    sigma: float
    brightness: float
    direction: jax.Array

    def __call__(self, n):
        d = jl.angular_distance(n, self.direction.astype(n.dtype))
        i = self.brightness * jnp.exp(-0.5 * (d / self.sigma) ** 2)
        return jnp.broadcast_to(i[..., None], n.shape)


def test_a_user_sky_renders_and_redshifts():
    direction = jl.direction_from_angles(0.2, -0.1)
    glow = Glow(0.3, 2.0, direction)
    star = jl.GaussianStar(0.3, 2.0, direction)
    n = jl.direction_from_angles(jnp.linspace(-3.0, 3.0, 7), jnp.linspace(-1.2, 1.2, 7))
    # the same arithmetic in another order: float64 round-off
    np.testing.assert_allclose(glow(n), star(n), rtol=1e-13, atol=1e-300)
    img, ref = jl.render(CAM, glow + jl.Uniform(0.1)), jl.render(CAM, star + jl.Uniform(0.1))
    assert np.any(img > 0.11)  # the glow is in view
    np.testing.assert_allclose(img, ref, rtol=1e-6)  # float32 images
    # flat spectrum: g^4 (bolometric), g^3 (spectral), as every plain RGB sky
    g = jnp.linspace(0.5, 2.0, 7)
    for mode, p in (("bolometric", 4), ("spectral", 3)):
        want = np.asarray(g)[:, None] ** p * np.asarray(star(n))
        np.testing.assert_allclose(glow.shifted(n, g, mode), want, rtol=1e-13, atol=1e-300)
    # in a rendered scene: a static camera at D sees g = (1 - 1/D)^-1/2 on every ray
    # that escapes (pixels on the shadow's edge, partly covered, are left out)
    shifted = jl.render(jl.Scene(CAM, glow, redshift=jl.Redshift("bolometric")))
    alpha = np.asarray(CAM.rays()[0][..., 0])
    sky = alpha > float(jl.shadow_angle(12.0)) + 0.05
    want = jl.render(CAM, glow)[sky] * (1 - 1 / 12.0) ** -2
    assert np.any(want > 0.01)  # lensed glow among the compared pixels
    np.testing.assert_allclose(shifted[sky], want, rtol=1e-6)  # float32 images


def test_sums_are_flat():
    a, b, c, d = (jl.Uniform(v) for v in (0.1, 0.2, 0.3, 0.4))
    s = (a + b) + (c + d)
    assert isinstance(s, jl.SkySum) and s.parts == (a, b, c, d)
    assert (a + (b + c)).parts == (a, b, c)
    with pytest.raises(TypeError):
        a + 1.0
    with pytest.raises(ValueError, match="non-empty tuple of skies"):
        jl.SkySum(())


def test_rotated_keeps_the_spectrum():
    # A blackbody star turned by yaw: the star at the turned position, colour shift too.
    kw = dict(sigma=0.05, brightness=2.0, temperature=4000.0)
    turned = jl.Rotated(jl.BlackbodyStars.from_angles([0.0], [0.1], **kw), yaw=0.3)
    there = jl.BlackbodyStars.from_angles([0.3], [0.1], **kw)
    n = jl.direction_from_angles(jnp.array([0.3, 0.32, 0.28]), jnp.array([0.1, 0.12, 0.09]))
    g = jnp.array([1.5, 0.7, 2.0])
    for mode in ("bolometric", "spectral"):
        # rotation round-off ~1e-16 in d, times d / sigma^2 <= 20 in the exponent
        np.testing.assert_allclose(
            turned.shifted(n, g, mode), there.shifted(n, g, mode), rtol=1e-12
        )
    spectral = np.asarray(turned.shifted(n, g, "spectral"))
    grey = np.asarray(g)[:, None] ** 3 * np.asarray(turned(n))
    assert not np.allclose(spectral, grey, rtol=1e-2)  # the colour changed, not only the level
