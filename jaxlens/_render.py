"""The host driver: every scene, every frame, in compiled blocks of bounded size.

`render(scene)` plans the scene (`plan`), builds the ray map of each frame's distance
once (float64 where `jax_enable_x64` is on, whatever the pixel dtype), and runs one
compiled program (`_kernel.shade`, `vmap`ped over the frames of a block) for every
block of frames and pixel rows, dispatching the next block before copying the last
one to the host, with a progress bar on long renders. Moving cameras, redshift and the
disk get the same blocks, memory bound and progress as a bare scene.

`render_array(scene)` is the same image as one traceable function, for `jit`, `vmap`
and `grad` with respect to any array field of the scene.

With `psf=` (a `_psf.AbstractPSF`), either renders the camera's frame enlarged by the
PSF's margin on every side at the same focal length in pixels (`_with_margin`), blurs
each channel by FFT and returns the original frame: what a fit compares with an image.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import _kernel
from ._camera import MAX_SIDE, Camera
from ._compile import ahead, program
from ._plan import CHUNK_SAMPLES, Plan, frame, plan, starts
from ._psf import AbstractPSF
from ._raymap import RayMap, placeholder, tabulate
from ._scene import Scene
from ._sky import AbstractSky
from ._trace import TABLE_SETTINGS
from ._util import concrete, host_driver, is_concrete


def as_scene(scene_or_camera, sky: AbstractSky | None = None, accuracy=None) -> Scene:
    """A `Scene` from a `Scene`, or from a camera and a sky (the shorthand
    `render(camera, sky)`); `accuracy` (radians), if given, replaces the scene's."""
    if isinstance(scene_or_camera, Scene):
        if sky is not None:
            raise ValueError("render(scene, sky): a Scene carries its sky; pass one or the other")
        scene = scene_or_camera
        if accuracy is not None and accuracy != scene.accuracy:
            scene = dataclasses.replace(scene, accuracy=accuracy)
        return scene
    if not isinstance(scene_or_camera, Camera):
        raise ValueError(f"expected a Scene or a Camera, got {type(scene_or_camera).__name__}")
    if sky is None:
        raise ValueError("render(camera, sky): a sky is needed with a camera")
    return Scene(scene_or_camera, sky, accuracy=1e-8 if accuracy is None else accuracy)


def _map_dtype(dtype):
    return jnp.float64 if jax.config.read("jax_enable_x64") else dtype


def ray_maps(distances, accuracy: float, dtype, radius=None) -> RayMap:
    """Ray maps of a batch of distances `(N,)` (units of R_S), stacked: built in
    float64 where `jax_enable_x64` is on (else in `dtype`), evaluated in `dtype`;
    with `radius` (the sky's sphere, beyond every distance), of its crossing.

    Each is `RayMap.build`'s (one compiled program for every distance of an accuracy,
    as `trace`'s table is built, `TABLE_SETTINGS`; the tables of the last distances
    kept, so the next render from the same place reuses its map), put in the pixel
    dtype with a batch axis on the host: no eager op (each a small compile in a fresh
    process) between it and the block program."""
    d = np.asarray(distances, _map_dtype(dtype)).reshape(-1)
    r = None if radius is None else np.asarray(radius, d.dtype)
    maps = [
        jax.tree.map(
            lambda a: np.asarray(a, dtype)[None],
            RayMap.build(x, accuracy=accuracy, radius=r, **TABLE_SETTINGS),
        )  # fmt: skip
        for x in d
    ]
    # Small tables (a few thousand knots): placed, and joined, on the host.
    return jax.tree.map(lambda *a: jax.device_put(np.concatenate(a)), *maps)


def _block_body(scene, plan, maps, row0, rows, pair):
    # vmap over the frames of the camera batch (and their ray maps) only. The scene's
    # values were `verify`ed on the host: no error callback, so the program can be
    # kept in the persistent compilation cache.
    def one(camera, m):
        s = eqx.tree_at(lambda s: s.camera, scene, camera)
        return _kernel.shade(s, plan, m, row0, rows, pair, check=False)

    if scene.camera.batch_shape == (1,):
        # One frame (every still image): no batching pass over the kernel's trace.
        camera, m = jax.tree.map(lambda a: a[0], (scene.camera, maps))
        return one(camera, m)[None].astype(jnp.float32)
    return eqx.filter_vmap(one)(scene.camera, maps).astype(jnp.float32)


# One program for every block of every render of a kind (XLA's default options: the
# block runs many times on much data).
_block = program(_block_body, profile="xla")


