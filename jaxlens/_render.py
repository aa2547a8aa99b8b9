"""Render: camera -> rays -> ray map -> sky directions -> sky radiance -> image.

The escape angle of a static camera depends on the local angle alpha alone
(DESIGN.md), so a render tabulates it once per distance (`RayMap`) and each sample
costs one table look-up. For a centred camera (yaw = pitch = roll = 0) alpha depends
on $|x|$ and $|y|$ only: the ray-map part is computed for one half of the columns
and mirrored, and `render` also pairs each block of rows in the top half with its
mirror image in the bottom half, so only a quarter of the samples go through the
map. The sky is then looked up at every sample.

Precision: the table is built in float64 where `jax_enable_x64` is on, whatever the
dtype the pixels are computed in; the position inside a knot interval is taken
against that knot's own $\\tau$, so a float32 render keeps the table's accuracy
(`benchmarks/bench_render.py` checks every pixel of a 1920 x 1080 float32 render
against a per-pixel float64 trace).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._camera import Camera
from ._fastmath import arctan2, sin_cos
from ._raymap import RayMap, hermite
from ._sky import AbstractSky

# Default number of area samples a compiled block holds (rows are grouped to fit).
CHUNK_SAMPLES = 1 << 21


class MapView(eqx.Module):
    """A `RayMap` prepared for pixel look-ups in a given dtype.

    **Fields:** `alpha_sh` (shadow angle, radians), `tau` (knot positions
    $\\tau_i = \\ln(\\alpha_i - \\alpha_{sh})$), `inv_dtau`, `phi` (escape angle at
    the knots, radians), `mslope` ($d\\phi/d\\tau \\cdot \\Delta\\tau$ at the knots).
    """

    alpha_sh: Float[Array, ""]
    tau: Float[Array, " n"]
    inv_dtau: Float[Array, ""]
    phi: Float[Array, " n"]
    mslope: Float[Array, " n"]

    @classmethod
    def of(cls, ray_map: RayMap, dtype=None) -> "MapView":
        """View of `ray_map` (any dtype) for evaluation in `dtype` (default: the
        map's own)."""
        dtype = ray_map.phi.dtype if dtype is None else dtype
        n = ray_map.phi.shape[-1]  # a batch of maps gives a batch of views
        knots = jnp.arange(n, dtype=ray_map.phi.dtype)
        tau = ray_map.tau0[..., None] + ray_map.dtau[..., None] * knots
        c = lambda a: jnp.asarray(a).astype(dtype)  # noqa: E731
        return cls(
            c(ray_map.alpha_sh),
            c(tau),
            c(1.0 / ray_map.dtau),
            c(ray_map.phi),
            c(ray_map.slope * ray_map.dtau[..., None]),
        )

    def escape_angle(self, alpha):
        """Escape angle (radians) at local angles `alpha`; the `RayMap` cubic Hermite
        interpolant, meaningful where `alpha > alpha_sh`, finite everywhere."""
        n = self.phi.shape[0]
        gap = alpha - self.alpha_sh
        tau0 = self.tau[0]
        floor_gap = jnp.exp(tau0)
        tau = jnp.log(jnp.maximum(gap, floor_gap))
        i = jnp.clip(jnp.floor((tau - tau0) * self.inv_dtau).astype(jnp.int32), 0, n - 2)
        # The fraction against the knot's own tau: no loss from |tau - tau0| ~ 30.
        t = (tau - self.tau[i]) * self.inv_dtau
        inside = hermite(t, self.phi[i], self.phi[i + 1], self.mslope[i], self.mslope[i + 1])
        # Below the first knot: the logarithmic law, linear in tau.
        gap_safe = jnp.where(gap > 0, gap, floor_gap)
        below = self.phi[0] + self.mslope[0] * self.inv_dtau * (jnp.log(gap_safe) - tau0)
        return jnp.where(gap < floor_gap, below, inside)


def _coverage(alpha, alpha_sh, width):
    """Fraction of a sample's footprint outside the shadow (a linear ramp over one
    sample width `width` in alpha), and the alpha of the escaping part's centre."""
    cover = jnp.clip((alpha - alpha_sh) / width + 0.5, 0.0, 1.0)
    edge = jnp.maximum(alpha, alpha_sh + 0.5 * width * (1.0 - cover))
    return cover, edge


def _geometry_centred(camera: Camera, view: MapView, row0, rows: int):
    """Camera-frame sky directions and coverage of the sample grid of rows
    `row0 .. row0+rows` of a centred camera, through the $x$ mirror symmetry.

    **Returns:** `s, c, cover` of shape `(rows k, W k)` with the direction
    $(s x, s y, -c)$, and `xs (W k,)`, `ys (rows k,)` (pixels).
    """
    k = camera.supersample
    f = camera.focal
    xs = camera.sample_x()
    ys = camera.sample_y(row0, rows)
    nxs = xs.shape[0]
    half, odd = nxs // 2, nxs % 2
    xh = jnp.abs(xs[half:])
    rho2 = xh[None, :] ** 2 + ys[:, None] ** 2
    rho = jnp.sqrt(rho2)
    alpha = arctan2(rho, jnp.broadcast_to(f, rho.shape))
    width = f / ((rho2 + f * f) * k)  # one sample's size in alpha: cos^2(alpha) / (f k)
    cover, edge = _coverage(alpha, view.alpha_sh, width)
    phi = view.escape_angle(edge)
    sin_phi, c = sin_cos(phi)
    safe = rho > 0
    s = jnp.where(safe, sin_phi / jnp.where(safe, rho, 1.0), 0.0)

    # Materialise the quarter before mirroring: XLA would otherwise fuse the map
    # look-up into every consumer of the mirrored arrays and repeat it.
    s, c, cover = jax.lax.optimization_barrier((s, c, cover))

    def mirror(a):
        return jnp.concatenate([a[:, odd:][:, ::-1], a], axis=1)

    return mirror(s), mirror(c), mirror(cover), xs, ys


def _directions_centred(s, c, xs, ys):
    return jnp.stack(
        [s * xs[None, :], s * ys[:, None], -jnp.broadcast_to(c, s.shape)], axis=-1
    )  # (rows k, W k, 3)


def _geometry_general(camera: Camera, view: MapView, row0, rows: int):
    """Camera-frame directions `(rows k, W k, 3)` and coverage of any camera."""
    k = camera.supersample
    xs = camera.sample_x()
    ys = camera.sample_y(row0, rows)
    x = jnp.broadcast_to(xs[None, :], (ys.shape[0], xs.shape[0]))
    y = jnp.broadcast_to(ys[:, None], x.shape)
    alpha, cb, sb = camera._angles(x, y, oriented=True)
    # One sample's size in alpha: d(alpha) = cos^2(angle off the image axis) d(rho)/f
    # at the image's centre, for an off-centre view the same to first order.
    f = camera.focal
    width = f / ((x * x + y * y + f * f) * k)
    cover, edge = _coverage(alpha, view.alpha_sh, width)
    phi = view.escape_angle(edge)
    sp, cp = sin_cos(phi)
    n = jnp.stack([sp * cb, sp * sb, -cp], axis=-1)
    return n, cover


def _average(radiance, rows: int, width: int, k: int):
    """Mean over each pixel's k x k samples: `(rows k, W k, 3)` -> `(rows, W, 3)`."""
    if k == 1:
        return radiance
    return radiance.reshape(rows, k, width, k, 3).mean(axis=(1, 3))


def _shade_block(camera, sky, view, row0, rows: int, centred: bool, at_origin: bool, pair: bool):
    """Radiance of pixel rows `row0 .. row0+rows`; with `pair` also of their mirror
    rows `H-row0-rows .. H-row0` (centred cameras only).

    **Returns:** `(rows, W, 3)`, or `(2 rows, W, 3)` with `pair` (the block, then
    its mirror rows, each top to bottom: the whole image when `rows` is `H/2`).
    """
    k, w = camera.supersample, camera.width
    if centred:
        s, c, cover, xs, ys = _geometry_centred(camera, view, row0, rows)
        halves = [(_directions_centred(s, c, xs, ys), cover)]
        if pair:
            halves.append((_directions_centred(s[::-1], c[::-1], xs, -ys[::-1]), cover[::-1]))
    else:
        halves = [_geometry_general(camera, view, row0, rows)]
    out = []
    for n, cov in halves:
        if not at_origin:
            n = camera.to_world(n)
        out.append(_average(sky(n) * cov[..., None], rows, w, k))
    return jnp.concatenate(out, axis=0) if pair else out[0]


def shade(camera: Camera, sky: AbstractSky, ray_map: RayMap, row0=0, rows: int | None = None):
    """Linear radiance of rows `row0 .. row0+rows` of the image, area-averaged.

    Samples that straddle the shadow edge are weighted by the fraction of their
    footprint outside the shadow (a linear ramp over one sample width in alpha), so
    the image, and its gradient with respect to distance and field of view, sees
    the edge as pixel coverage rather than a point-sampled step. The escaping part
    of such a sample takes the radiance of its centre of mass.

    **Arguments:** `camera` (one camera), `sky`, `ray_map` (built for the camera's
    distance, any dtype), `row0`, `rows` (pixel rows; default all).

    **Returns:** `(rows, W, 3)` array in the camera's dtype.
    """
    rows = camera.height if rows is None else rows
    view = MapView.of(ray_map, camera.dtype)
    return _shade_block(
        camera, sky, view, row0, rows, camera.is_centred(), camera.at_origin(), False
    )


def render_array(
    camera: Camera, sky: AbstractSky, *, accuracy: float = 1e-8
) -> Float[Array, "H W 3"]:
    """The whole image as one traceable function: works under `jit`, `vmap` (batches
    of cameras) and `grad` (with respect to any array field of camera and sky).

    **Arguments:** `camera` (one camera; distance in R_S, angles in radians), `sky`;
    `accuracy`: interpolation error of the ray map (radians).

    **Returns:** linear radiance `(H, W, 3)` in the camera's dtype; captured rays 0.
    """
    ray_map = RayMap.build(camera.distance, accuracy=accuracy)
    return shade(camera, sky, ray_map)


# ----------------------------------------------------------------- host side


def _map_dtype(dtype):
    return jnp.float64 if jax.config.read("jax_enable_x64") else dtype


@eqx.filter_jit
def _build_map(distance, accuracy):
    return RayMap.build(distance, accuracy=accuracy)


def _build_views(distances, accuracy: float, dtype) -> MapView:
    """Ray-map views of a batch of distances `(N,)`: the tables built in float64 where
    `jax_enable_x64` is on (else in `dtype`), one compiled program for any distance,
    evaluated in `dtype`."""
    d = np.asarray(distances, _map_dtype(dtype))
    maps = [_build_map(jnp.asarray(x), accuracy) for x in d]
    maps = jax.tree.map(lambda *a: jnp.stack(a), *maps)
    return MapView.of(maps, dtype)


@eqx.filter_jit
def _block_program(cameras, sky, views, row0, rows, centred, at_origin, pair):
    def one(camera, view):
        return _shade_block(camera, sky, view, row0, rows, centred, at_origin, pair)

    out = eqx.filter_vmap(one)(cameras, views)
    return out.astype(jnp.float32)


def plan_blocks(camera: Camera, chunk_samples: int = CHUNK_SAMPLES) -> dict:
    """How `render_frames` splits an image: frames and pixel rows per compiled block.

    **Returns:** a dict with `frames` (frames a block), `rows` (pixel rows a block,
    a pair of mirrored row blocks counting twice), `pair` (whether mirrored row
    pairs are used), `samples` (area samples a block holds).
    """
    if chunk_samples < 1:
        raise ValueError(f"chunk_samples={chunk_samples} must be >= 1")
    n = camera.batch_shape[0] if camera.batch_shape else 1
    k = camera.supersample
    centred = camera.is_centred()
    pair = centred and camera.height % 2 == 0
    per_row = camera.width * k * k * (2 if pair else 1)
    total_rows = camera.height // 2 if pair else camera.height
    if total_rows * per_row <= chunk_samples:
        rows = total_rows
        frames = int(min(n, max(1, chunk_samples // (total_rows * per_row))))
    else:
        rows = int(max(1, chunk_samples // per_row))
        frames = 1
    return {"frames": frames, "rows": rows, "pair": pair, "samples": frames * rows * per_row}


def _starts(total, step):
    """Block starts covering `range(total)` with blocks of `step`; the last block
    overlaps the previous one instead of running past the end."""
    return [(s, min(s, total - step)) for s in range(0, total, step)]


def render_frames(
    cameras: Camera,
    sky: AbstractSky,
    *,
    accuracy: float = 1e-8,
    chunk_samples: int = CHUNK_SAMPLES,
    progress: bool | None = None,
    dtype=None,
) -> np.ndarray:
    """Render a batch of cameras (animation frames) in compiled blocks.

    Each block is one compiled call over several frames (`jax.vmap` over the camera
    pytree) and a band of pixel rows, at most `chunk_samples` area samples in all;
    the same program serves every block, so memory stays bounded for any image size
    and any number of frames.

    **Arguments:**
    - `cameras`: a `Camera` with a leading batch axis (`stack_cameras`,
      `approach`, `orbit`, `pan`, `zoom`), or a single camera.
    - `sky`: an `AbstractSky` (shared by all frames).
    - `accuracy`: interpolation error of the ray map (radians).
    - `chunk_samples`: area samples a block (memory: about 100 bytes each).
    - `progress`: a progress bar (`None`: shown once the render has taken 2 s).
    - `dtype`: the dtype pixels are computed in (default the cameras'); the ray map
      is built in float64 where `jax_enable_x64` is on.

    **Returns:** linear float32 RGB `(N, H, W, 3)` (`(H, W, 3)` for one camera);
    captured rays are 0.
    """
    single = cameras.batch_shape == ()
    if single:
        cameras = jax.tree.map(lambda a: a[None], cameras)
    if len(cameras.batch_shape) != 1:
        raise ValueError(f"cameras have batch shape {cameras.batch_shape}; expected (N,)")
    dtype = jnp.dtype(cameras.dtype if dtype is None else dtype)
    cameras = jax.tree.map(lambda a: a.astype(dtype), cameras)
    plan = plan_blocks(cameras, chunk_samples)
    n, h, w = cameras.batch_shape[0], cameras.height, cameras.width
    centred, at_origin, pair = cameras.is_centred(), cameras.at_origin(), plan["pair"]
    views = _build_views(cameras.distance, float(accuracy), dtype)
    fb, rows = plan["frames"], plan["rows"]
    total_rows = h // 2 if pair else h
    frame_blocks = _starts(n, fb)
    row_blocks = _starts(total_rows, rows)
    bar = None
    count = len(frame_blocks) * len(row_blocks)
    if count == 1:  # one block holds the whole batch, rows in image order
        block = _block_program(cameras, sky, views, jnp.asarray(0, dtype), rows, centred,
                               at_origin, pair)  # fmt: skip
        out = np.array(block)  # a writable NumPy copy
        return out[0] if single else out
    out = np.empty((n, h, w, 3), np.float32)
    if count > 1 and progress is not False:
        from tqdm.auto import tqdm

        bar = tqdm(total=count, desc="render", unit="block", delay=0 if progress else 2.0,
                   leave=False)  # fmt: skip

    def store(task, block):
        (f0, fs), (r0, rs) = task
        block = np.asarray(block)[f0 - fs :]
        frames = slice(f0, fs + fb)
        if pair:
            out[frames, r0 : rs + rows] = block[:, r0 - rs : rows]
            out[frames, h - rs - rows : h - r0] = block[:, rows : 2 * rows - (r0 - rs)]
        else:
            out[frames, r0 : rs + rows] = block[:, r0 - rs :]
        if bar is not None:
            bar.update(1)

    pending = None
    try:
        for fblock in frame_blocks:
            fs = fblock[1]
            cams = jax.tree.map(lambda a: a[fs : fs + fb], cameras)
            vws = jax.tree.map(lambda a: a[fs : fs + fb], views)
            for rblock in row_blocks:
                # Dispatch the next block before copying the previous one to the host.
                result = _block_program(
                    cams, sky, vws, jnp.asarray(rblock[1], dtype), rows, centred, at_origin,
                    pair,
                )  # fmt: skip
                if pending is not None:
                    store(*pending)
                pending = ((fblock, rblock), result)
        store(*pending)
    finally:
        if bar is not None:
            bar.close()
    return out[0] if single else out


def render(
    camera: Camera,
    sky: AbstractSky,
    *,
    accuracy: float = 1e-8,
    chunk_samples: int = CHUNK_SAMPLES,
    progress: bool | None = None,
    dtype=None,
) -> np.ndarray:
    """Render what `camera` sees of `sky` around the black hole.

    Rendered in compiled blocks of at most `chunk_samples` area samples (one program
    for all blocks), so memory stays bounded for any image size: an 8192 x 8192
    image needs its 0.8 GB of output and a few hundred MB besides.

    **Arguments:**
    - `camera`: a `Camera` (distance in R_S, field of view in radians, size).
    - `sky`: an `AbstractSky` (sum skies with `+`).
    - `accuracy`: interpolation error of the ray map (radians).
    - `chunk_samples`: area samples a block.
    - `progress`: show a progress bar (default: once the render has taken 2 s).
    - `dtype`: dtype the pixels are computed in (default the camera's; float32 is
      about twice as fast and keeps sky directions within 0.01 pixel).

    **Returns:** linear float32 RGB image `(H, W, 3)`; captured rays are 0.
    """
    if camera.batch_shape != ():
        raise ValueError(
            f"render takes one camera; got a batch of shape {camera.batch_shape} "
            "(use render_frames)"
        )
    return render_frames(
        camera, sky, accuracy=accuracy, chunk_samples=chunk_samples, progress=progress,
        dtype=dtype,
    )  # fmt: skip


def sky_directions(camera: Camera, *, accuracy: float = 1e-8, dtype=None):
    """The world sky direction and shadow coverage of every area sample, by the same
    code path as `render` (for checks and benchmarks).

    **Returns:** `directions (H k, W k, 3)` (unit vectors; meaningless where the
    coverage is 0) and `coverage (H k, W k)` in [0, 1], as NumPy arrays.
    """
    dtype = jnp.dtype(camera.dtype if dtype is None else dtype)
    camera = jax.tree.map(lambda a: a.astype(dtype), camera)
    view = jax.tree.map(lambda a: a[0], _build_views(camera.distance[None], float(accuracy), dtype))
    n, cover = _directions_program(camera, view, camera.is_centred(), camera.at_origin())
    return np.asarray(n), np.asarray(cover)


@eqx.filter_jit
def _directions_program(camera, view, centred, at_origin):
    if centred:
        s, c, cover, xs, ys = _geometry_centred(camera, view, 0, camera.height)
        n = _directions_centred(s, c, xs, ys)
    else:
        n, cover = _geometry_general(camera, view, 0, camera.height)
    if not at_origin:
        n = camera.to_world(n)
    return n, cover


def block_memory(
    camera: Camera, sky: AbstractSky, *, chunk_samples: int = CHUNK_SAMPLES, dtype=None
) -> dict:
    """Memory of the compiled block program `render` would run for `camera` (compiled,
    not run): XLA's own accounting, in bytes.

    **Returns:** a dict with `temp`, `output`, `arguments` (bytes of one block) and
    `plan` (`plan_blocks`). The whole render needs this plus its float32 output
    image on the host.
    """
    single = camera.batch_shape == ()
    cameras = jax.tree.map(lambda a: a[None], camera) if single else camera
    dtype = jnp.dtype(cameras.dtype if dtype is None else dtype)
    cameras = jax.tree.map(lambda a: a.astype(dtype), cameras)
    plan = plan_blocks(cameras, chunk_samples)
    fb = plan["frames"]
    cams = jax.tree.map(lambda a: a[:fb], cameras)
    views = jax.tree.map(lambda a: a[:fb], _build_views(cams.distance, 1e-6, dtype))
    lowered = _block_program.lower(
        cams, sky, views, jnp.asarray(0, dtype), plan["rows"], cameras.is_centred(),
        cameras.at_origin(), plan["pair"],
    )  # fmt: skip
    stats = lowered.compile().compiled.memory_analysis()
    return {
        "temp": int(stats.temp_size_in_bytes),
        "output": int(stats.output_size_in_bytes),
        "arguments": int(stats.argument_size_in_bytes),
        "plan": plan,
    }
