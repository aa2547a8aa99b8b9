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

The objects. `GaussianPSF(sigma_px)` and `ImagePSF(image)` (subclasses of `AbstractPSF`)
carry a PSF with its margin: `otf(shape)`, `margin_px`, `width_px` and `apply(image)`
(blur an image rendered on the margin, crop it). `render(scene, psf=...)` renders the
frame with the margin and applies them, so the renderer draws what the fit compares
with an image. A margin over `MAX_MARGIN_PX` (4096 pixels) or a frame with its margin
over `MAX_PADDED_PIXELS` (2**26 pixels) is refused, naming the size asked for: a width
in arcseconds taken for pixels would otherwise ask for terabytes.
"""

import abc
import math
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from ._messages import real_array
from ._units import plain
from ._util import as_float, concrete, has_tracer

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
    sigma_px = plain(sigma_px, "sigma_px", "a width in pixels")
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
    return gaussian_otf_unchecked((h, w), sigma)


def gaussian_otf_unchecked(shape: tuple[int, int], sigma) -> Array:
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


# --- PSF objects ----------------------------------------------------------------------

# The largest margin a PSF may ask for, in pixels on every side: 4 sigma of a Gaussian
# of 1024 pixels. A wider PSF is a mistake of units (arcseconds or degrees given as
# pixels), and its margin alone would make a frame of >= 8193 x 8193 pixels.
MAX_MARGIN_PX = 4096
# The largest frame a PSF is applied to, margin included: 2**26 pixels (8192 x 8192),
# 512 MiB a channel in float64 and as much again for its Fourier transform.
MAX_PADDED_PIXELS = 2**26


def _count(n: float) -> str:
    """A count of pixels as a message shows it: 8,193 (whole, with commas) up to 1e15,
    then 4e+300."""
    return f"{n:,.0f}" if n < 1e15 else f"{n:.3g}"


def _size(pixels: float) -> str:
    """The memory of `pixels` float32 RGB pixels (a render's output), in words."""
    b = 12.0 * float(pixels)
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB"):
        if b < 1024 or unit == "EiB":
            return f"{b:.0f} {unit}" if unit == "bytes" else f"{b:.3g} {unit}"
        b /= 1024
    raise AssertionError("unreachable")


def _margin_of(sigma: float) -> int | float:
    """`psf_margin`'s margin of a Gaussian of width `sigma` (pixels), ceil(4 sigma), or
    the float 4 sigma where that is beyond `MAX_MARGIN_PX` (for the message only: an
    int of 4e300 pixels is no use, and 4 sigma may overflow to inf)."""
    return psf_margin(sigma) if 4.0 * sigma <= MAX_MARGIN_PX else 4.0 * sigma


def _check_margin(who: str, margin, hint: str) -> int:
    """`margin` (pixels) as an int in [0, MAX_MARGIN_PX], or a ValueError naming the
    frame it would ask for (a float margin only ever comes too large, from
    `_margin_of`); `hint` ends the message."""
    if isinstance(margin, float) and margin > MAX_MARGIN_PX:
        m = margin
    elif isinstance(margin, bool) or not isinstance(margin, int | np.integer):
        raise ValueError(f"{who}: margin_px={margin!r} must be a whole number of pixels >= 0")
    else:
        m = int(margin)
    if m < 0:
        raise ValueError(f"{who}: margin_px={m} must be >= 0 (pixels)")
    if m > MAX_MARGIN_PX:
        side = 2.0 * m + 1.0
        raise ValueError(
            f"{who} needs a margin of {_count(m)} pixels on every side of the frame: even "
            f"a 1-pixel image would be rendered on {_count(side)} x {_count(side)} pixels "
            f"({_size(side * side)} of float32 RGB); at most {MAX_MARGIN_PX:,} pixels{hint}"
        )
    return m


class AbstractPSF(eqx.Module):
    """A point-spread function on the pixel grid: what blurs a rendered image into what
    a detector records. A PSF is applied to an image rendered with a margin of
    `margin_px` pixels on every side (`render(scene, psf=...)` does that), by FFT, and
    the central crop is returned (module docstring: why the margin, and its error).

    The interface: `otf(shape)` (the optical transfer function, `rfft2` layout),
    `margin_px` (static: the margin a render needs), `width_px` (the Gaussian-equivalent
    width) and `apply(image)`; `padded_shape(shape)` gives the frame a render draws.
    Concrete classes: `GaussianPSF`, `ImagePSF`.
    """

    margin_px: eqx.AbstractVar[int]

    @abc.abstractmethod
    def otf(self, shape: tuple[int, int]) -> Array:
        """The OTF for an array of `shape` = `(rows, columns)` pixels, margin included:
        the PSF's discrete Fourier transform, unit sum, centred at pixel (0, 0), shape
        `(rows, columns // 2 + 1)` (`jnp.fft.rfft2`'s layout)."""

    @property
    @abc.abstractmethod
    def width_px(self) -> Float[Array, ""]:
        """The Gaussian-equivalent width, in pixels: the standard deviation along one
        axis of a Gaussian of the same second moment."""

    def padded_shape(self, shape: tuple[int, int]) -> tuple[int, int]:
        """The frame to render for an image of `shape` = `(rows, columns)` pixels: the
        image with `margin_px` pixels on every side. Raises `ValueError` when that frame
        has more than `MAX_PADDED_PIXELS` = 2**26 pixels (8192 x 8192), naming it."""
        h, w = _shape2(shape)
        m = self.margin_px
        hp, wp = h + 2 * m, w + 2 * m
        if hp * wp > MAX_PADDED_PIXELS:
            raise ValueError(
                f"{type(self).__name__}'s margin of {m:,} pixels makes the {h:,} x {w:,} "
                f"frame {hp:,} x {wp:,} pixels ({hp * wp:,} pixels, {_size(hp * wp)} of "
                f"float32 RGB); at most {MAX_PADDED_PIXELS:,} pixels (8192 x 8192) are "
                "blurred: render a smaller frame or use a narrower PSF"
            )
        return hp, wp

    def apply(self, image: Float[ArrayLike, "Hp Wp *C"]) -> Float[Array, "H W *C"]:
        """Blur an image rendered with this PSF's margin, and crop the margin.

        Works under `jit`, `vmap` and `grad` (with respect to the image and the PSF's
        array fields: `sigma_px`, the PSF image's pixels); the margin is static.

        **Arguments:**

        - `image`: linear radiance, `(H + 2 m, W + 2 m)` or `(H + 2 m, W + 2 m, C)`
            (channels last, each blurred alone), `m` = `margin_px`; at most
            `MAX_PADDED_PIXELS` pixels.

        **Returns:** the central `(H, W)` or `(H, W, C)` crop of the blurred image, in
        the image's float dtype (an integer image in the default float dtype). The
        total is kept, but for the light that crosses the crop's edge.
        """
        img = as_float(image)
        if img.ndim not in (2, 3):
            raise ValueError(
                f"image of shape {tuple(img.shape)} is neither (rows, columns) nor "
                "(rows, columns, channels)"
            )
        hp, wp = img.shape[:2]
        m = self.margin_px
        if min(hp, wp) <= 2 * m:
            raise ValueError(
                f"image of {hp} x {wp} pixels has no frame inside {type(self).__name__}'s "
                f"margin of {m} pixels on every side: render it on the frame with its "
                "margin (padded_shape)"
            )
        self.padded_shape((hp - 2 * m, wp - 2 * m))
        otf = self.otf((hp, wp))
        if img.ndim == 2:
            return convolve_psf(img, otf, pad=m)
        return jnp.moveaxis(convolve_psf(jnp.moveaxis(img, -1, 0), otf, pad=m), 0, -1)


class GaussianPSF(AbstractPSF):
    """A circular Gaussian PSF of standard deviation `sigma_px` pixels (the OTF of
    `gaussian_otf`: the band-limited Gaussian, no kernel to truncate).

    **Fields:**

    - `sigma_px`: the standard deviation, in pixels (FWHM = 2.3548 sigma_px), finite
        and > 0. A scalar array: it may be traced and differentiated (`jax.grad` of a
        loss of `apply` or `render_array(..., psf=)`).
    - `margin_px` (static): the margin a render needs, in pixels on every side:
        `ceil(4 sigma_px)` by default (`psf_margin`: at most ~1.3e-4 of the peak is
        lost past it or wrapped in), at most `MAX_MARGIN_PX` = 4096.

    **Arguments:** `sigma_px` as above; `margin_px`: the margin (default from a known
    `sigma_px`; needed when `sigma_px` is traced, since it fixes array shapes). A bad
    width or margin is a `ValueError` naming it (a traced width < 0 or NaN fails at run
    time in `otf`).
    """

    sigma_px: Float[Array, ""]
    margin_px: int = eqx.field(static=True)

    def __init__(self, sigma_px: ArrayLike, *, margin_px: int | None = None):
        sigma = as_float(real_array("sigma_px", sigma_px))
        if sigma.ndim != 0:
            raise ValueError(f"sigma_px must be one width in pixels; got shape {sigma.shape}")
        value = concrete(sigma)
        if value is not None and not (np.isfinite(value) and value > 0):
            raise ValueError(
                f"sigma_px={float(value)!r} must be finite and > 0 (pixels; for no blur, psf=None)"
            )
        who = "GaussianPSF"
        if margin_px is None:
            if value is None:
                raise ValueError(
                    "GaussianPSF of a traced sigma_px needs margin_px= (pixels): the margin "
                    "fixes array shapes"
                )
            who = f"GaussianPSF(sigma_px={float(value)!r})"
            margin_px = _margin_of(float(value))
        hint = " (sigma_px <= 1024). Is the width in pixels, not arcseconds or degrees?"
        self.margin_px = _check_margin(who, margin_px, hint)
        self.sigma_px = sigma

    @property
    def width_px(self) -> Float[Array, ""]:
        """`sigma_px` itself (pixels)."""
        return self.sigma_px

    def otf(self, shape: tuple[int, int]) -> Float[Array, "H W2"]:
        """`gaussian_otf(shape, sigma_px)`: real, `(rows, columns // 2 + 1)`."""
        return gaussian_otf(shape, self.sigma_px)


class ImagePSF(AbstractPSF):
    """A PSF given as an image (a star's cutout, a model of the optics), normalised to
    unit sum and centred by `centre` (the OTF of `image_otf`).

    **Fields:**

    - `image`: the PSF, `(h, w)` pixels of the image it blurs, any units (it is
        normalised), finite, with a total > 0 (negative pixels are allowed). An array:
        it may be traced and differentiated.
    - `centre` (static): `"middle"` (the image's geometric centre, index $(n - 1)/2$
        along each axis; prefer odd sizes) or `"centroid"` (its flux centroid), as
        `image_otf`.
    - `margin_px` (static): the margin a render needs, in pixels on every side: the
        distance from the centre to the image's farthest pixel, rounded up
        (`psf_margin`): all of the PSF's light lands in the crop. At most
        `MAX_MARGIN_PX` = 4096.

    **Arguments:** `image`, `centre` as above; `margin_px`: the margin (default as
    above; needed for `centre="centroid"` with a traced image). A bad image, centre or
    margin is a `ValueError` naming it.
    """

    image: Float[Array, "h w"]
    centre: str = eqx.field(static=True)
    margin_px: int = eqx.field(static=True)

    def __init__(
        self,
        image: ArrayLike,
        centre: Literal["middle", "centroid"] = "middle",
        *,
        margin_px: int | None = None,
    ):
        _check_centre(centre)
        if not isinstance(image, jax.Array | np.ndarray) and has_tracer(image):
            image = jnp.asarray(image)  # a list holding tracers
        p = as_float(real_array("image", image))
        if p.ndim != 2 or min(p.shape) < 1:
            raise ValueError(f"image of shape {tuple(p.shape)} is not a 2-D PSF image (h, w)")
        value = concrete(p)
        if value is not None:
            bad = ~np.isfinite(value)
            if np.any(bad):
                raise ValueError(
                    f"image has {int(np.sum(bad))} NaN or infinite pixels (the first at "
                    f"{tuple(int(i) for i in np.argwhere(bad)[0])}); a PSF image must be finite"
                )
            total = float(np.sum(value, dtype=np.float64))
            if not total > 0:
                raise ValueError(
                    f"image has a total of {total!r}; a PSF image's total must be > 0 "
                    "(it is normalised to 1)"
                )
        who = f"ImagePSF of {p.shape[0]:,} x {p.shape[1]:,} pixels"
        if margin_px is None:
            if centre == "middle":
                margin_px = max(p.shape) // 2
            elif value is None:
                raise ValueError(
                    'ImagePSF(centre="centroid") of a traced image needs margin_px= '
                    "(pixels): the margin fixes array shapes"
                )
            else:
                margin_px = psf_margin(value, centre="centroid")
        hint = ": crop the PSF image to where its light is"
        self.margin_px = _check_margin(who, margin_px, hint)
        self.centre = centre
        self.image = p

    @property
    def width_px(self) -> Float[Array, ""]:
        """The image's rms distance from its flux centroid over $\\sqrt 2$, in pixels
        (negative pixels counted as 0): a Gaussian's sigma for a Gaussian image."""
        p = jnp.clip(self.image, 0.0, None)
        total = jnp.sum(p)
        y = jnp.arange(p.shape[0], dtype=p.dtype)[:, None]
        x = jnp.arange(p.shape[1], dtype=p.dtype)[None, :]
        cy, cx = jnp.sum(p * y) / total, jnp.sum(p * x) / total
        return jnp.sqrt(jnp.sum(p * ((y - cy) ** 2 + (x - cx) ** 2)) / (2.0 * total))

    def otf(self, shape: tuple[int, int]) -> Complex[Array, "H W2"]:
        """`image_otf(shape, image, centre=centre)`: complex,
        `(rows, columns // 2 + 1)`."""
        return image_otf(shape, self.image, centre=self.centre)
