"""Many Gaussian stars, summed."""

import math
from pathlib import Path
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .. import _limits, _schema
from .._fastmath import arctan2
from .._limits import radians, real
from .._messages import describe
from .._schema import Key, anything
from .._util import concrete as _concrete
from ._base import AbstractRGBSky, direction_from_angles
from ._table import check_star_lists, star_directions, star_list_keys, value_range


class StarField(AbstractRGBSky):
    """Many Gaussian stars, summed; vectorised over stars and directions.

    Each direction is compared with every star (blocks of `block` stars at a time,
    through `lax.scan`, so memory is `block` x the number of directions): use it for
    up to a few hundred stars. The procedural `DefaultSky` holds millions.

    **Fields:** `directions (N, 3)` (unit vectors; given as finite non-zero vectors of
    any length), `sigma (N,)` (radians or an astropy angle, in $(0, \\pi)$), `brightness (N,)` (peak
    radiance) and `color (N, 3)` (RGB weights), both finite and at most 1e30 in
    magnitude; `block` (static).
    """

    directions: Float[Array, "N 3"]
    sigma: Float[Array, " N"]
    brightness: Float[Array, " N"]
    color: Float[Array, "N 3"]
    block: int = eqx.field(static=True)
    limits: ClassVar = {
        "directions": _limits.finite("non-zero 3-vectors"),
        "sigma": _limits.between(0.0, math.pi, "finite and in (0, pi)", "radians"),
        "brightness": _limits.radiance(),
        "color": _limits.radiance("RGB weights"),
    }

    def __init__(
        self,
        directions: ArrayLike,
        sigma: ArrayLike,
        brightness: ArrayLike = 1.0,
        color: ArrayLike = (1.0, 1.0, 1.0),
        *,
        block: int = 16,
    ):
        d = real("directions", directions)
        if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] < 1:
            raise ValueError(f"directions has shape {d.shape}; expected (N, 3) with N >= 1")
        n = d.shape[0]
        self.directions = unit_rows(d)
        self.sigma = jnp.broadcast_to(radians("sigma", sigma), (n,))
        self.brightness = jnp.broadcast_to(real("brightness", brightness), (n,))
        self.color = jnp.broadcast_to(real("color", color), (n, 3))
        self.block = int(block)

    @classmethod
    def from_angles(cls, lon, lat, sigma, brightness=1.0, color=(1.0, 1.0, 1.0)) -> "StarField":
        """Stars at longitudes `lon`, latitudes `lat` (radians, or astropy angle
        Quantities; 1-D arrays); `sigma` as the field."""
        lon, lat = radians("lon", lon), radians("lat", lat)
        d = direction_from_angles(jnp.atleast_1d(lon), jnp.atleast_1d(lat))
        return cls(d, sigma, brightness, color)

    @classmethod
    def random(cls, count: int, *, seed: int = 0, sigma=0.003, brightness=(0.05, 2.0)):
        """`count` stars uniform on the sphere, brightness log-uniform in the range
        `brightness`, colours from blue-white to orange; `sigma` in radians."""
        rng = np.random.default_rng(seed)
        d = rng.normal(size=(count, 3))
        lo, hi = brightness
        b = np.exp(rng.uniform(np.log(lo), np.log(hi), count))
        t = rng.uniform(0, 1, count)[:, None]
        color = np.concatenate([0.8 + 0.4 * t, 0.9 + 0.1 * t, 1.2 - 0.5 * t], axis=1)
        return cls(d, sigma, b, color)

    def __call__(self, n):
        dt = n.dtype
        shape = n.shape[:-1]
        flat = n.reshape(-1, 3)
        k = self.directions.shape[0]
        nb = -(-k // self.block)
        pad = nb * self.block - k

        def padded(a, value):
            return jnp.concatenate([a.astype(dt), jnp.full((pad,) + a.shape[1:], value, dt)])

        s = padded(self.directions, 0.0)
        s = s.at[k:, 2].set(1.0)
        # Tangent basis (e1, e2, s) of each star: d = atan2(|(n.e1, n.e2)|, n.s) exactly.
        helper = jnp.where(
            jnp.abs(s[:, :1]) < 0.9, jnp.array([1.0, 0, 0], dt), jnp.array([0, 1.0, 0], dt)
        )
        e1 = jnp.cross(s, helper)
        e1 = e1 / jnp.linalg.norm(e1, axis=-1, keepdims=True)
        e2 = jnp.cross(s, e1)
        basis = jnp.stack([e1, e2, s], axis=1).reshape(nb, self.block * 3, 3)
        # 1/sigma, not 1/(2 sigma^2): the latter overflows for sigma < 1e-19 (float32),
        # and the star's own centre (d = 0) would be 0 * inf.
        inv_s = (1.0 / padded(self.sigma, 1.0)).reshape(nb, self.block)
        amp = padded(self.brightness, 0.0).reshape(nb, self.block)
        col = padded(self.color, 0.0).reshape(nb, self.block, 3)

        def step(acc, blk):
            b, w, a, c = blk
            p = (flat @ b.T).reshape(-1, self.block, 3)
            d = arctan2(jnp.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2), p[..., 2]) * w
            i = a * jnp.exp(-0.5 * (d * d))
            return acc + i @ c, None

        acc, _ = jax.lax.scan(step, jnp.zeros((flat.shape[0], 3), dt), (basis, inv_s, amp, col))
        return acc.reshape(shape + (3,))


def unit_rows(d):
    """The rows of `d (N, 3)` as unit vectors: scaled by their largest component
    first (the norm of (1e200, 0, 0) overflows). A known row that is zero or not
    finite is a `ValueError`; a traced one gives NaN, which the sky's `limits` refuse."""
    c = _concrete(d)
    if c is not None:
        bad = ~np.all(np.isfinite(c), axis=-1) | ~np.any(c != 0, axis=-1)
        if np.any(bad):
            row = c[bad][0].tolist()
            raise ValueError(f"directions: row {int(np.argmax(bad))} = {row!r} must be a "
                             "finite non-zero 3-vector")  # fmt: skip
    d = d / jnp.max(jnp.abs(d), axis=-1, keepdims=True)
    return d / jnp.linalg.norm(d, axis=-1, keepdims=True)


def _check(where: str, fields: dict) -> None:
    check_star_lists(where, fields, ("brightness",))
    b = fields.get("brightness")
    if "lon_deg" not in fields and b is not None:
        low = min(np.atleast_1d(b))
        if not low > 0.0:  # random stars' brightness is log-uniform in its range
            raise ValueError(f"{where}.brightness = {describe(b)}: random stars "
                             "(count) need brightness values > 0 (the least and the largest "
                             "give the log-uniform range)")  # fmt: skip


@_schema.register(
    "sky",
    "stars",
    {
        **star_list_keys(0.15),
        "brightness": Key(
            "floats", None, anything, "a number or a list of numbers (peak radiance)"
        ),
    },
    check=_check,
)
def _stars(fields: dict, base: Path) -> StarField:
    """Stars at `lon_deg`, `lat_deg` (brightness a number or one a star, default 1), or
    `count` random ones (brightness log-uniform between the least and the largest
    value given, default 0.05 to 2)."""
    sigma = math.radians(fields["sigma_deg"])
    if "lon_deg" in fields:
        b = np.asarray(fields.get("brightness", 1.0), float)
        return StarField(star_directions(fields), sigma, b)
    rng = value_range(fields.get("brightness"), (0.05, 2.0))
    return StarField.random(fields["count"], seed=fields["seed"], sigma=sigma, brightness=rng)