def _prepare(scene: Scene, dtype):
    """The scene with a batch axis on its camera, in the pixel dtype."""
    cam = scene.camera
    if len(cam.batch_shape) > 1:
        raise ValueError(f"camera has batch shape {cam.batch_shape}; expected () or (N,)")
    dtype = _kernel.pixel_dtype(cam.dtype if dtype is None else dtype)
    # On the host (a few numbers a frame): no eager device op, each a small compile.
    cam = jax.tree.map(lambda a: np.asarray(a, dtype), cam)
    if cam.batch_shape == ():
        cam = jax.tree.map(lambda a: a[None], cam)
    return eqx.tree_at(lambda s: s.camera, scene, cam), dtype


def _maps_for(scene, plan, dtype):
    if plan.geometry != "table":
        return None
    return ray_maps(scene.camera.distance, scene.accuracy, dtype, scene.source_distance)


def _ahead(scene, p: Plan, dtype) -> tuple:
    """The block program's call for placeholder ray maps of the right shapes, for
    `ahead`: it compiles while the ray maps' own program compiles and runs (none
    without ray maps)."""
    if p.geometry != "table":
        return ()
    fb, accuracy = p.frames, float(scene.accuracy)
    maps = _map_placeholder(fb, accuracy, dtype)
    return ((_block, frame(scene, slice(0, fb)), p.kernel_key(), maps,
             np.asarray(0, scene.camera.dtype), p.rows, p.pair),)  # fmt: skip


def _map_placeholder(frames: int, accuracy: float, dtype) -> RayMap:
    """Zeros shaped as `frames` stacked `ray_maps` results: known without tracing the
    table's program."""
    return placeholder(dtype, (frames,), accuracy=accuracy, **TABLE_SETTINGS)


def render(
    scene: Scene | Camera,
    sky: AbstractSky | None = None,
    *,
    accuracy: float | None = None,
    psf: AbstractPSF | None = None,
    chunk_samples: int = CHUNK_SAMPLES,
    progress: bool | None = None,
    dtype=None,
) -> np.ndarray:
    """Render what a scene's camera sees (each of its frames, if it holds a batch).

    Rendered in compiled blocks of at most `chunk_samples` area samples (one program
    for all blocks), so memory stays bounded for any image size and any effects: an
    8192 x 8192 image needs its 0.8 GB of float32 output and a few hundred MB besides.

    **Arguments:**
    - `scene`: a `Scene`, or a `Camera` followed by `sky` (an `AbstractSky`): the
      shorthand for `Scene(camera, sky)`. A camera with a batch axis (`approach`,
      `orbit`, `pan`, `zoom`, `stack_cameras`) renders one image a frame.
    - `accuracy`: replaces the scene's ray-map accuracy (radians).
    - `psf`: a point-spread function (`GaussianPSF(sigma_px)`, `ImagePSF(image)`;
      widths in pixels of this image), or `None`. The camera's frame is rendered
      enlarged by the PSF's `margin_px` on every side at the same focal length in
      pixels (the FOV widened to match, so every pixel sees the same rays), each
      frame's channels are blurred by FFT (in float64 where `jax_enable_x64` is on)
      and the original frame is returned: the image a fit with this PSF compares with
      the data. The total light is kept but for what crosses the frame's edge. A PSF
      whose margin makes a frame of more than 2**26 pixels is a `ValueError`.
    - `chunk_samples`: area samples a block (memory: about 100 bytes each).
    - `progress`: a progress bar (`None`: shown once the render has taken 2 s).
    - `dtype`: the dtype pixels are computed in, float32 or float64 (default the
      camera's; float32 is about twice as fast and keeps sky directions within 0.01
      pixel); another is a `ValueError`.

    **Returns:** linear float32 RGB `(H, W, 3)`, or `(N, H, W, 3)` for a batch of
    frames; captured rays are 0. A host driver: under `jit`, `vmap` or `grad` use
    `render_array` (one compiled program, differentiable), which this raises a
    `TypeError` to say.
    """
    scene = as_scene(scene, sky, accuracy)
    host_driver("render", "use jaxlens.render_array there", scene, psf)
    single = scene.camera.batch_shape == ()
    if psf is not None:
        scene = _with_margin(scene, psf)
    out = _run(*_prepared(scene, chunk_samples, dtype), progress)
    if psf is not None:
        # A frame at a time (the device holds one frame's transforms).
        blur = np.float64 if jax.config.read("jax_enable_x64") else np.float32
        out = np.stack([np.asarray(_blur(psf, f, blur, np.float32)) for f in out])
    return out[0] if single else out


