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

Frequency shifts of the sky are a method of the sky family (`AbstractSky.shifted`);
blackbody colours live in `_color` and are re-exported here.
"""

import abc
import math
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from . import _limits

# The colour functions, re-exported for the modules that use them beside the effects.
from ._color import (
    C2 as C2,
    XYZ_TO_SRGB as XYZ_TO_SRGB,
    _lookup as _lookup,
    blackbody_color as blackbody_color,
    blackbody_luminance as blackbody_luminance,
    blackbody_rgb as blackbody_rgb,
    blackbody_xyz_quadrature as blackbody_xyz_quadrature,
    cie_cmf as cie_cmf,
    planck as planck,
    shifted_blackbody as shifted_blackbody,
)
from ._limits import radians
from ._schema import Key, anything, register
from ._sky import BlackbodyStars as BlackbodyStars
from ._units import length, plain

# ---------------------------------------------------------------------- observers


def static_blueshift(distance: ArrayLike) -> Float[Array, "..."]:
    """Frequency ratio $\\nu_{obs}/\\nu_\\infty = 1/\\sqrt{1 - 1/D}$ of light from
    infinity seen by a static observer at radius `distance` $D > 1$ (units of R_S)."""
    distance = length(distance, "distance")
    d = jnp.asarray(distance, jnp.result_type(float, distance))
    return jnp.sqrt(d / (d - 1.0))


def orbital_speed(distance: ArrayLike) -> Float[Array, "..."]:
    """Speed of a circular geodesic orbit at radius $D > 1.5$ (units of R_S), as a
    static observer there measures it: $v = 1/\\sqrt{2(D - 1)}$ (units of c)."""
    distance = length(distance, "distance")
    d = jnp.asarray(distance, jnp.result_type(float, distance))
    return jnp.sqrt(0.5 / (d - 1.0))


def infall_speed(distance: ArrayLike) -> Float[Array, "..."]:
    """Speed at radius $D$ (units of R_S) of a fall from rest at infinity, measured by
    the static observer there: $v = \\sqrt{1/D}$ (units of c)."""
    distance = length(distance, "distance")
    d = jnp.asarray(distance, jnp.result_type(float, distance))
    return jnp.sqrt(1.0 / d)


def lorentz_factor(v: ArrayLike) -> Float[Array, "..."]:
    """$\\gamma = 1/\\sqrt{(1 - v)(1 + v)}$ for a speed $0 \\le v < 1$ (units of c)."""
    v = plain(v, "v", "a speed in units of c")
    v = jnp.asarray(v, jnp.result_type(float, v))
    return 1.0 / jnp.sqrt((1.0 - v) * (1.0 + v))


def aberrate_cos(cos_a: ArrayLike, v: ArrayLike) -> Float[Array, "..."]:
    """Static-frame $\\cos a = (\\cos a' - v)/(1 - v \\cos a')$ of a look direction at
    angle $a'$ from the velocity in the frame moving at speed `v` (units of c)."""
    v = plain(v, "v", "a speed in units of c")
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
    v = plain(v, "v", "a speed in units of c")
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
    v = plain(v, "v", "a speed in units of c")
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
    limits: ClassVar[dict[str, _limits.Limit]] = {}

    def __check_init__(self):
        _limits.check_fields(self)

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
    view; an increasing `Camera.azimuth` is the motion at `angle` $= \\pi$); finite;
    an astropy angle Quantity is converted.
    """

    radial: ClassVar[bool] = False
    angle: Float[Array, ""]
    limits: ClassVar = {"angle": _limits.finite("radians")}

    def __init__(self, angle: ArrayLike = 0.0):
        self.angle = radians("angle", angle)

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
