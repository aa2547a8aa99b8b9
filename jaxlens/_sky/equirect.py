"""Sampling a sky onto an equirectangular grid."""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._base import AbstractSky, direction_from_angles


@eqx.filter_jit
def _equirect_block(sky, j0, width, height, rows, k, dtype):
    sub = (jnp.arange(k, dtype=dtype) + 0.5) / k
    i = (jnp.arange(width, dtype=dtype)[:, None] + sub).reshape(-1)
    j = ((j0 + jnp.arange(rows)).astype(dtype)[:, None] + sub).reshape(-1)
    lon = 2.0 * math.pi * i / width - math.pi
    lat = 0.5 * math.pi - math.pi * j / height
    n = direction_from_angles(lon[None, :], lat[:, None]).astype(dtype)
    img = sky(n).reshape(rows, k, width, k, 3).mean(axis=(1, 3))
    return img.astype(jnp.float32)


def equirectangular(
    sky: AbstractSky, width: int, height: int, *, supersample: int = 1, dtype=jnp.float32
) -> np.ndarray:
    """Sample a sky onto an equirectangular grid (the `Panorama` pixel convention).

    **Arguments:** `sky`; `width`, `height` (pixels; 2:1 for square pixels in angle);
    `supersample`: $k \\times k$ samples a pixel (uniform in longitude and latitude);
    `dtype`: the dtype the sky is evaluated in.

    **Returns:** float32 `(height, width, 3)` linear radiance; `Panorama(result)`
    gives the sky back (bilinearly interpolated).
    """
    if width < 1 or height < 1 or supersample < 1:
        raise ValueError(f"width={width}, height={height}, supersample={supersample} must be >= 1")
    k = supersample
    rows = min(height, max(1, (1 << 20) // (width * k * k)))
    out = np.empty((height, width, 3), np.float32)
    for r0 in range(0, height, rows):
        s = min(r0, height - rows)  # the last block overlaps instead of padding
        block = _equirect_block(sky, jnp.asarray(s), width, height, rows, k, jnp.dtype(dtype))
        out[r0 : s + rows] = np.asarray(block)[r0 - s :]
    return out
