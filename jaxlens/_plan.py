"""The plan of a scene: which stages and which escape-angle source it compiles, how the
image is blocked, and why.

`plan(scene)` decides in Python, from the scene's structure and (where they are
concrete) its values:

- **aberration**: none for a static camera; `"radial"` for a fall along the line to
  the hole (it only rescales $\\alpha$); `"boost"` for a tangential motion (3-vectors
  boosted to the static frame). Either way the static ray map stays one-dimensional.
- **geometry** (the source of $\\Phi$): the alpha table (`RayMap`, built once per
  distance); the weak-field series where every ray in view has its periapsis far out
  and the series' rigorous truncation bound is below the accuracy (and the view is
  small enough that the table's build is not amortised); or `"trace"`, the exact
  closed form per ray, when the scene forces it; for a sky on a sphere
  (`Scene.source_distance` $R$): the ray map of $(D, R)$ where $R \\ge 1.25 D$ and
  $D \\ge 1.5$ (one crossing a ray), `"crossing"` (that one crossing, exact per ray)
  for a nearer sphere beyond the camera, else `"crossings"`: each ray's crossings of
  it (up to two), exact per ray.
  A scene that forces `"weak_field"`
  keeps its accuracy: where the series' bound over the view is not below it (or cannot
  be computed, the camera's values traced), `plan` raises a `ValueError` with the bound
  and what to do instead.
- **redshift**, **disk**: present when the scene names them; the disk stage follows
  only the rays that can reach the disk, gathered into a batch whose size is the
  largest count over the blocks (rounded up to one of 16 steps).
- **blocking**: frames and pixel rows a compiled block holds (at most `chunk_samples`
  area samples), and whether mirrored row pairs are used.

Under `jit`/`grad` of the scene the values are unknown and the plan stays on the safe
side: the table, every ray masked for the disk.
"""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _kernel
from ._util import concrete as concrete_value, is_concrete
from ._weak import WEAK_MAX_SAMPLES, weak_field_series

CHUNK_SAMPLES = 1 << 21  # default area samples a compiled block holds
_BUCKETS = 16
DISK_BLOCK_DIVISOR = 4  # a disk scene's blocks hold chunk_samples / 4 area samples


@dataclasses.dataclass(frozen=True)
class Plan:
    """What the renderer compiles for a scene (hashable: it keys the compiled program).

    **Fields:**
    - `geometry`: `"table"`, `"weak_field"` or `"trace"` (the source of $\\Phi$), or
      `"crossings"` (a sky on a sphere, `Scene.source_distance`: the exact crossings of
      it per ray, up to two; `"crossing"`: the one crossing of a sphere beyond the
      camera; a sphere at $R \\ge 1.25 D$ is read from its `"table"`), or `"plane"`
      (`Scene.source_plane`: each ray's exact crossing of the plane).
    - `aberration`: `None`, `"radial"` or `"boost"`; `redshift`: `None`,
      `"bolometric"` or `"spectral"`; `disk`: whether disk rays are traced.
    - `disk_rays`: rays a block follows through the disk plane (`None`: all, masked);
      `disk_reach`: the most rays of one block that can reach the disk (before
      rounding up to `disk_rays`).
    - `centred`, `at_origin`: the camera's view is unrotated / its frame is the sky's.
    - `symmetric`: the mirror-symmetric path (centred, no tangential motion, no disk).
    - `frames`, `rows`, `pair`: frames and pixel rows a block holds (a mirrored pair
      of row blocks counting once), whether mirrored row pairs are used.
    - `blocks`: compiled calls for the whole batch; `samples`: area samples a block.
    - `weak_bound`: largest truncation bound of the weak-field series over the view
      (radians), where computed.
    - `reasons`: one line per decision.
    """

    geometry: str
    aberration: str | None
    redshift: str | None
    disk: bool
    disk_rays: int | None
    disk_reach: int | None
    centred: bool
    at_origin: bool
    symmetric: bool
    frames: int
    rows: int
    pair: bool
    blocks: int
    samples: int
    weak_bound: float | None
    reasons: tuple[str, ...]

    @property
    def stages(self) -> tuple[str, ...]:
        """The stages in the compiled program, in order."""
        out = ["samples"]
        if self.aberration is not None:
            out.append("aberration")
        if self.redshift is not None:
            out.append("redshift")
        out += [self.geometry, "sky"]
        if self.disk:
            out.append("disk")
        return tuple(out)

    def kernel_key(self) -> "Plan":
        """The plan with what does not change the compiled kernel blanked."""
        return dataclasses.replace(
            self, disk_reach=None, blocks=0, samples=0, weak_bound=None, reasons=()
        )

    def __str__(self):
        head = (
            f"geometry={self.geometry}, aberration={self.aberration}, redshift="
            f"{self.redshift}, disk={'traced' if self.disk else 'none'}; {self.blocks} "
            f"block(s) of {self.frames} frame(s) x {self.rows} row(s)"
            + (" (mirrored pairs)" if self.pair else "")
        )
        return "\n".join([head] + [f"  - {r}" for r in self.reasons])


