"""Render: camera -> rays -> ray map -> sky directions -> sky radiance -> image."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._camera import Camera, sky_direction
from ._raymap import RayMap
from ._sky import AbstractSky


def shade(camera: Camera, sky: AbstractSky, ray_map: RayMap, row0=0, rows: int | None = None):
    """Linear radiance of rows `row0 .. row0+rows` of the image, area-averaged.

    Samples that straddle the shadow edge are weighted by the fraction of their
    footprint outside the shadow (a linear ramp over one sample width in alpha), so
    the image, and its gradient with respect to distance and field of view, sees
    the edge as pixel coverage rather than a point-sampled step. The escaping part
    of such a sample takes the radiance of its centre of mass.

    **Returns:** `(rows, W, 3)` array in the camera's dtype.
    """
    alpha, cb, sb = camera.rays(row0, rows)
    ash = ray_map.alpha_sh.astype(alpha.dtype)
    width = jnp.cos(alpha) ** 2 / (camera.focal * camera.supersample)  # sample size in alpha
    cover = jnp.clip((alpha - ash) / width + 0.5, 0.0, 1.0)
    edge = jnp.maximum(alpha, ash + 0.5 * width * (1.0 - cover))
    phi = ray_map.escape_angle(edge)
    radiance = sky(sky_direction(phi, cb, sb)) * cover[..., None]
    return jnp.mean(radiance, axis=-2)


def render_array(
    camera: Camera, sky: AbstractSky, *, accuracy: float = 1e-8
) -> Float[Array, "H W 3"]:
    """The whole image as one traceable function: works under `jit`, `vmap` (batches
    of cameras) and `grad` (with respect to any array field of camera and sky).

    **Arguments:** `camera`, `sky`; `accuracy`: interpolation error of the ray map
    (radians).

    **Returns:** linear radiance `(H, W, 3)`.
    """
    ray_map = RayMap.build(camera.distance, accuracy=accuracy)
    return shade(camera, sky, ray_map)


@eqx.filter_jit
def _build_map(distance, accuracy):
    return RayMap.build(distance, accuracy=accuracy)


@eqx.filter_jit
def _shade_rows(camera, sky, ray_map, row0, rows):
    return shade(camera, sky, ray_map, row0, rows).astype(jnp.float32)


def render(
    camera: Camera,
    sky: AbstractSky,
    *,
    accuracy: float = 1e-8,
    chunk_pixels: int = 1 << 18,
    progress: bool | None = None,
) -> np.ndarray:
    """Render what `camera` sees of `sky` around the black hole.

    Rendered in chunks of about `chunk_pixels` area samples (one compiled program
    for all chunks), so memory stays bounded for any image size.

    **Arguments:**
    - `camera`: a `Camera` (distance in R_S, field of view in radians, size).
    - `sky`: an `AbstractSky` (sum skies with `+`).
    - `accuracy`: interpolation error of the ray map (radians).
    - `chunk_pixels`: samples per chunk.
    - `progress`: show a progress bar (default: when the render takes > 2 s).

    **Returns:** linear float32 RGB image `(H, W, 3)`; captured rays are 0.
    """
    ray_map = _build_map(camera.distance, accuracy)
    per_row = camera.width * camera.supersample**2
    rows = int(max(1, min(camera.height, chunk_pixels // per_row)))
    starts = list(range(0, camera.height, rows))
    out = np.empty((camera.height, camera.width, 3), np.float32)
    it = starts
    if len(starts) > 1 and progress is not False:
        from tqdm.auto import tqdm

        it = tqdm(starts, desc="render", unit="chunk", delay=0 if progress else 2.0, leave=False)
    for r0 in it:
        s = min(r0, camera.height - rows)  # the last chunk overlaps instead of padding
        block = np.asarray(_shade_rows(camera, sky, ray_map, jnp.asarray(s), rows))
        out[r0 : s + rows] = block[r0 - s :]
    return out
