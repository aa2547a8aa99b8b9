"""Point-spread functions: the Gaussian and image OTFs against direct spatial convolution
(scipy), the margin's error bound, flux conservation, no shift of a point source (odd
and even PSF images), gradients, float32, jit and vmap, and the argument checks; the PSF
objects against those functions, and `render(scene, psf=...)` against a brute-force
render, blur (scipy) and crop.

The PSF classes are not exported from `jaxlens` yet, so they are imported from their
private module.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage
from scipy.stats import norm

import jaxlens as jl
from jaxlens import convolve_psf, gaussian_otf, image_otf, psf_margin
from jaxlens._psf import AbstractPSF, GaussianPSF, ImagePSF

EPS64 = float(np.finfo(np.float64).eps)
EPS32 = float(np.finfo(np.float32).eps)


def _gaussian_image(shape, centre, sigma):
    """A sampled circular Gaussian (peak 1) on a grid of `shape`, centred at `centre`
    (row, column; pixel indices, pixel centres at integers)."""
    y, x = np.mgrid[0 : shape[0], 0 : shape[1]]
    return np.exp(-((y - centre[0]) ** 2 + (x - centre[1]) ** 2) / (2.0 * sigma**2))


def _centroid(img):
    y, x = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    t = img.sum()
    return (img * y).sum() / t, (img * x).sum() / t


def _alias_bound(sigma):
    """Largest difference between the band-limited Gaussian OTF and the sampled
    Gaussian's: the aliased terms, $\\le 2 e^{-\\pi^2 \\sigma^2 / 2}$ at the Nyquist
    frequency, with a factor 1.5 for the higher aliases and the normalisation."""
    return 3.0 * math.exp(-(math.pi**2) * sigma**2 / 2.0)


# --- the Gaussian OTF -----------------------------------------------------------------


@pytest.mark.parametrize("sigma", [1.5, 2.0, 3.0])
def test_gaussian_otf_matches_scipy_gaussian_filter(sigma):
    # pad = 0 and scipy's periodic boundary compare the kernels alone. scipy samples the
    # Gaussian (truncate=15: tails below e^-112); the OTF is the band-limited one. The
    # pointwise difference is at most max|dOTF| * ||x||_2 (Parseval), max|dOTF| the
    # aliasing bound, plus FFT round-off.
    rng = np.random.default_rng(0)
    img = rng.random((70, 90))
    out = np.asarray(convolve_psf(img, gaussian_otf(img.shape, sigma), pad=0))
    ref = ndimage.gaussian_filter(img, sigma, mode="wrap", truncate=15.0)
    tol = _alias_bound(sigma) * np.linalg.norm(img) + 100 * EPS64
    assert np.max(np.abs(out - ref)) < tol


def test_gaussian_otf_is_the_analytic_transform():
    # exp(-2 pi^2 sigma^2 (u^2 + v^2)) at rfft2's frequencies: 1 at (0, 0), and along the
    # first column (u = 0) the frequencies of fftfreq(H), including the Nyquist row.
    h, w, s = 12, 9, 1.3
    otf = np.asarray(gaussian_otf((h, w), s))
    assert otf.shape == (h, w // 2 + 1)
    v, u = np.fft.fftfreq(h), np.fft.rfftfreq(w)
    arg = -2.0 * math.pi**2 * s**2 * (v[:, None] ** 2 + u[None, :] ** 2)
    # exp's relative error is its argument's rounding, eps |arg| (|arg| <= 17 here)
    np.testing.assert_allclose(otf, np.exp(arg), rtol=4 * EPS64 * (1 + np.abs(arg).max()), atol=0)
    assert otf[0, 0] == 1.0
    np.testing.assert_array_equal(np.asarray(gaussian_otf((h, w), 0.0)), 1.0)  # no blur


# --- the margin -----------------------------------------------------------------------


def _linear_truth(sigma, frame, margin):
    """A scene with bright spots at and just outside the frame's edges, the frame of
    `frame` pixels inside a scene `margin` pixels wider on every side, and its linear
    convolution (scipy, kernel truncated at 14 sigma, well inside the scene's margin)."""
    rng = np.random.default_rng(3)
    h, w = frame
    scene = 0.1 * rng.random((h + 2 * margin, w + 2 * margin))
    for r, c in [(margin - 3, margin + 5), (margin + h + 2, margin + w // 2), (margin + 7, margin)]:
        scene[r, c] += 50.0  # point sources near (and beyond) the frame's edges
    truth = ndimage.gaussian_filter(scene, sigma, mode="constant", truncate=14.0)
    return scene, truth[margin : margin + h, margin : margin + w]


def _outside_square(sigma, pad):
    """Mass of the normalised sampled Gaussian outside the square of half-side `pad`."""
    n = np.arange(-60 * int(math.ceil(sigma)), 60 * int(math.ceil(sigma)) + 1)
    g = np.exp(-(n**2) / (2.0 * sigma**2))
    g /= g.sum()
    tail = g[np.abs(n) > pad].sum()
    return 1.0 - (1.0 - tail) ** 2


@pytest.mark.parametrize("nsigma", [4.0, 6.0])
def test_margin_bounds_the_wrap_around_error(nsigma):
    # The crop differs from the linear convolution only by the light carried farther
    # than pad: at most 2 x (PSF mass outside the square of half-side pad) x max|scene|
    # (the module docstring's bound), plus the aliasing of the band-limited kernel (at
    # sigma = 2.5, 3 e^-31, negligible).
    sigma, frame, margin = 2.5, (48, 60), 40
    scene, truth = _linear_truth(sigma, frame, margin)
    pad = psf_margin(sigma, nsigma=nsigma)
    assert pad == math.ceil(nsigma * sigma)
    model = scene[margin - pad : margin + frame[0] + pad, margin - pad : margin + frame[1] + pad]
    out = np.asarray(convolve_psf(model, gaussian_otf(model.shape, sigma), pad=pad))
    assert out.shape == frame
    bound = 2.0 * _outside_square(sigma, pad) * scene.max() + _alias_bound(sigma) * 50.0
    err = np.max(np.abs(out - truth))
    assert err < bound
    # without a margin the wrapped light of the edge sources is visible
    bare = scene[margin : margin + frame[0], margin : margin + frame[1]]
    no_margin = np.asarray(convolve_psf(bare, gaussian_otf(bare.shape, sigma), pad=0))
    assert np.max(np.abs(no_margin - truth)) > 100 * bound


# --- PSF images -----------------------------------------------------------------------


@pytest.mark.parametrize("psf_shape", [(5, 7), (1, 3), (9, 9)])
def test_odd_image_psf_matches_direct_convolution(psf_shape):
    # An odd PSF's middle pixel goes to the origin by a whole-pixel roll: the crop is the
    # direct spatial convolution (scipy.ndimage.convolve centres odd kernels on their
    # middle pixel too) up to FFT round-off, ~eps log2(N) of the image's scale.
    rng = np.random.default_rng(1)
    psf = rng.random(psf_shape) - 0.2  # negative pixels are allowed, the total is > 0
    pad = psf_margin(psf)
    assert pad == max(psf_shape) // 2
    img = rng.random((40 + 2 * pad, 50 + 2 * pad))
    out = np.asarray(convolve_psf(img, image_otf(img.shape, psf), pad=pad))
    ref = ndimage.convolve(img, psf / psf.sum(), mode="constant", cval=0.0)[pad:-pad, pad:-pad]
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e3 * EPS64 * np.abs(ref).max())


@pytest.mark.parametrize("n", [21, 22])
def test_sampled_gaussian_image_equals_gaussian_otf(n):
    # A sampled Gaussian centred on the PSF image's geometric centre, (n - 1) / 2: the
    # middle pixel for odd n, a pixel corner for even n, moved to the origin by half a
    # pixel. Both must give the analytic Gaussian OTF, up to the light the image cuts off
    # (counted twice: missing, and in the normalisation) and the aliasing. A half pixel
    # the wrong way would be off by ~0.1 at these widths.
    sigma, shape = 2.0, (64, 70)
    psf = _gaussian_image((n, n), ((n - 1) / 2, (n - 1) / 2), sigma)
    full = _gaussian_image((401, 401), (200, 200), sigma)
    cut = 1.0 - psf.sum() / full.sum()
    otf = np.asarray(image_otf(shape, psf))
    ref = np.asarray(gaussian_otf(shape, sigma))
    assert np.max(np.abs(otf - ref)) < 2.0 * cut + _alias_bound(sigma) + 100 * EPS64
    # and a real OTF: the PSF is symmetric about the origin
    assert np.max(np.abs(otf.imag)) < 100 * EPS64


def _point_source(shape, at):
    img = np.zeros(shape)
    img[at] = 1.0
    return img


@pytest.mark.parametrize("psf_shape", [(7, 7), (6, 8), (5, 6), (8, 5)])
def test_symmetric_psf_does_not_shift_a_point_source(psf_shape):
    # "middle" centres a PSF on its geometric centre: for a PSF symmetric about it (here
    # an elliptical Gaussian of widths 1.2 and 2 pixels), the blurred point source is
    # symmetric about the source's own pixel, odd, even or mixed sizes (to FFT round-off)
    # and brightest there. A half-pixel shift would break the symmetry at order 1.
    h, w = psf_shape
    y, x = np.mgrid[0:h, 0:w]
    psf = np.exp(-(((y - (h - 1) / 2) / 1.2) ** 2 + ((x - (w - 1) / 2) / 2.0) ** 2) / 2.0)
    at = (20, 23)
    img = _point_source((41, 47), at)
    out = np.asarray(convolve_psf(img, image_otf(img.shape, psf), pad=0))
    np.testing.assert_allclose(out, out[::-1, ::-1], rtol=0, atol=100 * EPS64)
    assert np.unravel_index(np.argmax(out), out.shape) == at
    np.testing.assert_allclose(_centroid(out), at, rtol=0, atol=1e-12)


def test_middle_of_an_off_centre_odd_psf_moves_the_image_by_the_offset():
    # The "middle" convention is the middle pixel, whatever the light does: a 5x5 PSF
    # with its light at offset (+1, -2) from the middle moves a point source by (+1, -2)
    # exactly (whole pixels, no interpolation); "centroid" leaves it in place.
    psf = np.zeros((5, 5))
    psf[3, 0] = 1.0
    img = _point_source((30, 31), (12, 15))
    moved = np.asarray(convolve_psf(img, image_otf(img.shape, psf), pad=0))
    np.testing.assert_allclose(moved, _point_source((30, 31), (13, 13)), rtol=0, atol=10 * EPS64)
    kept = np.asarray(convolve_psf(img, image_otf(img.shape, psf, centre="centroid"), pad=0))
    np.testing.assert_allclose(kept, img, rtol=0, atol=100 * EPS64)
    assert psf_margin(psf, centre="centroid") == 4  # the centroid is 4 columns from the edge


def test_centroid_centre_keeps_an_asymmetric_psf_from_shifting():
    # An asymmetric, well-sampled PSF (two Gaussians of widths 2.5 and 2.2 pixels, the
    # light centroid off the cutout's centre by a fraction of a pixel): the blurred point
    # source keeps its centroid to 1e-8 pixel (the aliasing of these widths, ~e^-24, and
    # the light the cutout cuts off, ~e^-18, set the floor).
    y, x = np.mgrid[0:31, 0:32]
    psf = np.exp(-((y - 15.3) ** 2 + (x - 14.8) ** 2) / (2 * 2.5**2)) + 0.3 * np.exp(
        -((y - 17) ** 2 + (x - 17.5) ** 2) / (2 * 2.2**2)
    )
    at = (32, 33)
    img = _point_source((65, 67), at)
    out = np.asarray(convolve_psf(img, image_otf(img.shape, psf, centre="centroid"), pad=0))
    np.testing.assert_allclose(_centroid(out), at, rtol=0, atol=1e-8)
    plain = np.asarray(convolve_psf(img, image_otf(img.shape, psf), pad=0))
    assert np.max(np.abs(np.subtract(_centroid(plain), at))) > 0.1  # the light's offset


# --- flux -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "otf_of",
    [
        lambda s: gaussian_otf(s, 1.7),
        lambda s: image_otf(s, np.random.default_rng(5).random((7, 9))),
        lambda s: image_otf(s, _gaussian_image((24, 25), (11.5, 12.0), 2.0)),
        lambda s: image_otf(s, _gaussian_image((25, 26), (12.3, 12.9), 2.0), centre="centroid"),
    ],
)
def test_flux_is_conserved(otf_of):
    # OTF(0) = 1: the circular convolution keeps the total to round-off. With a margin,
    # a point source at least 12 pixels inside the frame keeps its flux in the crop to
    # 1e-8: a Gaussian's light beyond 6 sigma is < 1e-8, the odd image PSF is compact,
    # and the well-sampled (sigma = 2) PSFs in cutouts of +-6 sigma, moved by a fraction
    # of a pixel, ring outside only with their aliasing (e^-20) and the light their
    # cutouts cut off (e^-18 of the peak).
    rng = np.random.default_rng(2)
    img = rng.random((50, 64))
    out = np.asarray(convolve_psf(img, otf_of(img.shape), pad=0))
    np.testing.assert_allclose(out.sum(), img.sum(), rtol=100 * EPS64)
    src = _point_source((50, 64), (25, 30))
    crop = np.asarray(convolve_psf(src, otf_of(src.shape), pad=12))
    assert abs(crop.sum() - 1.0) < 1e-8


# --- gradients ------------------------------------------------------------------------


def _loss(sigma, img, weight, pad):
    return jnp.sum(weight * convolve_psf(img, gaussian_otf(img.shape, sigma), pad=pad))


def test_gradient_in_sigma_against_finite_differences():
    # Central differences with h = 1e-4: truncation h^2 |f'''| / 6 ~ 2e-9 |f'''| and
    # round-off eps |f| / h ~ 1e-12 |f|; rtol 1e-7 covers both with room (f''' ~ f'
    # here: the loss varies on the scale of sigma itself).
    rng = np.random.default_rng(4)
    pad = 8
    img = rng.random((40 + 2 * pad, 44 + 2 * pad))
    weight = rng.standard_normal((40, 44))
    s, h = 1.8, 1e-4
    fd = (_loss(s + h, img, weight, pad) - _loss(s - h, img, weight, pad)) / (2 * h)
    rev = jax.grad(_loss)(s, img, weight, pad)
    fwd = jax.jacfwd(_loss)(s, img, weight, pad)
    np.testing.assert_allclose(rev, fd, rtol=1e-7)
    np.testing.assert_allclose(fwd, rev, rtol=1e-12)
    # and the OTF's own derivative, d/dsigma = -4 pi^2 sigma q^2 OTF, to round-off
    q2 = np.fft.fftfreq(20)[:, None] ** 2 + np.fft.rfftfreq(24)[None, :] ** 2
    d = jax.jacfwd(lambda t: gaussian_otf((20, 24), t))(s)
    ref = -4.0 * math.pi**2 * s * q2 * np.asarray(gaussian_otf((20, 24), s))
    np.testing.assert_allclose(d, ref, rtol=1e-13, atol=1e-16)
    # at sigma = 0 (no blur) the gradient is 0, not NaN
    assert float(jax.grad(_loss)(0.0, img, weight, pad)) == 0.0


def test_gradient_in_psf_pixels_against_finite_differences():
    # Through the normalisation and the centroid's sub-pixel move; a linear-ish function
    # of the pixel, so h = 1e-5 leaves truncation ~1e-10 and round-off ~1e-11: rtol 1e-6.
    rng = np.random.default_rng(7)
    img = rng.random((32, 36))
    weight = rng.standard_normal((24, 28))
    psf = rng.random((6, 7)) + 0.5

    @jax.jit
    def f(p):
        return jnp.sum(
            weight * convolve_psf(img, image_otf(img.shape, p, centre="centroid"), pad=4)
        )

    g = jax.grad(f)(jnp.asarray(psf))
    e = np.zeros_like(psf)
    e[2, 5] = 1e-5
    fd = (f(psf + e) - f(psf - e)) / 2e-5
    np.testing.assert_allclose(g[2, 5], fd, rtol=1e-6)


# --- float32, jit, vmap ---------------------------------------------------------------


def test_float32_path():
    # float32 in, float32 out (OTF, convolution, gradient). FFT round-off grows like
    # eps log2(N) (N = 7680 pixels, log2 N ~ 13): the image within 13 eps32 of its
    # scale of float64, the gradient (a sum over every pixel) within 1e-5 relative.
    rng = np.random.default_rng(8)
    img = rng.random((80, 96))
    s32, img32 = jnp.float32(2.5), jnp.asarray(img, jnp.float32)
    otf32 = gaussian_otf(img.shape, s32)
    assert otf32.dtype == jnp.float32
    assert image_otf(img.shape, jnp.ones((3, 4), jnp.float32)).dtype == jnp.complex64
    out32 = convolve_psf(img32, otf32, pad=10)
    assert out32.dtype == jnp.float32
    out64 = convolve_psf(img, gaussian_otf(img.shape, 2.5), pad=10)
    tol = EPS32 * math.log2(img.size) * np.abs(img).max()
    assert np.max(np.abs(np.asarray(out32, np.float64) - out64)) < tol

    def f(s, im):
        return jnp.sum(convolve_psf(im, gaussian_otf(im.shape, s), pad=10) * im[10:-10, 10:-10])

    g32 = jax.grad(f)(s32, img32)
    assert g32.dtype == jnp.float32
    np.testing.assert_allclose(float(g32), float(jax.grad(f)(2.5, img)), rtol=1e-5)
    # a float32 image with a float64 OTF stays float32
    assert convolve_psf(img32, gaussian_otf(img.shape, 2.5), pad=10).dtype == jnp.float32


def test_jit_and_vmap():
    # the same numbers eagerly, under jit (sigma traced) and vmapped over widths and
    # over images (to round-off).
    rng = np.random.default_rng(9)
    imgs = rng.random((3, 30, 34))
    sigmas = jnp.array([0.5, 1.5, 3.0])

    def blur(im, s):
        return convolve_psf(im, gaussian_otf(im.shape, s), pad=5)

    eager = np.stack([np.asarray(blur(im, s)) for im, s in zip(imgs, sigmas)])
    np.testing.assert_allclose(jax.jit(blur)(imgs[1], sigmas[1]), eager[1], atol=100 * EPS64)
    np.testing.assert_allclose(jax.vmap(blur)(imgs, sigmas), eager, atol=100 * EPS64)
    np.testing.assert_allclose(
        jax.jit(jax.vmap(blur, in_axes=(None, 0)))(imgs[0], sigmas),
        np.stack([np.asarray(blur(imgs[0], s)) for s in sigmas]),
        atol=100 * EPS64,
    )
    # leading batch axes broadcast without vmap
    np.testing.assert_allclose(
        convolve_psf(imgs, gaussian_otf(imgs.shape[1:], 1.5), pad=5),
        np.stack([np.asarray(blur(im, 1.5)) for im in imgs]),
        atol=100 * EPS64,
    )
    # image PSFs under vmap (traced PSF values)
    psfs = rng.random((3, 5, 6)) + 0.1
    batched = jax.vmap(lambda p: image_otf((30, 34), p))(psfs)
    np.testing.assert_allclose(batched[2], image_otf((30, 34), psfs[2]), atol=100 * EPS64)


def test_traced_bad_values_fail_at_run_time():
    with pytest.raises(Exception, match="sigma_px must be finite and >= 0"):
        jax.jit(lambda s: gaussian_otf((8, 8), s))(-1.0).block_until_ready()
    with pytest.raises(Exception, match="total <= 0"):
        jax.jit(lambda p: image_otf((8, 8), p))(-jnp.ones((3, 3))).block_until_ready()


# --- argument checks ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("psf", "match"),
    [
        (-np.ones((3, 3)), "total of -9.0"),
        (np.array([[1.0, np.nan], [0.0, 1.0]]), "NaN or infinite"),
        (np.zeros((3, 3)), "all zeros"),
        (np.ones((9, 3)), "bigger than the image of 8x8"),
        (np.ones(5), "not a 2-D image"),
    ],
)
def test_image_otf_rejects_bad_psfs(psf, match):
    with pytest.raises(ValueError, match=match):
        image_otf((8, 8), psf)


