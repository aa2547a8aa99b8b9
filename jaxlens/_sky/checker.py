"""A diagnostic checkerboard sphere."""

import math
from pathlib import Path
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .. import _limits, _schema
from .._limits import radians, real
from .._schema import Key, in_range
from ._base import AbstractRGBSky, angles_from_direction, unrotate
from ._table import BRIGHTNESS, ORIENTATION, orientation


class Checker(AbstractRGBSky):
    """A diagnostic checkerboard sphere: `n_lon` x `n_lat` squares in longitude and
    latitude, tinted by quadrant of longitude (red around $+z$ behind the hole, then
    green toward $+x$, blue in front, yellow toward $-x$), dark and light squares
    alternating, with thin white lines on the equator and the prime meridian.

    **Fields:** `n_lon`, `n_lat` (static, squares around and pole to pole),
    `brightness` (a scale in [0, 1e30]), `yaw`, `pitch`, `roll` (radians or astropy
    angles, finite, as `Rotated`).
    """

    n_lon: int = eqx.field(static=True)
    n_lat: int = eqx.field(static=True)
    brightness: Float[Array, ""]
    yaw: Float[Array, ""]
    pitch: Float[Array, ""]
    roll: Float[Array, ""]
    limits: ClassVar = {"brightness": _limits.scale(), **_limits.ORIENTATION}

    def __init__(self, n_lon: int = 24, n_lat: int = 12, *, brightness=1.0, yaw=0.0, pitch=0.0,
                 roll=0.0):  # fmt: skip
        self.n_lon, self.n_lat = int(n_lon), int(n_lat)
        self.brightness = real("brightness", brightness)
        self.yaw, self.pitch = radians("yaw", yaw), radians("pitch", pitch)
        self.roll = radians("roll", roll)

    def __check_init__(self):
        if self.n_lon < 1 or self.n_lat < 1:
            raise ValueError(f"n_lon={self.n_lon}, n_lat={self.n_lat} must be >= 1")

    def __call__(self, n):
        dt = n.dtype
        n = unrotate(n, self.yaw, self.pitch, self.roll)
        lon, lat = angles_from_direction(n)
        a = (lon + math.pi) * (self.n_lon / (2.0 * math.pi))
        b = (lat + 0.5 * math.pi) * (self.n_lat / math.pi)
        parity = (jnp.floor(a) + jnp.floor(b)) % 2.0
        # Quadrant of longitude: 0 around +z (behind the hole), 1 around +x, 2 in front
        # (lon = +-pi), 3 around -x.
        quadrant = jnp.floor((lon + 0.25 * math.pi) / (0.5 * math.pi)).astype(jnp.int32) % 4
        palette = jnp.asarray(
            [[1.0, 0.25, 0.2], [0.3, 1.0, 0.3], [0.25, 0.35, 1.0], [1.0, 0.9, 0.25]], dt
        )
        tint = palette[quadrant]
        level = (0.25 + 0.75 * parity)[..., None]
        line = (jnp.abs(lat) < 0.004) | (jnp.abs(lon) < 0.004)
        out = jnp.where(line[..., None], jnp.ones(3, dt), level * tint)
        return self.brightness.astype(dt) * out


@_schema.register(
    "sky",
    "checker",
    {
        "n_lon": Key("int", 24, in_range(0, 100001), "a whole number >= 1"),
        "n_lat": Key("int", 12, in_range(0, 100001), "a whole number >= 1"),
        **BRIGHTNESS,
        **ORIENTATION,
    },
)
def _checker(fields: dict, base: Path) -> Checker:
    return Checker(
        fields["n_lon"], fields["n_lat"], brightness=fields["brightness"], **orientation(fields)
    )