def _with_margin(scene: Scene, psf) -> Scene:
    """The scene with its camera's frame enlarged by `psf.margin_px` pixels on every
    side at the same focal length in pixels, $f = (W/2)/\\tan(\\mathrm{FOV}/2)$: the
    FOV widened to $2 \\arctan(\\tan(\\mathrm{FOV}/2)\\,W'/W)$, so pixel $(i, j)$ of the
    frame is pixel $(i + m, j + m)$ of the enlarged one, with the same rays. Works with
    traced camera values (`render_array` under `jit`)."""
    if not isinstance(psf, AbstractPSF):
        raise ValueError(
            f"psf must be a PSF (jaxlens.GaussianPSF, jaxlens.ImagePSF) or None; got "
            f"{type(psf).__name__}"
        )
    cam = scene.camera
    m = psf.margin_px
    hp, wp = psf.padded_shape((cam.height, cam.width))
    if max(hp, wp) > MAX_SIDE:
        raise ValueError(
            f"{type(psf).__name__}'s margin of {m:,} pixels makes the {cam.height:,} x "
            f"{cam.width:,} frame {hp:,} x {wp:,} pixels: a side of at most {MAX_SIDE:,}"
        )
    if m == 0:
        return scene
    fov = concrete(cam.fov)
    if fov is None:  # traced: the same formula in the camera's dtype
        fov = 2.0 * jnp.arctan(jnp.tan(0.5 * cam.fov) * (wp / cam.width))
    else:  # known: in float64 on the host, then rounded to the camera's dtype
        fov = 2.0 * np.arctan(np.tan(0.5 * fov.astype(np.float64)) * (wp / cam.width))
    big = Camera(cam.distance, fov, wp, hp, yaw=cam.yaw, pitch=cam.pitch, roll=cam.roll,
                 azimuth=cam.azimuth, elevation=cam.elevation, supersample=cam.supersample,
                 sampling=cam.sampling, dtype=cam.dtype)  # fmt: skip
    return eqx.tree_at(lambda s: s.camera, scene, big)


def _blur_body(psf, image, dtype, out_dtype):
    return psf.apply(image.astype(dtype)).astype(out_dtype)


# One program a PSF kind, frame size and dtype: a frame's channels blurred and cropped,
# computed in `dtype`, returned in `out_dtype`.
_blur = program(_blur_body, profile="xla")


def _prepared(scene: Scene, chunk_samples: int, dtype):
    """`(scene, plan, ray maps)` of a render: checked, with a frame axis, planned."""
    _kernel.verify(scene, dtype)
    scene, dtype = _prepare(scene, dtype)
    p = plan(scene, chunk_samples=chunk_samples)
    with ahead(*_ahead(scene, p, dtype)):
        maps = _maps_for(scene, p, dtype)
    return scene, p, maps


def render_share(scene: Scene, stage, index: int, count: int, *,
                 chunk_samples: int = CHUNK_SAMPLES, dtype=None):  # fmt: skip
    """`render(scene)` as one of `count` processes (a scene of one camera): process
    `index` renders its share of the blocks into `stage` (a `_multi.Stage`; blocks
    already there are skipped), and process 0 then waits for every block and puts the
    image together, bitwise `render`'s (the same blocks and programs).
    **Returns:** the image on process 0, `None` on the others."""
    from tqdm.auto import tqdm

    scene, p, maps = _prepared(scene, chunk_samples, dtype)
    tasks = _tasks(scene, p)
    with tqdm(total=len(tasks), desc="render", unit="block", delay=2.0, leave=False,
              disable=index != 0) as bar:  # fmt: skip
        stage.fill([range(k, k + 1) for k in range(len(tasks))],
                   lambda k: [_call(scene, p, maps, *tasks[k])], index, count, bar)  # fmt: skip
        if index != 0:
            return None
        stage.wait(len(tasks), bar)
    cam = scene.camera
    out = np.empty((cam.batch_shape[0], cam.height, cam.width, 3), np.float32)
    for k, task in enumerate(tasks):
        _store(out, p, task, stage.load(k))
    return out[0]


def _tasks(scene, p: Plan) -> list:
    """The blocks of a render, in order: `((f0, fs), (r0, rs))` (first new frame and
    row, and where the block starts)."""
    cam = scene.camera
    h = cam.height // 2 if p.pair else cam.height
    return [(f, r) for f in starts(cam.batch_shape[0], p.frames) for r in starts(h, p.rows)]


