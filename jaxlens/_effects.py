"""Effects of the observer's motion and of frequency shifts (units of R_S = 1).

Conventions. A *look direction* is the unit vector along which a camera pixel looks
(opposite to the photon's momentum), in the camera frame of `_camera` (the hole on
$+z$). A moving camera's pixels give look directions in its own rest frame; the ray
map is that of the static observer at the same event, so each direction is boosted
to the static frame first (`aberrate`), traced there, and the light's frequency is
multiplied by the Doppler factor of the boost.

- Static observer at $r = D$, light from infinity: $g_s = \\nu_{obs}/\\nu_\\infty =
  1/\\sqrt{1 - 1/D}$ (the photon's conserved energy over the local $\\sqrt{-g_{tt}}$).
- Circular geodesic at $r = D > 1.5$: $\\Omega^2 = M/r^3 = 1/(2D^3)$ ($M = 1/2$); the
  static observer measures the speed $v = D\\Omega/\\sqrt{1 - 1/D} = 1/\\sqrt{2(D - 1)}$
  (tangential; $v \\to 1$ at the photon sphere). Then $u^t = \\gamma/\\sqrt{1 - 1/D}
  = 1/\\sqrt{1 - 3/(2D)}$, the standard result.
- Radial fall from rest at infinity: $E = (1 - 1/r)\\,u^t = 1$, so the static observer
  measures $\\gamma = 1/\\sqrt{1 - 1/D}$, $v = \\sqrt{1/D}$, directed at the hole.
- Aberration: a pixel looking at angle $a'$ from the velocity (moving frame) sees
  light that a static observer receives from angle $a$,
  $\\cos a = (\\cos a' - v)/(1 - v\\cos a')$; the Doppler factor is
  $\\nu_{moving}/\\nu_{static} = 1/(\\gamma (1 - v \\cos a'))$.

Blackbody colours: the CIE 1931 2-degree colour matching functions as the analytic
multi-lobe Gaussian fit of Wyman, Sloan & Shirley (JCGT 2, 2013), integrated against
Planck's law on a 1 nm grid (360-830 nm) into a table uniform in $\\log T$, converted
to linear sRGB (D65). A blackbody seen with frequency ratio $g$ is, by the invariance
of $I_\\nu/\\nu^3$, exactly a blackbody of temperature $gT$ (`"spectral"`); the
`"bolometric"` mode keeps the colour and scales the intensity by $g^4$.
"""

import abc
import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._schema import Key, anything, register
from ._sky import AbstractSky, SkySum, angular_distance, direction_from_angles
from ._util import as_float as _farray

# ---------------------------------------------------------------------- observers


def static_blueshift(distance: ArrayLike) -> Float[Array, "..."]:
    """Frequency ratio $\\nu_{obs}/\\nu_\\infty = 1/\\sqrt{1 - 1/D}$ of light from
    infinity seen by a static observer at radius `distance` $D > 1$ (units of R_S)."""
    d = jnp.asarray(distance, jnp.result_type(float, distance))
    return jnp.sqrt(d / (d - 1.0))


def orbital_speed(distance: ArrayLike) -> Float[Array, "..."]:
    """Speed of a circular geodesic orbit at radius $D > 1.5$ (units of R_S), as a
    static observer there measures it: $v = 1/\\sqrt{2(D - 1)}$ (units of c)."""
    d = jnp.asarray(distance, jnp.result_type(float, distance))
    return jnp.sqrt(0.5 / (d - 1.0))


def infall_speed(distance: ArrayLike) -> Float[Array, "..."]:
    """Speed at radius $D$ (units of R_S) of a fall from rest at infinity, measured by
    the static observer there: $v = \\sqrt{1/D}$ (units of c)."""
    d = jnp.asarray(distance, jnp.result_type(float, distance))
    return jnp.sqrt(1.0 / d)


def lorentz_factor(v: ArrayLike) -> Float[Array, "..."]:
    """$\\gamma = 1/\\sqrt{(1 - v)(1 + v)}$ for a speed $0 \\le v < 1$ (units of c)."""
    v = jnp.asarray(v, jnp.result_type(float, v))
    return 1.0 / jnp.sqrt((1.0 - v) * (1.0 + v))


def aberrate_cos(cos_a: ArrayLike, v: ArrayLike) -> Float[Array, "..."]:
    """Static-frame $\\cos a = (\\cos a' - v)/(1 - v \\cos a')$ of a look direction at
    angle $a'$ from the velocity in the frame moving at speed `v` (units of c)."""
    return (cos_a - v) / (1.0 - v * cos_a)