def test_argument_checks():
    with pytest.raises(ValueError, match="sigma_px=-0.5"):
        gaussian_otf((8, 8), -0.5)
    with pytest.raises(ValueError, match="sigma_px=nan"):
        gaussian_otf((8, 8), float("nan"))
    with pytest.raises(ValueError, match="shape="):
        gaussian_otf((8,), 1.0)
    with pytest.raises(ValueError, match="centre='peak'"):
        image_otf((8, 8), np.ones((3, 3)), centre="peak")
    with pytest.raises(ValueError, match=r"needs \(\.\.\., 20, 11\)"):
        convolve_psf(np.zeros((20, 20)), gaussian_otf((18, 18), 1.0), pad=1)
    with pytest.raises(ValueError, match="pad=-1"):
        convolve_psf(np.zeros((20, 20)), gaussian_otf((20, 20), 1.0), pad=-1)
    with pytest.raises(ValueError, match="pad=10 leaves nothing"):
        convolve_psf(np.zeros((20, 20)), gaussian_otf((20, 20), 1.0), pad=10)
    assert psf_margin(2.0) == 8 and psf_margin(0.3) == 2 and psf_margin(0.0) == 0
    assert psf_margin(np.ones((7, 7))) == 3 and psf_margin(np.ones((6, 9))) == 4
    with pytest.raises(ValueError, match="concrete"):
        jax.jit(psf_margin)(1.0)