def _call(scene, p: Plan, maps, fblock, rblock):
    """One block's pixels (dispatched, not waited for)."""
    f0, r0 = fblock[1], rblock[1]
    fb, n = p.frames, scene.camera.batch_shape[0]
    m = maps if fb == n else jax.tree.map(lambda a: a[f0 : f0 + fb], maps)
    return _block(frame(scene, slice(f0, f0 + fb)), p.kernel_key(), m,
                  np.asarray(r0, scene.camera.dtype), p.rows, p.pair)  # fmt: skip


def _store(out, p: Plan, task, block) -> None:
    """Copy a block's new rows into the image batch `out` (N, H, W, 3)."""
    (f0, fs), (r0, rs) = task
    h, rows = out.shape[1], p.rows
    block = np.asarray(block)[f0 - fs :]
    frames = slice(f0, fs + p.frames)
    if p.pair:
        out[frames, r0 : rs + rows] = block[:, r0 - rs : rows]
        out[frames, h - rs - rows : h - r0] = block[:, rows : 2 * rows - (r0 - rs)]
    else:
        out[frames, r0 : rs + rows] = block[:, r0 - rs :]


def render_frames(cameras: Camera, sky: AbstractSky, **kwargs) -> np.ndarray:
    """`render(Scene(cameras, sky), **kwargs)`: the frames of a batch of cameras."""
    return render(cameras, sky, **kwargs)


def _run(scene, p: Plan, maps, progress):
    cam = scene.camera
    if p.blocks == 1:  # one block holds the whole batch, rows in image order
        return np.array(_call(scene, p, maps, (0, 0), (0, 0)))  # a writable NumPy copy
    out = np.empty((cam.batch_shape[0], cam.height, cam.width, 3), np.float32)
    bar = None
    if progress is not False:
        from tqdm.auto import tqdm

        bar = tqdm(total=p.blocks, desc="render", unit="block", delay=0 if progress else 2.0,
                   leave=False)  # fmt: skip
    pending = None
    try:
        for task in _tasks(scene, p):
            # Dispatch the next block before copying the previous one to the host.
            result = _call(scene, p, maps, *task)
            if pending is not None:
                _store(out, p, *pending)
                if bar is not None:
                    bar.update(1)
            pending = (task, result)
        _store(out, p, *pending)
        if bar is not None:
            bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return out


def render_array(
    scene: Scene | Camera,
    sky: AbstractSky | None = None,
    *,
    accuracy: float | None = None,
    plan: Plan | None = None,
    ray_map: RayMap | None = None,
    psf: AbstractPSF | None = None,
) -> Float[Array, "H W 3"]:
    """The image of a scene (one camera) as one traceable function: works under `jit`,
    `vmap` (batches of scenes) and `grad` (with respect to any array field of camera,
    sky, motion and disk).

    **Arguments:** `scene` (a `Scene`, or a `Camera` and a `sky`); `accuracy`
    (radians, replaces the scene's); `plan`: a `Plan` to follow (default: `plan(scene)`
    for the whole image as one block; under tracing the safe one); `ray_map`: the
    `RayMap` of the camera's distance if built already (default: built inside, so
    gradients with respect to the distance flow through the table; for a sky on a
    sphere that the plan reads from a table, that of $(D, R)$:
    `RayMap.build(D, radius=R)`); `psf`: a PSF, as
    in `render` (the frame rendered on the PSF's margin, blurred, cropped; gradients
    flow to the PSF's array fields too), or `None`. With a PSF, `plan` must be `None`
    (the enlarged frame is planned here).

    **Returns:** linear radiance `(H, W, 3)` in the camera's dtype (float32 or
    float64; another is a `ValueError`); captured rays 0. A bad traced value (distance
    <= 1, FOV outside (0, pi), a camera angle, or any field of the sky, motion or disk
    outside its range, see `limits` on each) raises an error at run time rather than
    giving a NaN image.

    Called eagerly (every value concrete), it checks the values on the host
    (`ValueError`) and runs as one compiled program, kept for later calls with the
    same kind of scene and the same sizes; under `jit`, `vmap` or `grad` it is part of
    the caller's program.
    """
    from . import _plan

    scene = as_scene(scene, sky, accuracy)
    if psf is not None:
        if plan is not None:
            raise ValueError(
                "render_array(..., psf=) plans the frame enlarged by the PSF's margin itself: "
                "pass plan=None"
            )
        big = render_array(_with_margin(scene, psf), ray_map=ray_map)
        return _blur(psf, big, big.dtype, big.dtype)
    eager = is_concrete((scene, ray_map))
    if eager:
        _kernel.verify(scene)  # the same messages, as ValueError
    else:
        scene = _kernel.checked(scene)
    cam = scene.camera
    if cam.batch_shape != ():
        raise ValueError(
            f"render_array takes one camera; got a batch of shape {cam.batch_shape} "
            "(use jax.vmap, or render for frames)"
        )
    # The whole image as one block, also for a disk's smaller blocks (a plan of several
    # would gather the disk's rays for one block only, and is refused below).
    whole = cam.width * cam.height * cam.supersample**2 * 2 * _plan.DISK_BLOCK_DIVISOR
    p = _plan.plan(scene, chunk_samples=whole) if plan is None else plan
    if p.disk and p.disk_rays is not None and p.blocks != 1:
        raise ValueError(
            f"plan gathers {p.disk_rays} disk rays a block of {p.blocks} blocks, not for the "
            "whole image: pass a plan of one block (jl.plan(scene, chunk_samples=...) large "
            "enough) or one with disk_rays=None"
        )
    if eager:
        # Called with concrete values: one compiled program, kept for the next call
        # with the same kind of scene and sizes (not op by op).
        return _render_array_compiled(scene, p.kernel_key(), ray_map)
    return _render_array(scene, p, ray_map)


