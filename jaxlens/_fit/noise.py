"""Noise: the expected value of a clipped noisy pixel (integer images store values
clipped to [0, 1]) and its slope, and the per-pixel noise level of an image."""

import abc
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.ndimage

from .._compile import program
from .pixels import pixel_centres


def _positive_part(u, s):
    """$E[(u + n)_+]$ for $n \\sim N(0, s^2)$: $u\\,\\Phi(u/s) + s\\,\\varphi(u/s)$."""
    z = u / s
    return u * jax.scipy.special.ndtr(z) + s * jnp.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)


def clipped_mean(m, lo, hi, noise):
    """Expected value of `clip(m + n, lo, hi)` with Gaussian noise $n$ of standard
    deviation `noise`: what an integer image stores where the noise crosses 0 or 1.

    $E = m + E[(lo - m - n)_+] - E[(m + n - hi)_+]$; `lo = -inf`, `hi = inf` give `m`.
    Broadcasts; works under `jit`, `vmap` and `grad`.

    **Arguments:** `m`: the noise-free pixel value; `lo`, `hi`: the stored range (0 and
    1 for an integer image normalised to [0, 1]); `noise`: the noise's standard
    deviation, in the units of `m`.

    **Returns:** the expected stored value, in the units of `m`.
    """
    s = jnp.maximum(noise, 1e-30)
    low = jnp.where(
        jnp.isfinite(lo), _positive_part(jnp.where(jnp.isfinite(lo), lo, 0.0) - m, s), 0.0
    )
    high = jnp.where(
        jnp.isfinite(hi), _positive_part(m - jnp.where(jnp.isfinite(hi), hi, 0.0), s), 0.0
    )
    return m + low - high


def clipped_slope(m, lo, hi, noise):
    """Derivative of `clipped_mean` with respect to `m`:
    $1 - \\Phi((lo - m)/s) - \\Phi((m - hi)/s)$."""
    s = jnp.maximum(noise, 1e-30)
    low = jnp.where(jnp.isfinite(lo), jax.scipy.special.ndtr((jnp.nan_to_num(lo) - m) / s), 0.0)
    high = jnp.where(jnp.isfinite(hi), jax.scipy.special.ndtr((m - jnp.nan_to_num(hi)) / s), 0.0)
    return 1.0 - low - high


# The relative standard deviation of `noise_level` on white noise is this over the
# square root of the second differences it takes (measured: 1.47-1.65 on 48 x 64 to
# 240 x 320 images of Gaussian noise, 200 draws each).
_LEVEL_SPREAD = 1.7


def second_differences(img) -> np.ndarray:
    """The finite second differences of an image along its rows and its columns, flat."""
    img = np.asarray(img)
    parts = [img[:, 2:] - 2.0 * img[:, 1:-1] + img[:, :-2], img[2:] - 2.0 * img[1:-1] + img[:-2]]
    d = np.concatenate([p.ravel() for p in parts])
    return d[np.isfinite(d)]


def _mad_level(d) -> float:
    """The white-noise level behind second differences `d`: their median absolute
    deviation as a normal's standard deviation, over sqrt(6)."""
    if d.size < 8:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(6.0))


# The most pixels the noise estimate reads: a larger image is read in bands of rows
# spread over its height (white noise is the same everywhere; the temporaries stay
# those of this many pixels).
_NOISE_PIXELS = 1 << 22
_BAND_ROWS = 256


