"""An equirectangular panorama covering the whole sky."""

import math
from pathlib import Path
from typing import ClassVar

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import _limits, _schema
from .._io import read_image
from .._limits import radians, real
from ._base import AbstractRGBSky, angles_from_direction, bilinear, to_rgb, unrotate
from ._table import BRIGHTNESS, IMAGE_PATH, ORIENTATION, orientation


def _panorama_texels(image):
    """The texels a `Panorama` samples: the image with its first column repeated
    after the last (the seam) and a row of the first (last) row's mean above (below)
    it, which the look-up places at the north (south) pole."""
    north = jnp.broadcast_to(jnp.mean(image[:1], axis=1, keepdims=True), (1,) + image.shape[1:])
    south = jnp.broadcast_to(jnp.mean(image[-1:], axis=1, keepdims=True), (1,) + image.shape[1:])
    rows = jnp.concatenate([north, image, south], axis=0)
    return jnp.concatenate([rows, rows[:, :1]], axis=1)


class Panorama(AbstractRGBSky):
    """An equirectangular (longitude-latitude) panorama covering the whole sky.

    Pixel (column $i$, row $j$) of a $w \\times h$ image is centred at longitude
    $2\\pi (i + 1/2)/w - \\pi$ and latitude $\\pi/2 - \\pi (j + 1/2)/h$: the image
    centre is $+z$ (behind the hole), the left and right edges meet at longitude
    $\\pm\\pi$ (in front of the camera), the top row is next to the north pole $+y$.
    Sampled bilinearly; the columns wrap, so the $\\pm\\pi$ seam is seamless; between
    the first (last) row's centre and the pole the value blends linearly in latitude
    into the mean of that row, so the pole has one value and no pinch.

    **Fields:** `texels (h + 2, w + 1, 3)`: the image in linear radiance, framed for
    the look-up (`image` gives it back; finite); `brightness` (scale, in [0, 1e30]),
    `yaw`, `pitch`, `roll` (radians or astropy angles, finite: the panorama's orientation, the old
    programs' "offset"; see `Rotated`).
    """

    texels: Float[Array, "h2 w1 3"]
    brightness: Float[Array, ""]
    yaw: Float[Array, ""]
    pitch: Float[Array, ""]
    roll: Float[Array, ""]
    limits: ClassVar = {
        "texels": _limits.texture(),
        "brightness": _limits.scale(),
        **_limits.ORIENTATION,
    }

    def __init__(self, image: ArrayLike, *, brightness=1.0, yaw=0.0, pitch=0.0, roll=0.0):
        """**Arguments:** `image`: `(h, w)` or `(h, w, 1..4)` linear radiance (see
        `to_rgb`); the other fields as above."""
        if not isinstance(image, jax.core.Tracer):
            image = jnp.asarray(to_rgb(image, name="panorama image"))
        self.texels = _panorama_texels(image)
        self.brightness = real("brightness", brightness)
        self.yaw, self.pitch = radians("yaw", yaw), radians("pitch", pitch)
        self.roll = radians("roll", roll)

    @property
    def image(self) -> Float[Array, "h w 3"]:
        """The panorama image `(h, w, 3)`."""
        return self.texels[1:-1, :-1]

    @classmethod
    def from_file(cls, path, **kwargs) -> "Panorama":
        """Read an equirectangular image with OpenImageIO (PNG, JPEG, EXR, HDR, ...;
        8- and 16-bit files are converted from sRGB to linear)."""
        return cls(to_rgb(read_image(path), name=f"panorama {str(path)!r}"), **kwargs)

    def __call__(self, n):
        dt = n.dtype
        n = unrotate(n, self.yaw, self.pitch, self.roll)
        h, w = self.texels.shape[0] - 2, self.texels.shape[1] - 1
        lon, lat = angles_from_direction(n)
        u = (lon * (0.5 / math.pi) + 0.5) * w - 0.5  # in [-0.5, w - 0.5]
        v = (0.5 - lat * (1.0 / math.pi)) * h - 0.5  # in [-0.5, h - 0.5]
        u0 = jnp.floor(u)
        i0 = u0.astype(jnp.int32)
        i0 = jnp.where(i0 < 0, w - 1, i0)  # the columns wrap: no seam at lon = +-pi
        fu = u - u0
        # Rows: texel row r + 1 holds image row r; rows 0 and h + 1 hold the poles,
        # half a row beyond the first and last row centres.
        interior = jnp.clip(jnp.floor(v).astype(jnp.int32) + 1, 1, max(h - 1, 1))
        j0 = jnp.where(v < 0, 0, jnp.where(v > h - 1, h, interior))
        fv = jnp.where(
            v < 0,
            2.0 * v + 1.0,
            jnp.where(v > h - 1, 2.0 * (v - (h - 1)), v - (interior - 1).astype(dt)),
        )
        val = bilinear(self.texels, j0, i0, fu, jnp.clip(fv, 0.0, 1.0), dt)
        return self.brightness.astype(dt) * val


def _check(where: str, fields: dict) -> None:
    if "path" not in fields:
        raise ValueError(f'{where} needs a path = "IMAGE" (an image file)')


@_schema.register("sky", "panorama", {**IMAGE_PATH, **BRIGHTNESS, **ORIENTATION}, check=_check)
def _panorama(fields: dict, base: Path) -> Panorama:
    """`path` is relative to `base` (the scene file's folder)."""
    return Panorama.from_file(
        base / fields["path"], brightness=fields["brightness"], **orientation(fields)
    )
