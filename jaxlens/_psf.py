"""Point-spread functions: the optical transfer function (OTF) of a Gaussian PSF or of a
PSF image, and the FFT convolution of a model image rendered with a margin.

An OTF here is the discrete Fourier transform of the PSF, normalised to unit sum, with
the PSF's centre at pixel (0, 0), in the layout of `jnp.fft.rfft2`: shape
`(H, W // 2 + 1)` for an array of `H` rows and `W` columns; row frequencies
$v$ = `fftfreq(H)`, column frequencies $u$ = `rfftfreq(W)`, in cycles per pixel.
Multiplying an image's `rfft2` by it and transforming back convolves the image with the
PSF without moving it.

Why a margin. The FFT convolves circularly: light the PSF spreads past one edge of the
array comes back in at the opposite edge. `convolve_psf` therefore takes the model rendered
on a frame enlarged by `pad` pixels on every side, `(H + 2 pad, W + 2 pad)`, and returns
the central `(H, W)` crop. A crop pixel is more than `pad` pixels from every pixel that
wraps around, and every pixel of the scene within `pad` pixels of it was rendered, so
the crop is the linear convolution of the scene except for the light the PSF carries
farther than `pad` pixels: at most twice the PSF's mass outside the square of half-side
`pad` times the brightest model pixel (the light missed beyond the margin, and the same
amount wrapped in). For a Gaussian of width $\\sigma$ that mass is
$1 - (1 - 2Q(\\mathrm{pad}/\\sigma))^2 \\approx 4 Q(\\mathrm{pad}/\\sigma)$, $Q$ the normal
tail: 1.3e-4 at `pad` = $4\\sigma$ (`psf_margin`), 1.1e-6 at $5\\sigma$, 4e-9 at $6\\sigma$;
in practice much less, since the light at the edges is spread over a whole row.
"""

import math
from typing import Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from ._util import as_float, concrete

_CENTRES = ("middle", "centroid")


def _shape2(shape) -> tuple[int, int]:
    """`shape` as two positive Python ints (rows, columns), or a ValueError."""
    try:
        h, w = (int(n) for n in shape)
        ok = h >= 1 and w >= 1 and all(int(n) == n for n in shape)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"shape={shape!r} must be two positive integers (rows, columns)")
    return h, w


def _check_centre(centre) -> None:
    if centre not in _CENTRES:
        raise ValueError(f"centre={centre!r} must be one of {', '.join(map(repr, _CENTRES))}")


def gaussian_otf(shape: tuple[int, int], sigma_px: ArrayLike) -> Float[Array, "H W2"]:
    """The OTF of a normalised circular Gaussian PSF, computed in the frequency domain:
    $\\exp(-2\\pi^2\\sigma^2(u^2 + v^2))$, $u, v$ in cycles per pixel.

    No kernel is built, so none is truncated. This is the Fourier transform of the
    continuous Gaussian at the array's frequencies, i.e. the band-limited Gaussian; the
    sampled Gaussian (`scipy.ndimage.gaussian_filter`'s kernel) differs from it by the
    aliased terms, at most $2 e^{-\\pi^2\\sigma^2/2}$ in the OTF: 7e-3 at $\\sigma$ = 1
    pixel, 3e-5 at 1.5, 5e-9 at 2. Below about one pixel the PSF is undersampled and no
    convolution of pixel values reproduces the continuous blur exactly.

    Real-valued (the PSF is symmetric about its centre). Works under `jit`, `vmap` and
    `grad` (forward and reverse) with respect to `sigma_px`; float32 in, float32 out.

    **Arguments:**

    - `shape`: `(rows, columns)` of the array to convolve, margin included, in pixels
        (static).
    - `sigma_px`: the Gaussian's standard deviation, in pixels, finite and >= 0 (0 is
        no blur). A scalar; may be traced. A concrete bad value raises `ValueError`, a
        traced one fails at run time (`eqx.error_if`).

    **Returns:** the OTF, real, shape `(rows, columns // 2 + 1)`, in the float dtype of
    `sigma_px` (the default float dtype for Python numbers).
    """
    h, w = _shape2(shape)
    sigma = as_float(sigma_px)
    if sigma.ndim != 0:
        raise ValueError(f"sigma_px must be a scalar (pixels); got shape {sigma.shape}")
    value = concrete(sigma_px)
    if value is not None:
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"sigma_px={float(value)!r} must be finite and >= 0 (pixels)")
    else:
        sigma = eqx.error_if(
            sigma, ~(jnp.isfinite(sigma) & (sigma >= 0)), "sigma_px must be finite and >= 0"
        )
    return _gaussian_otf((h, w), sigma)


