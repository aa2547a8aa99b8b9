"""Noise: the expected value of a clipped noisy pixel (integer images store values
clipped to [0, 1]) and its slope, and the per-pixel noise level of an image."""

import math

import jax
import jax.numpy as jnp
import numpy as np


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


def noise_level(img):
    """Per-pixel noise from the median absolute second difference (robust to the ring)."""
    d = img[:, 2:] - 2.0 * img[:, 1:-1] + img[:, :-2]
    if d.size < 8:
        return float(np.std(img))
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(6.0))


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
    pixels sit exactly there, else -inf (inf)."""
    lo = 0.0 if img.min() == 0.0 and np.mean(img == 0.0) > 2e-3 else -math.inf
    hi = 1.0 if img.max() == 1.0 and np.mean(img == 1.0) > 2e-3 else math.inf
    return lo, hi


def noise_clipped(img, prof, lo, hi) -> float:
    """Per-pixel noise (`prof`: the image's radial profile, `starts._Profile`).
    Unclipped images: the robust second-difference estimate. Clipped
    ones: from the sky well outside the ring (flat there), as the 84th minus the 50th
    percentile, which clipping below the median leaves intact; inside the shadow (flat
    at 0) when the sky outside is too small."""
    if not (math.isfinite(lo) or math.isfinite(hi)):
        return prof.noise
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w]
    rho = np.hypot(xx + 0.5 - 0.5 * w, 0.5 * h - (yy + 0.5))
    for region in (
        rho > prof.ring_radius + 8.0 * prof.ring_width + 3.0,
        rho < 0.5 * np.nan_to_num(prof.inner_half, nan=0.0),
    ):
        v = img[region]
        if v.size >= 200:
            q50, q84 = np.percentile(v, [50.0, 84.13])
            if q84 > q50 and q50 < hi:
                return float(q84 - q50)
    return prof.noise
