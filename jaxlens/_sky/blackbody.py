"""Gaussian stars with blackbody spectra: the sky whose frequency shift changes colour."""

import math
from pathlib import Path
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .. import _limits, _schema
from .._color import _lookup
from .._limits import radians, real
from .._schema import Key, anything
from ._base import AbstractSky, angular_distance, direction_from_angles
from ._table import bad_value, check_star_lists, star_directions, star_list_keys, value_range
from .starfield import unit_rows


class BlackbodyStars(AbstractSky):
    """Gaussian stars with blackbody colours: star $i$ has radiance
    $A_i\\, e^{-d^2/2\\sigma_i^2}$ (angular distance $d$) times the colour of its
    temperature, luminance $A_i$ at rest.

    **Fields:** `directions (N, 3)` (world unit vectors; given as finite non-zero
    vectors of any length), `sigma (N,)` (radians or an astropy angle, in
    $(0, \\pi)$), `brightness (N,)` (peak luminance at rest, finite, at most 1e30 in
    magnitude), `temperature (N,)` (K, finite and > 0).
    """

    directions: Float[Array, "N 3"]
    sigma: Float[Array, " N"]
    brightness: Float[Array, " N"]
    temperature: Float[Array, " N"]
    limits: ClassVar = {
        "directions": _limits.finite("non-zero 3-vectors"),
        "sigma": _limits.between(0.0, math.pi, "finite and in (0, pi)", "radians"),
        "brightness": _limits.radiance("luminance"),
        "temperature": _limits.positive("K"),
    }

    def __init__(self, directions, sigma, brightness=1.0, temperature=5800.0):
        d = real("directions", directions)
        if d.ndim != 2 or d.shape[-1] != 3 or d.shape[0] < 1:
            raise ValueError(f"directions has shape {d.shape}; expected (N, 3) with N >= 1")
        n = d.shape[0]
        self.directions = unit_rows(d)
        self.sigma = jnp.broadcast_to(radians("sigma", sigma), (n,))
        self.brightness = jnp.broadcast_to(real("brightness", brightness), (n,))
        self.temperature = jnp.broadcast_to(real("temperature", temperature), (n,))

    @classmethod
    def from_angles(cls, lon, lat, sigma, brightness=1.0, temperature=5800.0):
        """Stars at longitudes `lon`, latitudes `lat` (radians or astropy angles;
        `direction_from_angles`)."""
        d = direction_from_angles(
            jnp.atleast_1d(radians("lon", lon)), jnp.atleast_1d(radians("lat", lat))
        )
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
        """Radiance seen with frequency ratio `g (...)` (one per direction): `"spectral"`,
        each star the blackbody of temperature $gT$; `"bolometric"`, its rest colour
        times $g^4$."""
        return self._sum(n, g, mode)


_BRIGHTNESS_VALID = "a number or a list of numbers (peak luminance; > 0 for random stars)"
_TEMPERATURE_VALID = "a number > 0 or a list of them (K)"


def _check(where: str, fields: dict) -> None:
    check_star_lists(where, fields, ("brightness", "temperature"))
    t = fields.get("temperature")
    if t is not None and not np.all(np.asarray(t) > 0):
        raise bad_value(where, fields, "temperature", _TEMPERATURE_VALID)
    b = fields.get("brightness")
    if "lon_deg" not in fields and b is not None and not np.all(np.asarray(b) > 0):
        raise bad_value(where, fields, "brightness", _BRIGHTNESS_VALID)


@_schema.register(
    "sky",
    "blackbody",
    {
        **star_list_keys(0.2),
        "brightness": Key("floats", None, anything, _BRIGHTNESS_VALID),
        "temperature": Key("floats", None, anything, _TEMPERATURE_VALID),
    },
    check=_check,
)
def _blackbody(fields: dict, base: Path) -> BlackbodyStars:
    """Stars at `lon_deg`, `lat_deg` (brightness and temperature a number or one a
    star; defaults 1 and 5800 K), or `count` random ones (brightness and temperature
    log-uniform between the least and the largest value given; defaults 0.2 to 2 and
    2500 to 30000 K)."""
    sigma = math.radians(fields["sigma_deg"])
    b, t = fields.get("brightness"), fields.get("temperature")
    if "lon_deg" in fields:
        b = np.asarray(1.0 if b is None else b, float)
        t = np.asarray(5800.0 if t is None else t, float)
        return BlackbodyStars(star_directions(fields), sigma, b, t)
    return BlackbodyStars.random(
        fields["count"],
        seed=fields["seed"],
        sigma=sigma,
        brightness=value_range(b, (0.2, 2.0)),
        temperature=value_range(t, (2500.0, 30000.0)),
    )
