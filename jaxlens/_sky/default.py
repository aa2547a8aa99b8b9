"""The procedural default sky: a Milky-Way-like band, dust and hashed stars."""

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
from .._limits import real
from .._schema import Key, anything
from ._base import AbstractRGBSky
from ._table import BRIGHTNESS


# `_hash` and `_value_noise` are jitted: the sky calls them 34 and 3 times with the same
# shapes, so a render's block traces each once (the program, after XLA inlines the
# calls, is the same).
@jax.jit
def _hash(i, j, k, salt):
    """A 32-bit integer hash (lowbias32) of lattice indices -> [0, 1): deterministic,
    the same on every backend."""
    h = (
        i.astype(jnp.uint32) * jnp.uint32(0x8DA6B343)
        ^ j.astype(jnp.uint32) * jnp.uint32(0xD8163841)
        ^ k.astype(jnp.uint32) * jnp.uint32(0xCB1AB31F)
        ^ jnp.asarray(salt).astype(jnp.uint32)
    )
    h ^= h >> 16
    h *= jnp.uint32(0x7FEB352D)
    h ^= h >> 15
    h *= jnp.uint32(0x846CA68B)
    h ^= h >> 16
    return (h >> 8).astype(jnp.float32) * (1.0 / 16777216.0)


@jax.jit
def _value_noise(p, salt):
    """Smooth 3-D value noise in [0, 1] at points `p (..., 3)` (lattice spacing 1)."""
    c = jnp.floor(p)
    f = p - c
    f = f * f * (3.0 - 2.0 * f)
    ci = c.astype(jnp.int32)
    x, y, z = ci[..., 0], ci[..., 1], ci[..., 2]
    fx, fy, fz = f[..., 0], f[..., 1], f[..., 2]

    def lerp(a, b, t):
        return a + t * (b - a)

    def corner(dx, dy, dz):
        return _hash(x + dx, y + dy, z + dz, salt).astype(p.dtype)

    x00 = lerp(corner(0, 0, 0), corner(1, 0, 0), fx)
    x10 = lerp(corner(0, 1, 0), corner(1, 1, 0), fx)
    x01 = lerp(corner(0, 0, 1), corner(1, 0, 1), fx)
    x11 = lerp(corner(0, 1, 1), corner(1, 1, 1), fx)
    return lerp(lerp(x00, x10, fy), lerp(x01, x11, fy), fz)


def _fbm(p, octaves, salt):
    """Fractal sum of value noise, normalised to [0, 1]. A `fori_loop` over the
    octaves keeps the compiled program small."""

    def octave(o, total):
        scale = (2.0 ** o.astype(p.dtype)).astype(p.dtype)
        amp = (0.5 ** o.astype(p.dtype)).astype(p.dtype)
        return total + amp * _value_noise(p * scale + 17.0 * o.astype(p.dtype), salt + 7919 * o)

    total = jax.lax.fori_loop(0, octaves, octave, jnp.zeros(p.shape[:-1], p.dtype))
    return total * (1.0 / (2.0 - 2.0 ** (1 - octaves)))


def _cube_cells(n, cells):
    """Cube-map cell of each direction: face (0..5), cell indices and the position
    inside the face in cell units."""
    # Component by component: XLA's CPU code for a reduction or a gather over an axis
    # of 3 (argmax, take_along_axis) runs tens of times slower than elementwise.
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    ax, ay, az = jnp.abs(x), jnp.abs(y), jnp.abs(z)
    is_x = (ax >= ay) & (ax >= az)  # the largest component, the first of equals
    is_z = ~is_x & (az > ay)
    axis = jnp.where(is_x, 0, jnp.where(is_z, 2, 1))
    major = jnp.where(is_x, x, jnp.where(is_z, z, y))
    face = axis * 2 + (major < 0)
    ua = jnp.where(is_x, y, x)
    va = jnp.where(is_z, y, z)
    inv = 1.0 / jnp.abs(major)
    u = (ua * inv + 1.0) * (0.5 * cells)
    v = (va * inv + 1.0) * (0.5 * cells)
    return face, u, v


def _star_layer(n, cells, size, fraction, faint, bright, density, salt):
    """One layer of hashed stars: at most one a cube-map cell, at a hashed position
    inside it, Gaussian of sigma `size` (cell units), present with probability
    `fraction * density`, peak brightness a power law from `faint` up to `bright`."""
    face, u, v = _cube_cells(n, cells)
    iu, iv = jnp.floor(u), jnp.floor(v)
    ii, jj = iu.astype(jnp.int32), iv.astype(jnp.int32)
    h1, h2 = _hash(ii, jj, face, salt + 1), _hash(ii, jj, face, salt + 2)
    h3, h4 = _hash(ii, jj, face, salt + 3), _hash(ii, jj, face, salt + 4)
    temp = _hash(ii, jj, face, salt + 5).astype(n.dtype)
    du = u - (iu + 0.3 + 0.4 * h1)
    dv = v - (iv + 0.3 + 0.4 * h2)
    r2 = (du * du + dv * dv) * (1.0 / (size * size))
    present = h3 < fraction * density
    # Flux of a uniform population: N(> F) ~ F^-3/2, so F = F_min u^(-2/3), capped.
    mag = jnp.minimum(faint * jnp.maximum(h4, 1e-6) ** (-2.0 / 3.0), bright)
    # Fade to zero at the cell border, so no star is cut off by its cell.
    fu, fv = u - iu, v - iv
    edge = jnp.minimum(jnp.minimum(fu, 1.0 - fu), jnp.minimum(fv, 1.0 - fv))
    window = jnp.clip(edge * (1.0 / 0.2), 0.0, 1.0) ** 2
    i = jnp.where(present, mag * jnp.exp(-0.5 * r2) * window, 0.0)
    tint = jnp.stack([0.75 + 0.45 * temp, 0.85 + 0.15 * temp, 1.25 - 0.55 * temp], -1)
    return i[..., None] * tint