def _render_array(scene, p: Plan, ray_map):
    # The scene's values are checked already: on the host (eager) or by `checked`.
    cam = scene.camera
    if p.geometry == "table" and ray_map is None:
        # The distance is checked (`checked`/`verify`): no second error callback here.
        ray_map = tabulate(cam.distance, accuracy=scene.accuracy, radius=scene.source_distance,
                           **TABLE_SETTINGS)  # fmt: skip
    if ray_map is not None:
        ray_map = ray_map.astype(cam.dtype)
    rows = cam.height // 2 if p.pair else cam.height
    return _kernel.shade(scene, p, ray_map, 0, rows, p.pair, check=False)


# The scene `verify`ed on the host: no error callback in the program.
_render_array_compiled = eqx.filter_jit(_render_array)


def sky_directions(camera: Camera, *, accuracy: float = 1e-8, dtype=None):
    """The world sky direction and shadow coverage of every area sample of a static
    camera's image, by the same code path as `render` (for checks and benchmarks).

    **Returns:** `directions (H k, W k, 3)` (unit vectors; meaningless where the
    coverage is 0) and `coverage (H k, W k)` in [0, 1], as NumPy arrays.
    """
    from ._sky import Uniform

    scene, dtype = _prepare(Scene(camera, Uniform(0.0), accuracy=accuracy), dtype)
    p = plan(scene, chunk_samples=1 << 62)
    maps = ray_maps(scene.camera.distance, accuracy, dtype)
    m = jax.tree.map(lambda a: a[0], maps)
    n, cover = _directions(frame(scene, 0), p.kernel_key(), m, camera.height)
    return np.asarray(n), np.asarray(cover)


@eqx.filter_jit
def _directions(scene, plan, ray_map, rows):
    return _kernel.directions(scene, plan, ray_map, 0, rows)


def block_memory(
    scene: Scene | Camera,
    sky: AbstractSky | None = None,
    *,
    chunk_samples: int = CHUNK_SAMPLES,
    dtype=None,
) -> dict:
    """Memory of the compiled block program `render` would run for a scene (compiled,
    not run): XLA's own accounting, in bytes.

    **Returns:** a dict with `temp`, `output`, `arguments` (bytes of one block) and
    `plan` (the `Plan`). The whole render needs this plus its float32 output image on
    the host.
    """
    scene, dtype = _prepare(as_scene(scene, sky), dtype)
    p = plan(scene, chunk_samples=chunk_samples)
    part = frame(scene, slice(0, p.frames))
    maps = _maps_for(part, p, dtype)
    lowered = _block.lower(part, p.kernel_key(), maps, jnp.asarray(0, dtype), p.rows, p.pair)
    stats = lowered.compile().memory_analysis()
    return {
        "temp": int(stats.temp_size_in_bytes),
        "output": int(stats.output_size_in_bytes),
        "arguments": int(stats.argument_size_in_bytes),
        "plan": p,
    }