@pytest.mark.parametrize("sigma", [0.7, 1.3, 2.5, 10.0])
def test_margin_rule_of_thumb_is_what_the_docstring_says(sigma):
    # psf_margin's 4 sigma leaves at most 4 Q(4) = 1.3e-4 of the light outside the
    # square (the module docstring's figure): the continuous Gaussian's figure to 1 %,
    # and no more for the sampled Gaussian at the widths used.
    assert abs(4 * norm.sf(4.0) / 1.267e-4 - 1) < 0.01
    assert _outside_square(sigma, psf_margin(sigma)) <= 4 * norm.sf(4.0)


# --- PSF objects ----------------------------------------------------------------------


def test_psf_objects_give_the_functions_otfs_and_margins():
    # The objects are thin wrappers: the same OTF bit for bit, psf_margin's margin, and
    # apply is convolve_psf channel by channel.
    rng = np.random.default_rng(10)
    shape = (30, 37)
    g = GaussianPSF(1.7)
    np.testing.assert_array_equal(g.otf(shape), gaussian_otf(shape, 1.7))
    assert g.margin_px == psf_margin(1.7) == 7 and float(g.width_px) == 1.7
    psf = rng.random((6, 9)) + 0.1
    for centre in ("middle", "centroid"):
        p = ImagePSF(psf, centre)
        np.testing.assert_array_equal(p.otf(shape), image_otf(shape, psf, centre=centre))
        assert p.margin_px == psf_margin(psf, centre=centre)
    img = rng.random((3, *shape))
    for q in (g, ImagePSF(psf)):
        m = q.margin_px
        ref = np.asarray(convolve_psf(img, q.otf(shape), pad=m))
        out = np.asarray(q.apply(np.moveaxis(img, 0, -1)))
        assert out.shape == (shape[0] - 2 * m, shape[1] - 2 * m, 3)
        np.testing.assert_array_equal(np.moveaxis(out, -1, 0), ref)
        np.testing.assert_array_equal(q.apply(img[1]), ref[1])
    with pytest.raises(TypeError, match="abstract"):
        AbstractPSF()