def _flat_differences(img) -> np.ndarray:
    """The second differences (rows and columns, finite) where the image is flat: not
    where the image smoothed by a Gaussian of 1.5 px curves by more than 3 of its own
    robust standard deviations, nor within 2 px of such a place. The ring's and the
    arcs' curvature, which the median absolute deviation of every difference takes for
    noise (10-25 % too much on a ring 1-3 px wide over 12 % of the pixels), is left
    out; on white noise the estimate moves by 0.2 %. An image of more than
    `_NOISE_PIXELS` is read in bands of `_BAND_ROWS` rows spread over its height."""
    h, w = np.shape(img)
    bands = max(1, min(-(-h // _BAND_ROWS), _NOISE_PIXELS // max(_BAND_ROWS * w, 1)))
    if bands * _BAND_ROWS >= h:
        starts = [0]
        rows = h
    else:
        starts = np.linspace(0, h - _BAND_ROWS, bands).astype(int)
        rows = _BAND_ROWS
    fill_value = float(np.nanmedian(img[:: max(1, h // 512), :: max(1, w // 512)]))
    kept = []
    for r0 in starts:
        band = np.asarray(img[r0 : r0 + rows], np.float64)
        fill = np.where(np.isfinite(band), band, fill_value)
        smooth = scipy.ndimage.gaussian_filter(fill, 1.5, mode="nearest")
        del fill
        for axis in (1, 0):
            curve = np.diff(smooth, 2, axis=axis)
            spread = 1.4826 * np.median(np.abs(curve - np.median(curve)))
            flat = ~scipy.ndimage.binary_dilation(np.abs(curve) > 3.0 * spread, iterations=2)
            del curve
            d = np.diff(band, 2, axis=axis)[flat]
            kept.append(d[np.isfinite(d)])
    return np.concatenate(kept)


def noise_estimate(img) -> tuple[float, float]:
    """`(level, spread)`: the per-pixel noise of an image (its units) from the median
    absolute deviation of its second differences where it is flat (`_flat_differences`;
    NaN pixels left out), scaled to a white Gaussian noise's standard deviation, and
    that level's relative standard deviation on white noise. An image too small (or
    nowhere flat) is judged by all its differences; 0 for fewer than 8."""
    d = _flat_differences(img) if min(np.shape(img)) >= 16 else np.empty(0)
    if d.size < 64:
        d = second_differences(img)
    return _mad_level(d), _LEVEL_SPREAD / math.sqrt(max(d.size, 1))


def noise_level(img) -> float:
    """Per-pixel noise of an image (its units): `noise_estimate`'s level."""
    return noise_estimate(img)[0]


def noise_level_spread(img) -> float:
    """The relative standard deviation of `noise_level(img)` on white noise."""
    return noise_estimate(img)[1]


def white_noise_found(img) -> tuple[bool, float]:
    """Whether the image carries pixel noise: the robust noise estimates from second and
    from fourth differences along rows (each scaled to white noise) agree for pixel
    noise (ratio ~1; 0.76 for noise averaged over two pixels), while smooth structure
    sets the second differences of a noiseless image and barely reaches the fourth
    (a flat image: both 0), and round-off (below 1e-6 of the largest value) is no
    measurement's noise. **Returns:** `(found, ratio)`, found when the ratio is within
    [0.5, 2] and the noise above round-off."""
    d2 = img[:, 2:] - 2.0 * img[:, 1:-1] + img[:, :-2]
    d4 = d2[:, 2:] - 2.0 * d2[:, 1:-1] + d2[:, :-2]
    if d4.size < 8:
        return True, math.nan

    def mad(d):
        return float(np.median(np.abs(d - np.median(d))))

    s2, s4 = mad(d2) / math.sqrt(6.0), mad(d4) / math.sqrt(70.0)
    ratio = s4 / s2 if s2 > 0 else 0.0
    above_roundoff = s2 > 1e-6 * float(np.max(np.abs(img)))
    return bool(above_roundoff and 0.5 <= ratio <= 2.0), ratio


def clipping_bounds(img):
    """Bounds at which the stored values were clipped: 0 (1) when at least 0.2 % of the
    pixels sit exactly there, else -inf (inf). NaN pixels are not counted as either."""
    lo = 0.0 if np.nanmin(img) == 0.0 and np.mean(img == 0.0) > 2e-3 else -math.inf
    hi = 1.0 if np.nanmax(img) == 1.0 and np.mean(img == 1.0) > 2e-3 else math.inf
    return lo, hi


def noise_clipped(img, prof, lo, hi) -> float:
    """Per-pixel noise (`prof`: the image's radial profile, `starts._Profile`).
    Unclipped images: the robust second-difference estimate. Clipped
    ones: from the sky well outside the ring (flat there), as the 84th minus the 50th
    percentile, which clipping below the median leaves intact; inside the shadow (flat
    at 0) when the sky outside is too small."""
    if not (math.isfinite(lo) or math.isfinite(hi)):
        return prof.noise
    x, y = pixel_centres(*img.shape)
    rho = np.hypot(x[None, :], y[:, None])
    for region in (
        rho > prof.ring_radius + 8.0 * prof.ring_width + 3.0,
        rho < 0.5 * np.nan_to_num(prof.inner_half, nan=0.0),
    ):
        v = img[region]
        v = v[np.isfinite(v)]
        if v.size >= 200:
            q50, q84 = np.percentile(v, [50.0, 84.13])
            if q84 > q50 and q50 < hi:
                return float(q84 - q50)
    return prof.noise


def gain_estimate(img, valid) -> float:
    """Counts per data unit of an image with Poisson noise, from its mean-variance
    relation (variance = mean / gain): the median of mean / variance over the 8 x 8
    tiles with signal and no invalid pixel (the variance from `noise_level`)."""
    h, w = img.shape
    ratios = []
    for r in range(0, h - 7, 8):
        for c in range(0, w - 7, 8):
            if not valid[r : r + 8, c : c + 8].all():
                continue
            t = img[r : r + 8, c : c + 8]
            var, mean = _mad_level(second_differences(t)) ** 2, float(t.mean())
            if var > 0 and mean > 0:
                ratios.append(mean / var)
    if not ratios:
        raise ValueError("cannot estimate the gain (no tile with signal): give gain=")
    return float(np.median(ratios))


# How far a fit's residuals may exceed the noise before the model is said not to
# describe the image: in standard deviations of the statistic (5: once in 3.5 million
# fits of a model that does describe it).
GOODNESS_SIGMAS = 5.0


class AbstractNoise(eqx.Module):
    """A noise model: how an observed pixel scatters about the model's value.

    A model gives the residuals a least-squares fit minimises (`residuals`: standard
    normal where the model describes the data), its estimate from an image where its
    level is not given (`estimated`), and the goodness-of-fit statistic of a fit's
    residuals (`excess`). A new noise model is a subclass of this one."""

    name: eqx.AbstractClassVar[str]
    statistic: eqx.AbstractClassVar[str]  # what its residuals are called in a message

    @abc.abstractmethod
    def estimated(self, img, valid, *, profile=None, level=None) -> "AbstractNoise":
        """This model with what it does not give estimated from the image `img` (data
        units, NaN where not `valid`): the form `residuals` takes. `profile`: the
        image's radial profile (`starts.radial_profile`), where the estimate needs the
        flat sky; `level`: `noise_estimate(img)` where the caller has it."""

    @abc.abstractmethod
    def residuals(self, model, data, weight):
        """The residuals (noise units) of `model` (the noise-free value of each
        compared bin) against `data` (each bin's mean), `weight` the square root of the
        pixels in a bin (0: left out). Traceable."""

    def residual_slope(self, model, data, weight) -> np.ndarray:
        """The derivative of each bin's residual with respect to its model value (noise
        units per data unit; `residuals`' arguments), exact (forward mode), float64."""
        with jax.enable_x64(True):
            args = jax.tree.map(lambda a: np.asarray(a, np.float64), (model, data, weight))
            return np.asarray(_residual_slope(self, *args))

    @property
    @abc.abstractmethod
    def level_given(self) -> bool:
        """Whether the noise's level was given, rather than estimated from the image."""

    @abc.abstractmethod
    def spread(self) -> float:
        """The relative standard deviation of the estimated level's variance (0 when
        given): what the residuals' sum of squares is uncertain by beyond its own
        scatter."""

    def error_scale(self, chi2_dof: float) -> float:
        """The factor on the curvature's covariance: 1 where the noise's level is known
        (given, or implied by the model as Poisson counts are)."""
        return 1.0

    def levels(self) -> tuple[float, float]:
        """`(sigma, gain)` for a fit's record: the Gaussian level (data units) and the
        Poisson gain (counts per data unit), NaN where the model has none."""
        return math.nan, math.nan

    @property
    def checked_for_white_noise(self) -> bool:
        """Whether the image must show pixel noise for the errors to mean a noise (a level
        estimated from the image, as opposed to given or implied by counts)."""
        return False

    @property
    def reestimated(self) -> bool:
        """Whether a fit re-estimates the level from its first pass's residuals."""
        return False

    def excess(self, chi2: float, dof: int) -> float:
        """How many standard deviations the residuals' sum of squares `chi2` over `dof`
        degrees of freedom lies above its expectation under this model: its own
        scatter, $\\sqrt{2/\\mathrm{dof}}$, and the estimated level's uncertainty
        (`spread`) in quadrature. Above `GOODNESS_SIGMAS` the model does not describe
        the image."""
        dof = max(int(dof), 1)
        return (chi2 / dof - 1.0) / math.sqrt(2.0 / dof + self.spread() ** 2)


@program(profile="legacy_fusion_o0_side")
def _residual_slope(noise, model, data, weight):
    # The residuals are bin by bin: their Jacobian is diagonal, one forward pass.
    def rows(m):
        return noise.residuals(m, data, weight)

    return jax.jvp(rows, (model,), (jnp.ones_like(model),))[1]


class Gaussian(AbstractNoise):
    """Additive Gaussian noise of standard deviation `sigma` (data units, one original
    pixel), `None` to estimate it from the image; values stored clipped to the format's
    range (`lo`, `hi`: found in the image, `clipping_bounds`) are modelled as such
    (`clipped_mean`).

    Fields after `estimated`: `sigma`, `lo`, `hi` (arrays), `scale` (the residuals'
    unit: `sigma`, at least 1e-12 of the image's scale), `rel` (`noise_level_spread`;
    0: the level was given)."""

    name = "gaussian"
    statistic = "residuals"
    sigma: Any = None
    lo: Any = -math.inf
    hi: Any = math.inf
    scale: Any = None
    rel: Any = 0.0

    def __check_init__(self):
        # A level given by the caller (the estimated form, with its `scale`, may be 0: a
        # noiseless image, which the fit flags).
        s = self.sigma
        given = self.scale is None and not isinstance(s, jax.Array)
        if s is not None and given and not (0.0 < float(s) < math.inf):
            raise ValueError(f"noise sigma={s!r} must be positive and finite (data units)")

    @property
    def level_given(self) -> bool:
        return self.sigma is not None and float(self.rel) == 0.0

    def estimated(self, img, valid, *, profile=None, level=None) -> "Gaussian":
        """(`level`: `noise_estimate(img)` where the caller has it already.)"""
        lo, hi = clipping_bounds(img)
        given = self.level_given
        if given:
            sigma, rel = float(self.sigma), 0.0
        else:
            sigma, rel = noise_estimate(img) if level is None else level
            if profile is not None and (math.isfinite(lo) or math.isfinite(hi)):
                sigma = noise_clipped(img, profile, lo, hi)
        return self.with_level(sigma, lo, hi, float(np.nanmax(np.abs(img))), rel)

    def with_level(self, sigma, lo, hi, data_scale, rel) -> "Gaussian":
        """The estimated form: level `sigma`, clipping `lo`, `hi`, the image's largest
        absolute value `data_scale`, the level's relative spread `rel` (0: given)."""
        scale = max(float(sigma), 1e-12 * max(float(data_scale), 1e-300))
        f = np.float64
        return Gaussian(f(sigma), f(lo), f(hi), f(scale), f(rel))

    def residuals(self, model, data, weight):
        return weight * (clipped_mean(model, self.lo, self.hi, self.sigma) - data) / self.scale

    def error_scale(self, chi2_dof: float) -> float:
        # A level estimated from the image: the residuals set the errors' scale.
        return 1.0 if self.level_given else float(chi2_dof)

    def levels(self) -> tuple[float, float]:
        return float(self.sigma), math.nan

    @property
    def checked_for_white_noise(self) -> bool:
        return not self.level_given

    @property
    def reestimated(self) -> bool:
        # Clipped values: the level from the flat sky, refined from the residuals.
        clipped = bool(np.isfinite(self.lo) or np.isfinite(self.hi))
        return not self.level_given and clipped

    def spread(self) -> float:
        return 0.0 if self.level_given else 2.0 * float(self.rel)


class Poisson(AbstractNoise):
    """Counts: an observed value times `gain` (counts per data unit) is Poisson about
    the model's; `gain=None` estimates it from the image (`gain_estimate`). The
    residuals are deviance residuals, whose squares sum to twice the negative
    log-likelihood less its minimum, so least squares is the maximum-likelihood fit."""

    name = "poisson"
    statistic = "deviance"
    gain: Any = None
    rel: Any = 0.0

    def __check_init__(self):
        g = self.gain
        if g is not None and not isinstance(g, jax.Array) and not (0.0 < float(g) < math.inf):
            raise ValueError(f"gain={g!r} must be positive and finite (counts per data unit)")

    @property
    def level_given(self) -> bool:
        return self.gain is not None and float(self.rel) == 0.0

    def estimated(self, img, valid, *, profile=None, level=None) -> "Poisson":
        if self.level_given:
            return Poisson(np.float64(self.gain), np.float64(0.0))
        # The gain from tiles: as uncertain as the per-tile variances' median.
        tiles = max((img.shape[0] // 8) * (img.shape[1] // 8), 1)
        rel = _LEVEL_SPREAD / math.sqrt(64.0 * tiles)
        return Poisson(np.float64(gain_estimate(img, valid)), np.float64(rel))

    def levels(self) -> tuple[float, float]:
        return math.nan, float(self.gain)

    def residuals(self, model, data, weight):
        gain = self.gain
        mu = jnp.maximum(gain * weight**2 * model, 1e-12)
        y = gain * weight**2 * data
        q = y / mu
        d = q - 1.0
        small = jnp.abs(d) < 1e-3
        qs = jnp.where(small, 2.0, q)
        ratio = jnp.where(
            small,
            1.0 - d / 3.0 + d * d / 6.0,
            2.0 * (qs * jnp.log(jnp.maximum(qs, 1e-300)) - qs + 1.0) / (qs - 1.0) ** 2,
        )
        r = (y - mu) / jnp.sqrt(mu) * jnp.sqrt(jnp.maximum(ratio, 0.0))
        return jnp.where(weight > 0, r, 0.0)

    def spread(self) -> float:
        return 0.0 if self.level_given else 2.0 * float(self.rel)


def as_noise(noise, gain=None) -> AbstractNoise:
    """A noise model from what `fit` accepts: an `AbstractNoise`; `"gaussian"` or
    `None` (Gaussian, level estimated); a number (Gaussian of that standard deviation,
    data units); `"poisson"` (with `gain`, or estimated)."""
    if isinstance(noise, AbstractNoise):
        return noise
    if noise is None or (isinstance(noise, str) and noise == "gaussian"):
        return Gaussian()
    if isinstance(noise, str) and noise == "poisson":
        return Poisson(gain)
    if isinstance(noise, (int, float, np.floating, np.integer)) and not isinstance(noise, bool):
        return Gaussian(float(noise))
    raise ValueError(f"noise={noise!r} must be 'gaussian', 'poisson', a noise level (data "
                     "units) or a noise model (jaxlens.Gaussian, jaxlens.Poisson)")  # fmt: skip
