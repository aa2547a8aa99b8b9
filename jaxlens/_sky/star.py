"""One star of Gaussian profile."""

import math
from pathlib import Path
from typing import ClassVar

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .. import _limits, _schema
from .._limits import radians, real
from .._messages import cut
from .._schema import Key, anything
from .._util import concrete as _concrete, to_device
from ._base import AbstractCompactSky, angular_distance, direction_from_angles
from ._table import SIGMA


class GaussianStar(AbstractCompactSky):
    """A star of Gaussian profile in angular distance $d$: $I = A e^{-d^2 / 2\\sigma^2}$.

    **Fields:** `sigma` (radians or an astropy angle, standard deviation in great-circle angle, in
    $(0, \\pi)$), `brightness` $A$ (peak radiance, finite, at most 1e30 in magnitude:
    a fit may pass through negative values), `direction` (a finite non-zero 3-vector,
    need not be unit length; default $+z$, exactly behind the hole), `color` (RGB
    weights, as `brightness`).

    Give the position either as `direction` or as `lon`, `lat` (radians or astropy angles; see
    `direction_from_angles`).
    """

    sigma: Float[Array, ""]
    brightness: Float[Array, ""]
    direction: Float[Array, "3"]
    color: Float[Array, "3"]
    limits: ClassVar = {
        "sigma": _limits.between(0.0, math.pi, "finite and in (0, pi)", "radians"),
        "brightness": _limits.radiance(),
        "direction": _limits.finite("a non-zero 3-vector"),
        "color": _limits.radiance("RGB weights"),
    }

    def __init__(
        self,
        sigma: ArrayLike,
        brightness: ArrayLike = 1.0,
        direction: ArrayLike | None = None,
        color: ArrayLike = (1.0, 1.0, 1.0),
        *,
        lon: ArrayLike | None = None,
        lat: ArrayLike | None = None,
    ):
        self.sigma = radians("sigma", sigma)
        self.brightness = real("brightness", brightness)
        if lon is not None or lat is not None:
            if direction is not None:
                raise ValueError("give the star position as direction or as lon/lat, not both")
            d = direction_from_angles(radians("lon", 0.0 if lon is None else lon),
                                      radians("lat", 0.0 if lat is None else lat))  # fmt: skip
        else:
            d = real("direction", (0.0, 0.0, 1.0) if direction is None else direction)
            c = _concrete(d)
            if c is not None and (c.shape != (3,) or not np.all(np.isfinite(c)) or not c.any()):
                raise ValueError(f"direction={cut(repr(c.tolist()))} must be a finite non-zero "
                                 "3-vector")  # fmt: skip
            # Scaled by the largest component first: the norm of (1e200, 0, 0) is inf.
            if c is not None:
                c = c / np.max(np.abs(c))
                d = to_device(c / np.linalg.norm(c), d.dtype)
            else:
                d = d / jnp.max(jnp.abs(d))
                d = d / jnp.linalg.norm(d)
        self.direction = d
        self.color = real("color", color)

    def __call__(self, n):
        dt = n.dtype
        d = angular_distance(n, self.direction.astype(dt))
        i = self.brightness.astype(dt) * jnp.exp(-0.5 * (d / self.sigma.astype(dt)) ** 2)
        return i[..., None] * self.color.astype(dt)

    def crossing(self, e1, e3):
        """Closest approach of the great circle $\\sin\\Phi\\,e_1 + \\cos\\Phi\\,e_3$
        to the star and $\\int I\\,d\\Phi$ across it: $A \\sqrt{2\\pi}\\,\\sigma\\,
        e^{-d_\\perp^2 / 2\\sigma^2}$ (RGB), $d_\\perp$ the star's angle from the circle
        (the profile across the circle is Gaussian to $O(\\sigma^2)$)."""
        dt = e1.dtype
        s = self.direction.astype(dt)
        a = jnp.sum(e1 * s, axis=-1)
        b = jnp.sum(e3 * s, axis=-1)
        c = jnp.sum(jnp.cross(e1, e3) * s, axis=-1)
        # A star at the circle's pole (a = b = 0) is a quarter turn from all of it:
        # keep the arctangents off their singular point (and their gradients finite).
        pole = (a == 0) & (b == 0)
        a, b = jnp.where(pole, 0.0, a), jnp.where(pole, 1.0, b)
        phi0 = jnp.mod(jnp.arctan2(a, b), 2.0 * jnp.pi)
        perp = jnp.where(pole, 0.5 * jnp.pi, jnp.arctan2(jnp.abs(c), jnp.sqrt(a * a + b * b)))
        sigma = self.sigma.astype(dt)
        peak = self.brightness.astype(dt) * math.sqrt(2.0 * math.pi) * sigma
        integral = peak * jnp.exp(-0.5 * (perp / sigma) ** 2)
        return phi0, integral[..., None] * self.color.astype(dt)


@_schema.register(
    "sky",
    "star",
    {
        **SIGMA,
        "brightness": Key("float", 1.0, anything, "a finite number (peak radiance)"),
        "lon_deg": Key("float", 0.0, anything, "a finite number (degrees)"),
        "lat_deg": Key("float", 0.0, anything, "a finite number (degrees)"),
        "color": Key("color", [1.0, 1.0, 1.0], anything, "a number or a list of 3 numbers (RGB)"),
    },
)
def _star(fields: dict, base: Path) -> GaussianStar:
    rad = math.radians
    return GaussianStar(
        rad(fields["sigma_deg"]),
        fields["brightness"],
        color=np.broadcast_to(np.asarray(fields["color"], float), (3,)),
        lon=rad(fields["lon_deg"]),
        lat=rad(fields["lat_deg"]),
    )