def blocking(camera, chunk_samples: int = CHUNK_SAMPLES, *, symmetric: bool = True) -> dict:
    """How an image (or a batch of frames) is split into compiled blocks.

    **Returns:** a dict with `frames` (frames a block), `rows` (pixel rows a block; a
    pair of mirrored row blocks counts once), `pair` (whether mirrored row pairs are
    used), `samples` (area samples a block holds), `blocks` (blocks in all).
    """
    if not (isinstance(chunk_samples, int) and chunk_samples >= 1):
        raise ValueError(f"chunk_samples={chunk_samples!r} must be a whole number >= 1")
    n = camera.batch_shape[0] if camera.batch_shape else 1
    k = camera.supersample
    pair = symmetric and camera.height % 2 == 0
    per_row = camera.width * k * k * (2 if pair else 1)
    total_rows = camera.height // 2 if pair else camera.height
    if total_rows * per_row <= chunk_samples:
        rows = total_rows
        frames = int(min(n, max(1, chunk_samples // (total_rows * per_row))))
    else:
        rows = int(max(1, chunk_samples // per_row))
        frames = 1
    blocks = -(-n // frames) * -(-total_rows // rows)
    return {
        "frames": frames,
        "rows": rows,
        "pair": pair,
        "samples": frames * rows * per_row,
        "blocks": blocks,
    }


def starts(total: int, step: int) -> list[tuple[int, int]]:
    """Block starts covering `range(total)` with blocks of `step`: pairs (first new
    index, start of the block); the last block overlaps the previous one instead of
    running past the end."""
    return [(s, min(s, total - step)) for s in range(0, total, step)]


def _bucket(count: int, total: int) -> int:
    """Padded size of a gathered batch: the next of 16 steps of `total` (so the disk
    batch takes at most 16 sizes)."""
    step = max(1, -(-total // _BUCKETS))
    return int(min(total, max(step, -(-count // step) * step)))


@eqx.filter_jit
def _weak_bound(scene, plan, rows):
    """The weak-field series' largest truncation bound over the static angles of one
    frame's samples (radians), as one compiled program."""
    alpha = _kernel.static_alpha(scene, plan, 0, rows)
    return jnp.max(weak_field_series(alpha, scene.camera.distance)[1])


@eqx.filter_jit
def _reach_count(scene, plan, row0, rows):
    return jnp.sum(_kernel.reach(scene, plan, row0, rows))


def frame(scene, index):
    """The scene with only frame(s) `index` (an int or a slice) of its camera batch."""
    return eqx.tree_at(lambda s: s.camera, scene, jax.tree.map(lambda a: a[index], scene.camera))


def _frames(scene):
    cam = scene.camera
    n = cam.batch_shape[0] if cam.batch_shape else 1
    for i in range(n):
        yield i, (scene if not cam.batch_shape else frame(scene, i))


def plan(scene, *, chunk_samples: int = CHUNK_SAMPLES) -> Plan:
    """Decide how a scene is rendered (see the module docstring).

    **Arguments:** `scene` (a `Scene`; its camera may hold a batch of frames);
    `chunk_samples`: area samples a compiled block may hold.

    **Returns:** a `Plan`; `str(plan)` lists each decision and its reason.
    """
    if _staging():
        # Inside a caller's `jit` with values known now: the host decisions are taken at
        # trace time, where every operation runs on its own.
        with jax.ensure_compile_time_eval():
            return _plan(scene, chunk_samples)
    # Otherwise the measurements (weak-field bound, disk reach) run as compiled
    # programs, not op by op (one small compile an operation).
    return _plan(scene, chunk_samples)


def _staging() -> bool:
    """Whether a caller's `jit` is tracing now (a value placed on the device is then a
    tracer; eagerly, placing it compiles nothing)."""
    return isinstance(jax.device_put(0.0), jax.core.Tracer)


def _forced_weak_bound(scene, base: Plan, concrete: bool) -> float:
    """The weak-field series' largest bound over a scene that forces it (radians), or a
    ValueError when it is not below the scene's accuracy: forcing the series chooses
    the method, not a looser accuracy (the table and the exact trace meet it anyway)."""
    if not concrete:
        raise ValueError(
            "method='weak_field' needs the camera's values to bound the series' error, and "
            "they are traced here: use method='auto' or 'table' under jit/grad/vmap"
        )
    cam = scene.camera
    bound = max(float(_weak_bound(one, base.kernel_key(), cam.height)) for _, one in _frames(scene))
    if not bound < scene.accuracy:
        what = (
            f"error bound {bound:.2e} rad" if math.isfinite(bound)
            else "error bound inf (rays pass near the hole, where it does not apply)"
        )  # fmt: skip
        raise ValueError(
            f"method='weak_field' is forced, but the weak-field series' {what} over this "
            f"view is not below the accuracy {scene.accuracy:.1e} rad: use method='auto' or "
            "'table' (they meet the accuracy), or an accuracy above the bound to accept "
            "the series"
        )
    return bound


# The smallest R / D whose ray map of (D, R) is taken. The crossing's azimuth has a
# square-root kink at alpha = pi/2 as R -> D (the sphere through the camera): at
# R = 1.1 D the table at accuracy 1e-8 was 1.6e-8 off there (D = 1e6), at 1.25 D and
# beyond at most 6e-9 (D = 1.6, 20, 1e6; accuracies 1e-8 and 1e-10, against
# finite_crossings on 2e5 rays).
SHELL_TABLE_MIN = 1.25


def _shell_geometry(scene, concrete: bool) -> tuple[str, str]:
    """The source of the crossings of a sky on a sphere (`Scene.source_distance`) and
    why: the ray map of $(D, R)$ for a sphere beyond a camera outside the photon sphere
    (one crossing a ray, smooth in $\\tau$ as the escape angle; $R \\ge$
    `SHELL_TABLE_MIN` $D$), else each ray's exact crossings; a `ValueError` for what
    has neither."""
    cam = scene.camera
    r = None if not concrete else concrete_value(scene.source_distance)
    d = np.asarray(cam.distance) if concrete else None
    beyond = r is not None and bool(np.all(r >= SHELL_TABLE_MIN * d) and np.all(d >= 1.5))
    if beyond and scene.method in ("auto", "table"):
        return "table", (
            f"source_distance R = {float(r):g} >= {SHELL_TABLE_MIN:g} D: the sky lies on the "
            "sphere r = R, each ray crosses it once, after its periapsis, at an azimuth as "
            "smooth in tau as the escape angle: the ray map of (D, R) "
            "(RayMap.build(..., radius=R)), interpolated per ray, a look-up as cheap as the "
            "sky at infinity's (the exact crossings per ray cost several times more a "
            "frame: benchmarks/results/source_distance.md)"
        )
    if cam.sampling == "gauss":
        raise ValueError(
            'sampling="gauss" with a source_distance needs the ray map of (D, R): a sphere '
            "beyond a camera outside the photon sphere, known values (source_distance >= "
            f"{SHELL_TABLE_MIN:g} x distance, distance >= 1.5); render others with "
            'sampling="uniform"'
        )
    if scene.method not in ("auto", "trace"):
        raise ValueError(
            f"method={scene.method!r} has no form for this source_distance (the ray map "
            f"holds the one crossing of a sphere at R >= {SHELL_TABLE_MIN:g} D, values known, "
            "the weak-field series the escape angle at infinity): use method='auto' or "
            "'trace'"
        )
    if r is not None and np.all(r > d) and np.all(d >= 1.5):
        why = (
            "method='trace' forced by the scene" if scene.method == "trace" else
            f"R = {float(r):g} < {SHELL_TABLE_MIN:g} D: the ray map of (D, R) would miss "
            "the accuracy where the crossing bends sharply (alpha near pi/2)"
        )  # fmt: skip
        return "crossing", (
            f"source_distance: the sky lies on the sphere r = R > D; {why}: each ray's one "
            "crossing of it, after its periapsis, from the exact closed form per ray "
            "(finite_crossings), the sky evaluated once a ray"
        )
    if scene.method == "trace":
        why = "method='trace' forced by the scene"
    elif r is None:
        why = "the distances are traced, so whether R > D is not known"
    elif not np.all(d >= 1.5):
        why = "the camera is inside the photon sphere (rays inside the shadow cross R too)"
    else:
        why = f"R = {float(r):g} <= D: rays cross the sphere twice, in and out"
    return "crossings", (
        f"source_distance: the sky lies on the sphere r = R; {why}: each ray's crossings "
        "of it (up to 2, their radiance added) from the exact closed form per ray "
        "(finite_crossings)"
    )


def _plan(scene, chunk_samples):
    cam = scene.camera
    reasons = []
    concrete = is_concrete((cam, scene.motion, scene.source_distance)) and (
        scene.disk is None or is_concrete(scene.disk.r_out)
    )
    if scene.motion is None:
        aberration = None
        reasons.append("static camera: no aberration, the pixel angles are the static ones")
    elif scene.motion.radial:
        aberration = "radial"
        reasons.append(
            f"{type(scene.motion).__name__}: motion along the line to the hole, so the "
            "aberration only rescales alpha (the map stays 1-D)"
        )
    else:
        aberration = "boost"
        reasons.append(
            f"{type(scene.motion).__name__}: tangential motion, pixel directions are "
            "boosted to the static frame as 3-vectors; the static map stays 1-D"
        )
    redshift = None if scene.redshift is None else scene.redshift.mode
    if redshift is None:
        reasons.append("no Redshift: colours as emitted, no frequency shift computed")
    else:
        reasons.append(
            f"Redshift({redshift!r}): g = 1/sqrt(1 - 1/D)"
            + (" x sqrt(1 - 1/R)" if scene.source_distance is not None else "")
            + (" x Doppler factor" if scene.motion is not None else "")
        )
    centred, at_origin = cam.is_centred(), cam.at_origin()
    has_disk = scene.disk is not None
    gauss = cam.sampling == "gauss"
    if gauss:
        if has_disk:
            raise ValueError(
                'sampling="gauss" does not support a Disk yet: render the disk with '
                'sampling="uniform"'
            )
        if scene.method not in ("auto", "table"):
            raise ValueError(
                f'sampling="gauss" needs the ray-map table (its thin rings solve it), not '
                f"method={scene.method!r}"
            )
        reasons.append(
            f"area-exact sampling: {cam.supersample} x {cam.supersample} Gauss-Legendre "
            "cells a pixel, the exact share of each outside the shadow edge, the thin rings "
            "of compact sources integrated across the cells; the ray map is the geometry"
        )
    symmetric = centred and aberration != "boost" and not has_disk and not gauss
    if symmetric:
        reasons.append("centred view, rays depend on |x| and |y|: a quarter of the samples "
                       "go through the escape angle, mirrored")  # fmt: skip
    block_samples = chunk_samples
    if has_disk and chunk_samples >= 2 * DISK_BLOCK_DIVISOR:
        # A ray followed through the disk plane holds several times a plain sample's
        # memory (its crossings and RK4 states): smaller blocks keep the render's peak
        # memory near a bare scene's (benchmarks/results/memory.md).
        block_samples = chunk_samples // DISK_BLOCK_DIVISOR
        reasons.append(
            f"Disk: blocks of chunk_samples / {DISK_BLOCK_DIVISOR} = {block_samples} area "
            "samples, for the memory of the traced rays"
        )
    b = blocking(cam, block_samples, symmetric=symmetric)
    samples_view = cam.width * cam.height * cam.supersample**2
    base = Plan("table", aberration, redshift, has_disk, None, None, centred, at_origin, symmetric,
                b["frames"], b["rows"], b["pair"], b["blocks"], b["samples"], None, ())  # fmt: skip

    weak_bound = None
    if scene.source_plane is not None:
        if gauss or scene.method not in ("auto", "trace"):
            raise ValueError(
                "source_plane needs each ray's exact plane crossing: uniform sampling and "
                f"method='auto' or 'trace' (got sampling={cam.sampling!r}, method="
                f"{scene.method!r})"
            )
        geometry = "plane"
        reasons.append(
            "source_plane L: the sky is read in the direction from the hole to each ray's "
            "outward crossing of the plane z = L (plane_crossings: Newton's method on the "
            "radius of the crossing sphere, an exact crossing a step); "
            "PlaneImage.at_distance(image, S, L) draws a picture S wide on it"
        )
    elif scene.source_distance is not None:
        geometry, why = _shell_geometry(scene, concrete)
        reasons.append(why)
    elif gauss:
        geometry = "table"
    elif scene.method == "weak_field":
        geometry = "weak_field"
        weak_bound = _forced_weak_bound(scene, base, concrete)
        reasons.append(
            f"method='weak_field' forced by the scene: series bound {weak_bound:.2e} rad < "
            f"accuracy {scene.accuracy:.1e}"
        )
    elif scene.method != "auto":
        geometry = scene.method
        reasons.append(f"method={scene.method!r} forced by the scene")
    elif not concrete:
        geometry = "table"
        reasons.append("camera values are traced: the view cannot be bounded, use the table")
    elif samples_view > WEAK_MAX_SAMPLES:
        geometry = "table"
        reasons.append(
            f"{samples_view} rays a view > {WEAK_MAX_SAMPLES}: the table's build is amortised "
            "and its look-up is cheaper than the weak-field series"
        )
    else:
        bounds = []
        for _, one in _frames(scene):
            bounds.append(float(_weak_bound(one, base.kernel_key(), cam.height)))
        weak_bound = max(bounds)
        if weak_bound < scene.accuracy:
            geometry = "weak_field"
            reasons.append(
                f"every ray in view has a far periapsis: weak-field series bound "
                f"{weak_bound:.2e} rad < accuracy {scene.accuracy:.1e}, no table needed"
            )
        else:
            geometry = "table"
            what = "inf (rays near the hole)" if not math.isfinite(weak_bound) else (
                f"{weak_bound:.2e} rad")  # fmt: skip
            reasons.append(
                f"weak-field bound {what} >= accuracy {scene.accuracy:.1e}: alpha table "
                "(RayMap) built once per distance, interpolated per ray"
            )
    disk_rays = None
    if has_disk:
        if concrete:
            total_rows = cam.height
            counts = [
                int(_reach_count(one, base.kernel_key(), jnp.asarray(r0), b["rows"]))
                for _, one in _frames(scene)
                for _, r0 in starts(total_rows, b["rows"])
            ]
            per_block = b["rows"] * cam.width * cam.supersample**2
            disk_rays = _bucket(max(counts), per_block)
            reasons.append(
                f"Disk: at most {max(counts)} of a block's {per_block} rays can come within "
                f"r_out = {float(np.max(scene.disk.r_out)):g}; only they are traced through "
                f"the disk plane ({scene.disk.crossings} crossings x {scene.disk.steps} RK4 "
                f"steps), in batches of {disk_rays}"
            )
        else:
            reasons.append("Disk: traced values, all rays traced through the plane (masked)")
    else:
        reasons.append("no Disk: no per-ray tracing")
    reasons.append(
        f"{b['blocks']} compiled block(s) of at most {b['samples']} area samples "
        f"(chunk_samples = {chunk_samples})"
    )
    return dataclasses.replace(
        base, geometry=geometry, disk_rays=disk_rays, weak_bound=weak_bound,
        disk_reach=None if disk_rays is None else max(counts),
        reasons=tuple(reasons),
    )  # fmt: skip
