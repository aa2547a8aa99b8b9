"""Blackbody colours (temperatures in K), and their frequency shift.

The CIE 1931 2-degree colour matching functions as the analytic multi-lobe Gaussian
fit of Wyman, Sloan & Shirley (JCGT 2, 2013), integrated against Planck's law on a
1 nm grid (360-830 nm) into a table uniform in $\\ln T$, converted to linear sRGB
(D65). A blackbody seen with frequency ratio $g$ is, by the invariance of
$I_\\nu/\\nu^3$, exactly a blackbody of temperature $gT$ (`"spectral"`); the
`"bolometric"` mode keeps the colour and scales the intensity by $g^4$.
"""

import functools
import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._units import plain

# Wyman, Sloan & Shirley (2013), "Simple analytic approximations to the CIE XYZ
# colour matching functions", multi-lobe fit: (weight, mu, sigma below mu, above), nm.
_CMF_LOBES = (
    ((1.056, 599.8, 37.9, 31.0), (0.362, 442.0, 16.0, 26.7), (-0.065, 501.1, 20.4, 26.2)),
    ((0.821, 568.8, 46.9, 40.5), (0.286, 530.9, 16.3, 31.1)),
    ((1.217, 437.0, 11.8, 36.0), (0.681, 459.0, 26.0, 13.8)),
)
# XYZ -> linear sRGB (IEC 61966-2-1, D65 white).
XYZ_TO_SRGB = np.array(
    [
        [3.2404542, -1.5371385, -0.4985314],
        [-0.9692660, 1.8760108, 0.0415560],
        [0.0556434, -0.2040259, 1.0572252],
    ]
)
C2 = 1.438776877e7  # second radiation constant hc/k, nm K (CODATA 2018)
_LAMBDA = np.arange(360.0, 831.0, 1.0)  # nm
_LOG_T0, _LOG_T1, _NT = math.log(300.0), math.log(1.0e6), 4096  # table range (K)


def cie_cmf(wavelength: ArrayLike, xp=jnp) -> Float[Array, "... 3"]:
    """CIE 1931 2-degree colour matching functions $(\\bar x, \\bar y, \\bar z)$ at
    `wavelength` (nm), from the Wyman-Sloan-Shirley multi-lobe fit (`xp`: `jnp` or
    `np`). **Returns:** `(..., 3)`, dimensionless ($\\bar y$ peaks at 1 near 555 nm)."""
    wavelength = plain(wavelength, "wavelength", "a wavelength in nm")
    lam = xp.asarray(wavelength)
    out = []
    for lobes in _CMF_LOBES:
        total = 0.0
        for w, mu, s1, s2 in lobes:
            t = (lam - mu) / xp.where(lam < mu, s1, s2)
            total = total + w * xp.exp(-0.5 * t * t)
        out.append(total)
    return xp.stack(out, axis=-1)


def planck(wavelength: ArrayLike, temperature: ArrayLike, xp=jnp):
    """Planck's law up to the constant $2hc^2$: $\\lambda^{-5}/(e^{c_2/\\lambda T} - 1)$,
    `wavelength` in nm, `temperature` in K (spectral radiance per unit wavelength,
    in units of $2hc^2$ nm$^{-5}$)."""
    wavelength = plain(wavelength, "wavelength", "a wavelength in nm")
    temperature = plain(temperature, "temperature", "a temperature in K")
    lam = xp.asarray(wavelength)
    return lam**-5.0 / xp.expm1(C2 / (lam * temperature))


def blackbody_xyz_quadrature(temperature) -> np.ndarray:
    """CIE XYZ of a blackbody at `temperature` (K, NumPy array) by direct quadrature
    of `planck` x `cie_cmf` on the 1 nm grid (trapezoid; the reference the table is
    made from). **Returns:** `(..., 3)` in units of $2hc^2$ nm$^{-4}$."""
    temperature = plain(temperature, "temperature", "a temperature in K")
    t = np.asarray(temperature, np.float64)[..., None]
    spec = planck(_LAMBDA, t, xp=np)[..., None] * cie_cmf(_LAMBDA, xp=np)
    return np.trapezoid(spec, _LAMBDA, axis=-2)