def aberrate(n: Float[Array, "... 3"], v: ArrayLike, e: Float[Array, "3"]) -> Float[Array, "... 3"]:
    """Boost look directions from the frame moving at speed `v` along the unit vector
    `e` to the static frame (the exact Lorentz aberration, as 3-vectors).

    With $p = n\\cdot e$: $n_s = e\\,(p - v)/(1 - vp) + (n - p e)\\sqrt{1 - v^2}/(1 - vp)$,
    a unit vector for unit $n$ (`aberrate(aberrate(n, v, e), -v, e) == n`).

    **Arguments:** `n (..., 3)` unit look directions (moving frame), `v` speed (units of
    c, broadcasts with `n[..., 0]`), `e (3,)` unit direction of the motion.

    **Returns:** static-frame unit look directions `(..., 3)`.
    """
    e = jnp.asarray(e, n.dtype)
    v = jnp.asarray(v, n.dtype)
    p = n[..., 0] * e[0] + n[..., 1] * e[1] + n[..., 2] * e[2]
    inv = 1.0 / (1.0 - v * p)
    along = ((p - v) * inv)[..., None]
    across = (jnp.sqrt((1.0 - v) * (1.0 + v)) * inv)[..., None]
    return along * e + across * (n - p[..., None] * e)


def doppler_factor(cos_a: ArrayLike, v: ArrayLike) -> Float[Array, "..."]:
    """$\\nu_{moving}/\\nu_{static} = \\sqrt{1 - v^2}/(1 - v\\cos a')$ for light seen along
    a look direction at angle $a'$ from the velocity (moving frame; `v` in c)."""
    return jnp.sqrt((1.0 - v) * (1.0 + v)) / (1.0 - v * cos_a)


def frequency_ratio(distance: ArrayLike, cos_a: ArrayLike = 1.0, v: ArrayLike = 0.0):
    """$g = \\nu_{obs}/\\nu_\\infty$ of light from infinity seen at radius `distance`
    (units of R_S) by an observer moving at speed `v` (c; 0: static) relative to the
    static observer, looking at angle $a'$ from its velocity (`cos_a`, moving frame):
    $g = \\frac{1}{\\sqrt{1-1/D}}\\,\\frac{\\sqrt{1-v^2}}{1 - v\\cos a'}$."""
    return static_blueshift(distance) * doppler_factor(cos_a, v)


class AbstractMotion(eqx.Module):
    """How the camera moves relative to the static observer at its position.

    `radial` (class constant): the motion is along the line to the hole, so the
    aberration keeps the ray map axisymmetric about the hole's direction.
    """

    radial: eqx.AbstractClassVar[bool]

    @abc.abstractmethod
    def speed(self, distance):
        """Speed relative to the static observer (units of c) at `distance` (R_S)."""

    @abc.abstractmethod
    def direction(self, dtype) -> Float[Array, "3"]:
        """Unit vector of the motion, camera frame (the hole on $+z$)."""

    @abc.abstractmethod
    def check_distance(self, distance) -> None:
        """ValueError where the motion is impossible at a concrete `distance` (R_S)."""


class CircularOrbit(AbstractMotion):
    """A camera on a circular geodesic orbit at $r = D > 1.5$ (units of R_S).

    Speed $v = 1/\\sqrt{2(D - 1)}$ in the static frame (`orbital_speed`), tangential.
    **Fields:** `angle`: direction of motion across the line of sight, radians from
    the camera frame's $+x$ toward $+y$ (0: moving to the right of an unrotated
    view; an increasing `Camera.azimuth` is the motion at `angle` $= \\pi$).
    """

    radial: ClassVar[bool] = False
    angle: Float[Array, ""]

    def __init__(self, angle: ArrayLike = 0.0):
        self.angle = jnp.asarray(angle, jnp.result_type(float, angle))

    def speed(self, distance):
        return orbital_speed(distance)

    def direction(self, dtype):
        a = self.angle.astype(dtype)
        return jnp.stack([jnp.cos(a), jnp.sin(a), jnp.zeros_like(a)])

    def check_distance(self, distance) -> None:
        d = np.asarray(distance)
        if np.any(~(d > 1.5)):
            raise ValueError(
                f"distance={float(np.min(d))!r}: a circular orbit needs D > 1.5 (units of "
                "R_S; the photon sphere, where its speed reaches c)"
            )


class RadialInfall(AbstractMotion):
    """A camera falling radially from rest at infinity: speed $\\sqrt{1/D}$ toward the
    hole (camera frame $+z$), measured by the static observer at $D$ (units of R_S)."""

    radial: ClassVar[bool] = True

    def speed(self, distance):
        return infall_speed(distance)

    def direction(self, dtype):
        return jnp.asarray([0.0, 0.0, 1.0], dtype)

    def check_distance(self, distance) -> None:
        pass  # a fall from rest at infinity reaches every D > 1 below c