def _gaussian_otf(shape: tuple[int, int], sigma) -> Array:
    """`gaussian_otf` of a width `sigma` (a float array, pixels) known to be valid: no
    checks (a traced one's is a host callback)."""
    h, w = shape
    q2 = np.fft.fftfreq(h)[:, None] ** 2 + np.fft.rfftfreq(w)[None, :] ** 2
    return jnp.exp((-2.0 * math.pi**2) * jnp.asarray(q2, sigma.dtype) * (sigma * sigma))


def _shift_factor(n: int, d, dtype, *, half: bool) -> Array:
    """Fourier factor that moves the content at offset `d` (pixels, along an axis of
    `n` pixels) to offset 0: $e^{2\\pi i f d}$, with $\\cos(\\pi d)$ at the Nyquist
    frequency of an even `n` (the real part: the same factor for $f = \\pm 1/2$, so a
    real PSF stays real). `half`: the `rfftfreq` layout, else `fftfreq`."""
    f = jnp.asarray(np.fft.rfftfreq(n) if half else np.fft.fftfreq(n), dtype)
    d = jnp.asarray(d, dtype)
    factor = jnp.exp((2j * math.pi) * f * d)
    if n % 2 == 0:
        factor = factor.at[n // 2].set(jnp.cos(math.pi * d).astype(factor.dtype))
    return factor


def _centroid(p, axis):
    """Flux centroid of the normalised PSF `p` along `axis` (0: rows, 1: columns), as a
    pixel index (pixel centres at 0, 1, ...)."""
    n = p.shape[axis]
    idx = jnp.arange(n, dtype=p.dtype)
    return jnp.sum(idx * jnp.sum(p, axis=1 - axis))


def image_otf(
    shape: tuple[int, int],
    psf: ArrayLike,
    *,
    centre: Literal["middle", "centroid"] = "middle",
) -> Complex[Array, "H W2"]:
    """The OTF of a PSF given as an image: normalised to unit sum, its centre placed at
    pixel (0, 0), so that convolving by it does not shift the image.

    The centre, along each axis of `n` pixels (pixel centres at indices 0 .. n - 1):

    - `centre="middle"` (the default): the geometric centre of the PSF image, index
        $(n - 1)/2$. For odd `n` that is the middle pixel, `n // 2`, moved to the
        origin by a whole-pixel roll: exact. For even `n` it is the corner between
        pixels `n/2 - 1` and `n/2`, half a pixel off the grid: the PSF is moved by the
        half pixel in Fourier space (band-limited interpolation), so a PSF symmetric
        about its geometric centre blurs a point source symmetrically about the source's
        own pixel. That interpolation is exact for a well-sampled PSF (a core of
        sigma >= 2 pixels, FWHM >= 4.7: the centroid then stays put to 1e-9 pixel) that
        falls to ~0 at the edges of its image; an undersampled one (sigma ~ 1 pixel) has
        light above the Nyquist frequency, which no sub-pixel move keeps intact (its
        centroid moves by ~1e-4 pixel), and one cut off sharply rings (tails of about
        the edge value divided by $\\pi$ times the distance, in pixels). Prefer
        odd-sized PSF images where there is a choice.
    - `centre="centroid"`: the PSF's flux centroid (any size), moved to the origin the
        same way: the convolution then keeps the flux centroid of any image where it
        was, also for a star cutout that is not centred.

    Works under `jit`, `vmap` and `grad` with respect to the PSF's values.

    **Arguments:**

    - `shape`: `(rows, columns)` of the array to convolve, margin included, in pixels
        (static).
    - `psf`: the PSF image, `(h, w)` with `h <= rows`, `w <= columns`, any parity, in
        any units (it is normalised); negative pixels are allowed, a total <= 0 is not.
    - `centre`: `"middle"` or `"centroid"`, as above.

    **Returns:** the OTF, complex, shape `(rows, columns // 2 + 1)`, complex64 for a
    float32 PSF. Raises `ValueError` for a PSF that is not 2-D, is larger than `shape`,
    has NaN or infinite pixels, is all zeros or has a negative total (for a traced PSF
    the value checks fail at run time, `eqx.error_if`).
    """
    h, w = _shape2(shape)
    _check_centre(centre)
    p = as_float(psf)
    if p.ndim != 2 or min(p.shape) < 1:
        raise ValueError(f"psf of shape {tuple(p.shape)} is not a 2-D image (h, w)")
    ph, pw = p.shape
    if ph > h or pw > w:
        raise ValueError(
            f"psf image of {ph}x{pw} pixels (rows x columns) is bigger than the image of "
            f"{h}x{w} it convolves; crop the PSF or enlarge the margin"
        )
    value = concrete(psf)
    if value is not None:
        value = np.asarray(value, np.float64)
        if not np.all(np.isfinite(value)):
            raise ValueError(f"psf has {np.sum(~np.isfinite(value))} NaN or infinite pixels")
        if not np.any(value):
            raise ValueError("psf is all zeros: it has no light to spread")
        total = float(np.sum(value))
        if not total > 0:
            raise ValueError(f"psf has a total of {total!r}; a PSF's total must be > 0")
    else:
        bad = ~jnp.all(jnp.isfinite(p)) | ~(jnp.sum(p) > 0)
        p = eqx.error_if(p, bad, "psf has NaN/infinite pixels or a total <= 0")
    p = p / jnp.sum(p)
    ry, rx = (ph - 1) // 2, (pw - 1) // 2
    if centre == "middle":
        cy, cx = 0.5 * (ph - 1), 0.5 * (pw - 1)
    else:
        cy, cx = _centroid(p, 0), _centroid(p, 1)
    full = jnp.zeros((h, w), p.dtype).at[:ph, :pw].set(p)
    otf = jnp.fft.rfft2(jnp.roll(full, (-ry, -rx), axis=(0, 1)))
    if centre == "centroid" or ph % 2 == 0:
        otf = otf * _shift_factor(h, cy - ry, p.dtype, half=False)[:, None]
    if centre == "centroid" or pw % 2 == 0:
        otf = otf * _shift_factor(w, cx - rx, p.dtype, half=True)[None, :]
    return otf


def convolve_psf(
    image: Float[ArrayLike, "*batch Hp Wp"],
    otf: ArrayLike,
    *,
    pad: int,
) -> Float[Array, "*batch H W"]:
    """Convolve a model rendered with a margin by a PSF, by FFT, and crop the margin.

    The model is rendered on the frame enlarged by `pad` pixels on every side; the FFT
    convolution is circular, so light spread past one edge wraps around to the other,
    and the margin keeps that wrapped light (and the missing light from beyond the
    margin) off the returned frame as long as `pad` is at least the PSF's radius:
    `psf_margin` gives ceil(4 sigma) for a Gaussian, half the size for a PSF image (see
    the module's docstring for the error bound).

    Works under `jit`, `vmap` and `grad` (with respect to the image and the OTF).

    **Arguments:**

    - `image`: the model, `(..., H + 2 pad, W + 2 pad)`, real; leading axes are batch
        axes (for a channels-last `(H, W, C)` image, move the channels first).
    - `otf`: from `gaussian_otf` or `image_otf` for the shape `(H + 2 pad, W + 2 pad)`,
        i.e. `(..., H + 2 pad, (W + 2 pad) // 2 + 1)`; broadcast against the batch axes.
    - `pad`: the margin, in pixels, >= 0 (static).

    **Returns:** the central `(..., H, W)` crop of the convolved model, in the image's
    float dtype (an OTF of another precision is converted to it).
    """
    img = as_float(image)
    if img.ndim < 2:
        raise ValueError(f"image of shape {tuple(img.shape)} is not (..., rows, columns)")
    try:
        p = int(pad)
        ok = p == pad and p >= 0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"pad={pad!r} must be an integer >= 0 (pixels)")
    hp, wp = img.shape[-2:]
    if 2 * p >= min(hp, wp):
        raise ValueError(
            f"pad={p} leaves nothing of an image of {hp}x{wp} pixels: the frame is the "
            "image less pad pixels on every side"
        )
    otf = jnp.asarray(otf)
    want = (hp, wp // 2 + 1)
    if otf.ndim < 2 or tuple(otf.shape[-2:]) != want:
        raise ValueError(
            f"otf of shape {tuple(otf.shape)} does not fit an image of {hp}x{wp} pixels "
            f"(it needs (..., {want[0]}, {want[1]})): make the OTF for the shape of the "
            "image with its margin"
        )
    if jnp.iscomplexobj(otf):
        otf = otf.astype(jnp.result_type(img.dtype, jnp.complex64))
    else:
        otf = otf.astype(img.dtype)
    out = jnp.fft.irfft2(jnp.fft.rfft2(img) * otf, s=(hp, wp))
    return out[..., p : hp - p, p : wp - p]


def psf_margin(
    psf: ArrayLike,
    *,
    nsigma: float = 4.0,
    centre: Literal["middle", "centroid"] = "middle",
) -> int:
    """The margin, in pixels, to render a model with before `convolve_psf`: the PSF's
    radius. Host-side (it fixes array shapes), so `psf` must be concrete.

    **Arguments:**

    - `psf`: a Gaussian's width sigma, in pixels (a number), or a PSF image `(h, w)`.
    - `nsigma`: for a Gaussian, the radius in units of sigma; 4 leaves at most about
        1.3e-4 of the PSF's light outside the margin's square (module docstring).
    - `centre`: for a PSF image, the centre convention of `image_otf`.

    **Returns:** `ceil(nsigma * sigma)` for a Gaussian; for a PSF image with
    `centre="middle"` half its larger side, `max(h, w) // 2` (the distance from the
    centre to the farthest pixel centre, rounded up), and with `centre="centroid"` the
    distance from the centroid to the farthest pixel centre along either axis, rounded
    up.
    """
    value = concrete(psf)
    if value is None:
        raise ValueError("psf_margin needs a concrete psf (it fixes array shapes), not a tracer")
    value = np.asarray(value, np.float64)
    if value.ndim == 0:
        sigma = float(value)
        if not (math.isfinite(sigma) and sigma >= 0):
            raise ValueError(f"sigma_px={sigma!r} must be finite and >= 0 (pixels)")
        if not (math.isfinite(nsigma) and nsigma > 0):
            raise ValueError(f"nsigma={nsigma!r} must be finite and > 0")
        return int(math.ceil(nsigma * sigma))
    if value.ndim != 2 or min(value.shape) < 1:
        raise ValueError(f"psf of shape {value.shape} is neither a width nor a 2-D image")
    _check_centre(centre)
    if centre == "middle":
        return max(value.shape) // 2
    total = float(np.sum(value))
    if not (np.all(np.isfinite(value)) and total > 0):
        raise ValueError("psf has NaN/infinite pixels or a total <= 0")
    radius = 0.0
    for axis in (0, 1):
        n = value.shape[axis]
        c = float(np.sum(np.arange(n) * np.sum(value, axis=1 - axis)) / total)
        radius = max(radius, c, n - 1 - c)
    return int(math.ceil(radius - 1e-9))