def _build_table():
    log_t = np.linspace(_LOG_T0, _LOG_T1, _NT)
    xyz = blackbody_xyz_quadrature(np.exp(log_t))
    y = xyz[:, 1]
    rgb = xyz @ XYZ_TO_SRGB.T / y[:, None]
    # Normalise luminance to 1 at 6500 K.
    ref = blackbody_xyz_quadrature(np.array([6500.0]))[0, 1]
    return np.concatenate([np.log(y / ref)[:, None], rgb], axis=1)  # (NT, 4)


_DLOG_T = (_LOG_T1 - _LOG_T0) / (_NT - 1)


@functools.cache
def _table():
    """The table and the end slopes of ln Y in ln T (for linear extrapolation beyond
    it), made on first use: most scenes have no blackbody, and the quadrature would
    lengthen every import of the renderer."""
    table = _build_table()
    lo = float((table[1, 0] - table[0, 0]) / _DLOG_T)  # Python floats: weak types
    hi = float((table[-1, 0] - table[-2, 0]) / _DLOG_T)
    return table, lo, hi


def _lookup(log_t):
    """Linear interpolation of the table at $\\ln T$: `(log Y, r, g, b)` `(..., 4)`.
    Chromaticity is held at the table's ends; $\\ln Y$ continues with the end slopes
    (Rayleigh-Jeans, $Y \\propto T$, above $10^6$ K)."""
    values, slope_lo, slope_hi = _table()
    table = jnp.asarray(values, log_t.dtype)
    s = (log_t - _LOG_T0) / _DLOG_T
    i = jnp.clip(jnp.floor(s), 0, _NT - 2)
    f = jnp.clip(s - i, 0.0, 1.0)
    i = i.astype(jnp.int32)
    lo, hi = table[i], table[i + 1]
    val = lo + f[..., None] * (hi - lo)
    below = table[0, 0] + slope_lo * (log_t - _LOG_T0)
    above = table[-1, 0] + slope_hi * (log_t - _LOG_T1)
    log_y = jnp.where(s < 0, below, jnp.where(s > _NT - 1, above, val[..., 0]))
    return log_y, val[..., 1:]


def _log_temperature(temperature):
    t = jnp.asarray(temperature, jnp.result_type(float, temperature))
    return jnp.log(t)


def blackbody_color(temperature: ArrayLike) -> Float[Array, "... 3"]:
    """Linear sRGB colour of a blackbody at `temperature` (K), normalised to luminance
    $Y = 1$. Colours outside the sRGB gamut (below ~1900 K) keep their small negative
    channels; clip for display."""
    temperature = plain(temperature, "temperature", "a temperature in K")
    return _lookup(_log_temperature(temperature))[1]


def blackbody_luminance(temperature: ArrayLike) -> Float[Array, "..."]:
    """Luminance $Y$ of a blackbody at `temperature` (K), relative to one at 6500 K."""
    temperature = plain(temperature, "temperature", "a temperature in K")
    return jnp.exp(_lookup(_log_temperature(temperature))[0])


def blackbody_rgb(temperature: ArrayLike) -> Float[Array, "... 3"]:
    """Linear sRGB of a blackbody at `temperature` (K): colour times luminance, in
    units of the luminance of a 6500 K blackbody."""
    temperature = plain(temperature, "temperature", "a temperature in K")
    log_y, rgb = _lookup(_log_temperature(temperature))
    return jnp.exp(log_y)[..., None] * rgb


def shifted_blackbody(temperature: ArrayLike, g: ArrayLike, mode: str = "spectral"):
    """Linear sRGB of a blackbody of rest temperature `temperature` (K) and unit rest
    luminance, seen with frequency ratio $g = \\nu_{obs}/\\nu_{emit}$.

    `mode="spectral"`: $I_\\nu/\\nu^3$ is invariant, so the observed spectrum is a
    blackbody of temperature $gT$: colour of $gT$, luminance $Y(gT)/Y(T)$.
    `mode="bolometric"`: colour of $T$, intensity $\\times g^4$.

    **Returns:** `(..., 3)` (broadcast of `temperature` and `g`).
    """
    temperature = plain(temperature, "temperature", "a temperature in K")
    log_t = _log_temperature(temperature)
    g = jnp.asarray(g, log_t.dtype)
    if mode == "bolometric":
        _, rgb = _lookup(log_t)
        return (g**4)[..., None] * rgb
    if mode != "spectral":
        raise ValueError(f"mode={mode!r} must be 'bolometric' or 'spectral'")
    log_y0, _ = _lookup(log_t)
    log_y, rgb = _lookup(log_t + jnp.log(g))
    return jnp.exp(log_y - log_y0)[..., None] * rgb