def test_image_psf_width_is_the_rms_radius_about_the_centroid():
    # A sampled Gaussian of sigma 2, off the cutout's centre: the discrete second moment
    # is sigma^2 to within e^(-2 pi^2 sigma^2) (Poisson summation), the cutout at >= 5
    # sigma drops ~e^-12.5 of the light: 1e-4 relative. A point of light has width 0
    # wherever it sits (the centroid, not the middle pixel, is the centre).
    psf = _gaussian_image((25, 27), (11.6, 13.3), 2.0)
    assert abs(float(ImagePSF(psf).width_px) / 2.0 - 1) < 1e-4
    dot = np.zeros((7, 7))
    dot[1, 5] = 3.0
    assert float(ImagePSF(dot).width_px) == 0.0
    # two points 4 pixels apart: rms radius 2, width 2 / sqrt(2)
    two = np.zeros((7, 7))
    two[3, 1] = two[3, 5] = 1.0
    assert abs(float(ImagePSF(two).width_px) - math.sqrt(2.0)) < 1e-12


def test_apply_keeps_the_flux_and_is_differentiable_in_sigma():
    # Light that starts >= 12 pixels (6 sigma) inside the crop stays in it to 1e-8
    # (the Gaussian's mass beyond 6 sigma); a jitted apply is the eager one; the
    # gradient in sigma matches central differences (h = 1e-4: truncation ~h^2 / 6 of
    # the third derivative, round-off eps / h: rtol 1e-7, as for convolve_psf), through
    # a PSF built inside the function and through the object as a pytree.
    import equinox as eqx

    rng = np.random.default_rng(11)
    g = GaussianPSF(2.0)
    m = g.margin_px
    img = np.zeros((60, 64, 3))
    img[m + 12 : -m - 12, m + 12 : -m - 12] = rng.random((60 - 2 * m - 24, 64 - 2 * m - 24, 3))
    out = g.apply(img)
    np.testing.assert_allclose(np.sum(out, axis=(0, 1)), np.sum(img, axis=(0, 1)), rtol=1e-8)
    weight = rng.standard_normal(out.shape)

    @jax.jit
    def loss(s):
        return jnp.sum(weight * GaussianPSF(s, margin_px=m).apply(img))

    s, h = 2.0, 1e-4
    np.testing.assert_allclose(loss(s), np.sum(weight * out), rtol=1e-13)
    fd = (loss(s + h) - loss(s - h)) / (2 * h)
    grad = jax.jit(jax.grad(loss))(s)
    np.testing.assert_allclose(grad, fd, rtol=1e-7)
    of_object = eqx.filter_jit(eqx.filter_grad(lambda q: jnp.sum(weight * q.apply(img))))(g)
    np.testing.assert_allclose(of_object.sigma_px, grad, rtol=1e-12)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: GaussianPSF(0.0), r"sigma_px=0.0 must be finite and > 0"),
        (lambda: GaussianPSF(-1.0), r"sigma_px=-1.0 must be finite and > 0"),
        (lambda: GaussianPSF(float("nan")), r"sigma_px=nan"),
        (lambda: GaussianPSF(float("inf")), r"sigma_px=inf"),
        (lambda: GaussianPSF([1.0, 2.0]), r"one width in pixels; got shape \(2,\)"),
        (lambda: GaussianPSF(1.0, margin_px=-1), r"margin_px=-1 must be >= 0"),
        (lambda: GaussianPSF(1.0, margin_px=2.5), r"margin_px=2.5 must be a whole number"),
        (lambda: ImagePSF(np.zeros((3, 3))), r"total of 0.0"),
        (lambda: ImagePSF(-np.ones((3, 3))), r"total of -9.0"),
        (lambda: ImagePSF(np.array([[1.0, np.inf], [0, 1]])), r"1 NaN or infinite pixels"),
        (lambda: ImagePSF(np.ones(5)), r"shape \(5,\) is not a 2-D PSF image"),
        (lambda: ImagePSF(np.ones((3, 3, 3))), r"shape \(3, 3, 3\) is not a 2-D"),
        (lambda: ImagePSF(np.ones((3, 3)), "peak"), r"centre='peak'"),
        (lambda: GaussianPSF(1.0).apply(np.zeros((8, 8))), r"8 x 8 pixels has no frame"),
        (lambda: GaussianPSF(1.0).apply(np.zeros((20, 20, 3, 1))), r"neither"),
        (lambda: jax.jit(lambda s: GaussianPSF(s).sigma_px)(1.0), r"needs margin_px="),
        (
            lambda: jax.jit(lambda p: ImagePSF(p, "centroid").image)(np.ones((3, 3))),
            r"traced image needs margin_px=",
        ),
    ],
)
def test_psf_objects_refuse_bad_values(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_psf_objects_refuse_complex_widths():
    with pytest.raises(TypeError, match="sigma_px=.* must be real numbers"):
        GaussianPSF(1.0 + 1.0j)


def test_huge_psfs_are_refused_naming_the_size_they_ask_for():
    # A width in arcseconds given as pixels: the margin alone would be 4 million pixels a
    # side, hundreds of TiB of image. Refused when the PSF is built, before any work.
    with pytest.raises(ValueError, match=r"margin of 4,000,000 pixels .* 8,000,001 x 8,000,001 "
                       r"pixels \(698 TiB of float32 RGB\); at most 4,096"):  # fmt: skip
        GaussianPSF(1e6)
    with pytest.raises(ValueError, match=r"margin of 4e\+300 pixels"):
        GaussianPSF(1e300)  # 4 sigma is no int of any use: still a clear message
    with pytest.raises(ValueError, match=r"ImagePSF of 2 x 8,200 pixels needs a margin of 4,100"):
        ImagePSF(np.ones((2, 8200)))
    GaussianPSF(1024.0)  # the largest margin, 4096 pixels, is allowed
    # the frame with its margin is bounded too (2**26 pixels), for apply and render
    wide = GaussianPSF(250.0)  # a margin of 1000 pixels
    with pytest.raises(ValueError, match=r"frame 8,200 x 8,200 pixels \(67,240,000 pixels"):
        wide.padded_shape((6200, 6200))
    assert wide.padded_shape((6000, 6200)) == (8000, 8200)
    cam = jl.Camera(15.0, 1.0, 7000, 7000)
    with pytest.raises(ValueError, match=r"frame 9,000 x 9,000 pixels"):
        jl.render(cam, jl.Checker(), psf=wide)
    with pytest.raises(ValueError, match=r"frame 9,000 x 9,000 pixels"):
        jl.render_array(cam, jl.Checker(), psf=wide)


# --- render with a PSF ----------------------------------------------------------------

_W, _H, _FOV = 40, 32, math.radians(60.0)
_SKY = jl.Checker(12, 6)


def _camera(width, height, fov, **kwargs):
    # yaw: the hole off the image centre, so the mirror-symmetric fast path is not used
    return jl.Camera(15.0, fov, width, height, yaw=0.05, supersample=2, **kwargs)


def _enlarged(margin, fov=_FOV):
    """The camera of the frame with `margin` pixels on every side at the same focal
    length in pixels, from the definition f = (W/2) / tan(FOV/2)."""
    w = _W + 2 * margin
    return _camera(w, _H + 2 * margin, 2.0 * math.atan(math.tan(fov / 2) * w / _W))


def _brute_force(margin, blur):
    """A frame `margin` pixels wider on every side rendered without a PSF, each channel
    blurred by `blur` in float64, cropped to the frame."""
    big = jl.render(jl.Scene(_enlarged(margin), _SKY)).astype(np.float64)
    out = np.stack([blur(big[..., c]) for c in range(3)], axis=-1)
    return out[margin:-margin, margin:-margin], big[margin:-margin, margin:-margin]


def test_render_with_a_gaussian_psf_is_render_blur_crop():
    # The reference: a frame 16 pixels wider on every side (more than the 10-sigma reach
    # of its kernel), blurred by scipy's sampled Gaussian. The render's own margin is
    # 4 sigma = 6 pixels: it may miss, and wrap in, at most 2 x 1.3e-4 of the peak
    # (module docstring); the band-limited and sampled Gaussians differ by their
    # aliasing, ~3 e^(-pi^2 sigma^2 / 2) = 5e-5 at sigma = 1.5; the pixels are float32
    # (6e-8). So 1e-3 of the peak; one pixel of misregistration would be ~0.3.
    sigma = 1.5
    scene = jl.Scene(_camera(_W, _H, _FOV), _SKY)
    got = jl.render(scene, psf=GaussianPSF(sigma))
    assert got.shape == (_H, _W, 3) and got.dtype == np.float32
    ref, sharp = _brute_force(
        16, lambda a: ndimage.gaussian_filter(a, sigma, mode="constant", truncate=10.0)
    )
    peak = ref.max()
    assert peak > 0.5  # a checkerboard in view, not a black frame
    assert np.max(np.abs(got - ref)) < 1e-3 * peak
    assert np.max(np.abs(got - sharp)) > 0.1 * peak  # the blur is there
    assert np.max(np.abs(got[:, 1:] - ref[:, :-1])) > 0.1 * peak  # a shift would show
    # an image PSF of the same sampled Gaussian (13 x 13, its cutout at 4 sigma: light
    # it leaves out ~1.3e-4, counted twice) draws the same image; same margin, 6 pixels
    psf = _gaussian_image((13, 13), (6, 6), sigma)
    assert ImagePSF(psf).margin_px == 6
    np.testing.assert_allclose(jl.render(scene, psf=ImagePSF(psf)), got, rtol=0, atol=1e-3 * peak)


def test_render_with_a_psf_keeps_the_light():
    # A star behind the hole, all of its images well inside a wide frame on a black sky
    # (the 3 pixels along each edge of the frame with the PSF's margin hold < 1e-12 of
    # the light): the blurred frame's total is the sharp frame's (float32 pixels summed,
    # FFT round-off: 1e-5 relative), while its peak drops.
    star = jl.GaussianStar(math.radians(2.0), lon=0.1, lat=0.05)
    fov = math.radians(100.0)
    blurred = jl.render(_camera(_W, _H, fov), star, psf=GaussianPSF(1.5)).astype(np.float64)
    sharp = jl.render(_enlarged(6, fov), star).astype(np.float64)  # the same program
    edges = sharp[:3].sum() + sharp[-3:].sum() + sharp[:, :3].sum() + sharp[:, -3:].sum()
    assert sharp.sum() > 10.0 and edges < 1e-12 * sharp.sum()
    np.testing.assert_allclose(blurred.sum(axis=(0, 1)), sharp.sum(axis=(0, 1)), rtol=1e-5)
    assert blurred.max() < 0.8 * sharp.max()


def test_render_array_with_a_psf_under_jit_is_render():
    # The traced path: the FOV and the PSF's width traced, the enlarged camera built
    # inside the program. The same pixels as render's, to float32 rounding (render's
    # output) of a peak of ~1.
    @jax.jit
    def draw(fov, sigma):
        return jl.render_array(_camera(_W, _H, fov), _SKY, psf=GaussianPSF(sigma, margin_px=6))

    got = draw(_FOV, 1.5)
    assert got.shape == (_H, _W, 3) and got.dtype == jnp.float64
    ref = jl.render(jl.Scene(_camera(_W, _H, _FOV), _SKY), psf=GaussianPSF(1.5))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)


def test_render_of_frames_with_a_psf():
    # A batch of frames is blurred frame by frame: each as rendered alone.
    cams = jl.stack_cameras([_camera(_W, _H, _FOV), _camera(_W, _H, 0.9 * _FOV)])
    psf = GaussianPSF(1.5)
    frames = jl.render(cams, _SKY, psf=psf)
    assert frames.shape == (2, _H, _W, 3)
    one = jl.render(_camera(_W, _H, 0.9 * _FOV), _SKY, psf=psf)
    np.testing.assert_allclose(frames[1], one, rtol=0, atol=1e-6)


def test_render_psf_argument_checks():
    cam = _camera(_W, _H, _FOV)
    with pytest.raises(ValueError, match="psf must be a PSF .* got float"):
        jl.render(cam, _SKY, psf=1.5)
    with pytest.raises(ValueError, match="pass plan=None"):
        jl.render_array(cam, _SKY, psf=GaussianPSF(1.0), plan=jl.plan(jl.Scene(cam, _SKY)))