class DefaultSky(AbstractRGBSky):
    """The procedural default sky: a Milky-Way-like band with a bulge, clumpy star
    clouds, dark dust lanes and two layers of stars. Made by code (no image file),
    deterministic, continuous across the whole sphere.

    The band is a great circle tilted 30 degrees across the view, its centre (the
    bulge) 40 degrees to the left of $+z$. Its brightness and dust are fractal value
    noise in 3-D (no seam, no pole); stars sit in cube-map cells, at most one a cell,
    at hashed positions, more of them near the band, so evaluating the sky costs the
    same for every direction.

    **Fields:** `brightness` (overall scale, in [0, 1e30]), `cells` (static: cells a cube face of
    the faint star layer), `star_size` (static: Gaussian sigma of a star, in units of
    its cell), `stars` (static: include the star layers).
    """

    brightness: Float[Array, ""]
    cells: int = eqx.field(static=True)
    star_size: float = eqx.field(static=True)
    stars: bool = eqx.field(static=True)
    limits: ClassVar = {"brightness": _limits.scale()}

    def __init__(self, brightness: ArrayLike = 1.0, *, cells: int = 256, star_size: float = 0.08,
                 stars: bool = True):  # fmt: skip
        self.brightness = real("brightness", brightness)
        self.cells = int(cells)
        self.star_size = float(star_size)
        self.stars = bool(stars)

    def __check_init__(self):
        if self.cells < 1 or not self.star_size > 0:
            raise ValueError(f"cells={self.cells} must be >= 1, star_size={self.star_size} > 0")

    def galactic_frame(self):
        """Unit vectors (centre, east, pole) of the band's frame, world coordinates."""
        tilt, lon_c = math.radians(30.0), math.radians(-40.0)
        east = np.array([math.cos(tilt), math.sin(tilt), 0.0])  # along the band, +x-ward
        pole = np.array([-math.sin(tilt), math.cos(tilt), 0.0])
        # Centre: +z turned about the pole by lon_c (stays in the band).
        z = np.array([0.0, 0.0, 1.0])
        centre = math.cos(lon_c) * z + math.sin(lon_c) * np.cross(pole, z)
        east = np.cross(pole, centre)
        return centre, east, pole

    def __call__(self, n):
        dt = n.dtype
        centre, east, pole = (jnp.asarray(v, dt) for v in self.galactic_frame())
        # Matrix-vector products (XLA's dot; full precision, not a GPU's TF32): as a sum
        # over the last axis, XLA's CPU code ran ~40 times slower; written out component
        # by component, the render's block held 48 MB more.
        nc, ne, npole = (jnp.dot(n, v, precision="highest") for v in (centre, east, pole))
        b = arctan2(npole, jnp.sqrt(nc * nc + ne * ne))  # galactic latitude
        l = arctan2(ne, nc)  # noqa: E741  galactic longitude
        # Star clouds and dust: 3-D fractal noise on the sphere (no seams).
        clouds = _fbm(n * 5.0, 5, 11)
        grain = _fbm(n * 23.0 + 3.0, 3, 29)
        dustn = _fbm(n * 9.0 + 7.0, 4, 47)
        width = 0.11 + 0.05 * (clouds - 0.5) + 0.06 * jnp.exp(-((l / 0.7) ** 2))
        disk = jnp.exp(-((b / width) ** 2)) * (0.3 + 0.7 * jnp.exp(-((l / 1.6) ** 2)))
        disk = disk * (0.35 + 1.3 * clouds**2) * (0.75 + 0.5 * grain)
        halo = 0.12 * jnp.exp(-((b / 0.45) ** 2)) * (0.4 + 0.6 * jnp.exp(-((l / 1.2) ** 2)))
        bulge = jnp.exp(-((l / 0.2) ** 2) - (b / 0.15) ** 2) * (0.8 + 0.4 * clouds)
        # Dust: a rift along the plane, wavy and filamentary.
        ridge = 1.0 - jnp.abs(2.0 * dustn - 1.0)
        lane = jnp.exp(-(((b - 0.035 * (dustn - 0.5)) / (0.03 + 0.02 * grain)) ** 2))
        tau = 2.2 * lane * ridge**2 * (0.4 + 0.6 * jnp.exp(-((l / 1.5) ** 2)))
        redden = jnp.asarray([0.75, 1.0, 1.35], dt)
        trans = jnp.exp(-tau[..., None] * redden)
        glow = (
            0.16 * disk[..., None] * jnp.asarray([0.78, 0.84, 1.0], dt)
            + 0.5 * bulge[..., None] * jnp.asarray([1.0, 0.8, 0.55], dt)
            + 0.03 * halo[..., None] * jnp.asarray([0.8, 0.85, 1.0], dt)
        ) * trans
        out = glow
        if self.stars:
            density = 0.25 + 0.75 * jnp.exp(-((b / 0.25) ** 2)) + 0.5 * bulge
            faint = _star_layer(n, self.cells, self.star_size, 0.6, 0.02, 0.6, density, 100)
            bright = _star_layer(
                n, max(self.cells // 4, 1), 0.75 * self.star_size, 0.5, 0.1, 6.0, density, 200
            )
            out = out + (faint * trans + bright).astype(dt)
        return self.brightness.astype(dt) * out


@_schema.register(
    "sky", "default", {**BRIGHTNESS, "stars": Key("bool", True, anything, "true or false")}
)
def _default(fields: dict, base: Path) -> DefaultSky:
    return DefaultSky(fields["brightness"], stars=fields["stars"])