@register("motion", "orbit", {
    "angle_deg": Key("float", 0.0, anything, "a finite number (degrees)"),
})  # fmt: skip
def _orbit_from_table(t, base) -> CircularOrbit:
    return CircularOrbit(math.radians(t["angle_deg"]))


@register("motion", "infall", {})
def _infall_from_table(t, base) -> RadialInfall:
    return RadialInfall()


class Redshift(eqx.Module):
    """Frequency shift of all light (sky and disk) reaching the camera.

    **Fields:** `mode` (static): `"bolometric"` (colour kept, intensity $\\times g^4$)
    or `"spectral"` ($I_\\nu/\\nu^3$ invariance: a blackbody of temperature $T$ is seen
    as one of $gT$; skies without a spectrum are taken as flat, $I_\\nu$ = const per
    channel, and scaled by $g^3$).
    """

    mode: str = eqx.field(static=True, default="spectral")

    def __check_init__(self):
        if self.mode not in ("bolometric", "spectral"):
            raise ValueError(f"mode={self.mode!r} must be 'bolometric' or 'spectral'")


_MODES = ("spectral", "bolometric")


@register("redshift", "redshift", {
    "mode": Key("str", "spectral", lambda v: v in _MODES, " | ".join(_MODES)),
})  # fmt: skip
def _redshift_from_table(t, base) -> Redshift:
    return Redshift(t["mode"])


# ---------------------------------------------------------------------- colour

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
    lam = xp.asarray(wavelength)
    return lam**-5.0 / xp.expm1(C2 / (lam * temperature))


def blackbody_xyz_quadrature(temperature) -> np.ndarray:
    """CIE XYZ of a blackbody at `temperature` (K, NumPy array) by direct quadrature
    of `planck` x `cie_cmf` on the 1 nm grid (trapezoid; the reference the table is
    made from). **Returns:** `(..., 3)` in units of $2hc^2$ nm$^{-4}$."""
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


_TABLE = _build_table()
_DLOG_T = (_LOG_T1 - _LOG_T0) / (_NT - 1)
# End slopes of ln Y in ln T, for linear extrapolation beyond the table.
_SLOPE_LO = (_TABLE[1, 0] - _TABLE[0, 0]) / _DLOG_T
_SLOPE_HI = (_TABLE[-1, 0] - _TABLE[-2, 0]) / _DLOG_T


def _lookup(log_t):
    """Linear interpolation of the table at $\\ln T$: `(log Y, r, g, b)` `(..., 4)`.
    Chromaticity is held at the table's ends; $\\ln Y$ continues with the end slopes
    (Rayleigh-Jeans, $Y \\propto T$, above $10^6$ K)."""
    table = jnp.asarray(_TABLE, log_t.dtype)
    s = (log_t - _LOG_T0) / _DLOG_T
    i = jnp.clip(jnp.floor(s), 0, _NT - 2)
    f = jnp.clip(s - i, 0.0, 1.0)
    i = i.astype(jnp.int32)
    lo, hi = table[i], table[i + 1]
    val = lo + f[..., None] * (hi - lo)
    below = table[0, 0] + _SLOPE_LO * (log_t - _LOG_T0)
    above = table[-1, 0] + _SLOPE_HI * (log_t - _LOG_T1)
    log_y = jnp.where(s < 0, below, jnp.where(s > _NT - 1, above, val[..., 0]))
    return log_y, val[..., 1:]


def _log_temperature(temperature):
    t = jnp.asarray(temperature, jnp.result_type(float, temperature))
    return jnp.log(t)


def blackbody_color(temperature: ArrayLike) -> Float[Array, "... 3"]:
    """Linear sRGB colour of a blackbody at `temperature` (K), normalised to luminance
    $Y = 1$. Colours outside the sRGB gamut (below ~1900 K) keep their small negative
    channels; clip for display."""
    return _lookup(_log_temperature(temperature))[1]


def blackbody_luminance(temperature: ArrayLike) -> Float[Array, "..."]:
    """Luminance $Y$ of a blackbody at `temperature` (K), relative to one at 6500 K."""
    return jnp.exp(_lookup(_log_temperature(temperature))[0])


def blackbody_rgb(temperature: ArrayLike) -> Float[Array, "... 3"]:
    """Linear sRGB of a blackbody at `temperature` (K): colour times luminance, in
    units of the luminance of a 6500 K blackbody."""
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


# ---------------------------------------------------------------------- skies


class BlackbodyStars(AbstractSky):
    """Gaussian stars with blackbody colours: star $i$ has radiance
    $A_i\\, e^{-d^2/2\\sigma_i^2}$ (angular distance $d$) times the colour of its
    temperature, luminance $A_i$ at rest.

    **Fields:** `directions (N, 3)` (world unit vectors), `sigma (N,)` (radians),
    `brightness (N,)` (peak luminance at rest), `temperature (N,)` (K).
    """

    directions: Float[Array, "N 3"]
    sigma: Float[Array, " N"]
    brightness: Float[Array, " N"]
    temperature: Float[Array, " N"]

    def __init__(self, directions, sigma, brightness=1.0, temperature=5800.0):
        d = _farray(directions)
        if d.ndim != 2 or d.shape[-1] != 3 or d.shape[0] < 1:
            raise ValueError(f"directions has shape {d.shape}; expected (N, 3) with N >= 1")
        n = d.shape[0]
        self.directions = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
        self.sigma = jnp.broadcast_to(_farray(sigma), (n,))
        self.brightness = jnp.broadcast_to(_farray(brightness), (n,))
        self.temperature = jnp.broadcast_to(_farray(temperature), (n,))

    def __check_init__(self):
        for name in ("sigma", "temperature"):
            try:
                v = np.asarray(getattr(self, name))
            except Exception:  # traced
                continue
            if not np.all(np.isfinite(v) & (v > 0)):
                unit = "radians" if name == "sigma" else "K"
                raise ValueError(f"{name}={v.tolist()!r} must be finite and > 0 ({unit})")

    @classmethod
    def from_angles(cls, lon, lat, sigma, brightness=1.0, temperature=5800.0):
        """Stars at longitudes `lon`, latitudes `lat` (radians; `direction_from_angles`)."""
        d = direction_from_angles(jnp.atleast_1d(_farray(lon)), jnp.atleast_1d(_farray(lat)))
        return cls(d, sigma, brightness, temperature)

    @classmethod
    def random(cls, count: int, *, seed: int = 0, sigma=0.004, brightness=(0.2, 2.0),
               temperature=(2500.0, 30000.0)):  # fmt: skip
        """`count` stars uniform on the sphere; brightness and temperature (K)
        log-uniform in the given ranges; `sigma` in radians."""
        rng = np.random.default_rng(seed)
        d = rng.normal(size=(count, 3))
        b = np.exp(rng.uniform(*np.log(brightness), count))
        t = np.exp(rng.uniform(*np.log(temperature), count))
        return cls(d, sigma, b, t)

    def _sum(self, n, g, mode):
        dt = n.dtype
        flat = n.reshape(-1, 3)
        gf = None if g is None else jnp.broadcast_to(jnp.asarray(g, dt), n.shape[:-1]).reshape(-1)
        log_g = None if gf is None else jnp.log(gf)

        def step(acc, star):
            s, sig, amp, log_t = star
            d = angular_distance(flat, s)
            w = amp * jnp.exp(-0.5 * (d / sig) ** 2)
            log_y0, rgb0 = _lookup(log_t)
            if log_g is None:
                col = rgb0[None, :]
            elif mode == "bolometric":
                col = (gf**4)[:, None] * rgb0
            else:
                log_y, rgb = _lookup(log_t + log_g)
                col = jnp.exp(log_y - log_y0)[:, None] * rgb
            return acc + w[:, None] * col, None

        stars = (
            self.directions.astype(dt),
            self.sigma.astype(dt),
            self.brightness.astype(dt),
            jnp.log(self.temperature.astype(dt)),
        )
        acc, _ = jax.lax.scan(step, jnp.zeros((flat.shape[0], 3), dt), stars)
        return acc.reshape(n.shape[:-1] + (3,))

    def __call__(self, n):
        """Rest-frame radiance (no frequency shift) at unit directions `n (..., 3)`."""
        return self._sum(n, None, None)

    def shifted(self, n, g, mode: str):
        """Radiance seen with frequency ratio `g (...)` (one per direction), `mode` as
        `Redshift`."""
        return self._sum(n, g, mode)


def shifted_sky(sky: AbstractSky, n: Float[Array, "... 3"], g, mode: str):
    """Radiance of `sky` at directions `n` seen with frequency ratio `g` (`...`).

    Components with a spectrum (`shifted` method, e.g. `BlackbodyStars`) shift it;
    plain RGB skies are scaled by $g^4$ (bolometric) or $g^3$ (spectral, flat
    $I_\\nu$ per channel). Sums are shifted part by part.
    """
    parts = sky.parts if isinstance(sky, SkySum) else (sky,)
    total = 0.0
    for part in parts:
        if isinstance(part, SkySum):
            total = total + shifted_sky(part, n, g, mode)
        elif hasattr(part, "shifted"):
            total = total + part.shifted(n, g, mode)
        else:
            power = 4 if mode == "bolometric" else 3
            total = total + (jnp.asarray(g, n.dtype) ** power)[..., None] * part(n)
    return total
