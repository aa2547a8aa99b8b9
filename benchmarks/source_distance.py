"""What a source at a finite distance costs per ray, against a source at infinity.

    .venv/bin/python benchmarks/source_distance.py [--rays N]

The exact closed forms on the same rays (uniform in alpha over (0, pi), a camera at
D = 20) in one run, each jitted, compile timed apart, the median of repeats:
`escape_angle` (the sky at infinity), `radius_crossings` to a sphere beyond the camera
(R = 50) and inside its radius (R = 10, where rays cross it twice), and the public
`radius_crossings` with a radius array that mixes finite and infinite values (both
programs run). float64 and float32.

The per-ray rows end with the look-up of the renderer's ray map at infinity and of
its map of (D, R = 50) (`RayMap.build(D, radius=R)`).

Then the cost of a 1080p frame (1920 x 1080, one ray a pixel) through `jl.render` of a
scene whose sky lies at infinity (`source_distance=None`: the ray map, kept for the
distance, so a frame pays its look-up only), on a sphere beyond the camera (R = 2D: the
ray map of (D, R); R = 1.1 D: the exact crossings, the table's bound being 1.25 D) and
inside its radius (R = D/2, rays cross it twice and the sky is evaluated at both), as
ratios to `None` in the same run, float32 and float64; compile (first call) timed apart.
`--frames-only` skips the per-ray rows (kept from the last run's file). Writes
`results/source_distance.md`.
"""

import argparse
import math

import jax
import jax.numpy as jnp
import numpy as np
from _common import (
    RESULTS,
    load_average,
    machine_markdown,
    markdown_table,
    time_jitted,
)

import jaxlens as jl
from jaxlens._exact import escape_angle, finite_crossings
from jaxlens._raymap import RayMap
from jaxlens._trace import TABLE_SETTINGS

D = 20.0


def _table(dtype, radius):
    """The renderer's ray map of the camera (and of the sphere `radius`), in `dtype`."""
    m = RayMap.build(D, accuracy=1e-8, radius=radius, **TABLE_SETTINGS)
    return m.astype(dtype)


def rows(n: int, dtype):
    alpha = jnp.asarray(np.linspace(1e-3, math.pi - 1e-3, n), dtype)
    d = jnp.asarray(D, dtype)
    mixed = jnp.where(jnp.arange(n) % 2 == 0, jnp.inf, 50.0).astype(dtype)
    cases = [
        ("escape_angle (R = inf)", jax.jit(lambda a: escape_angle(a, d)[0]), (alpha,)),
        ("finite crossings, R = 50 (beyond the camera)",
         jax.jit(lambda a: finite_crossings(a, d, jnp.asarray(50.0, dtype))), (alpha,)),
        ("finite crossings, R = 10 (inside its radius)",
         jax.jit(lambda a: finite_crossings(a, d, jnp.asarray(10.0, dtype))), (alpha,)),
        ("jl.radius_crossings, R mixed 50 / inf",
         jax.jit(lambda a, r: jl.radius_crossings(a, d, r)), (alpha, mixed)),
        ("ray map at infinity, look-up (the renderer's)",
         jax.jit(lambda a, m: m.escape_angle(a)), (alpha, _table(dtype, None))),
        ("ray map of (D, R = 50), look-up",
         jax.jit(lambda a, m: m.escape_angle(a)), (alpha, _table(dtype, 50.0))),
    ]  # fmt: skip
    out, base = [], None
    for name, fn, args in cases:
        compile_s, run_s, _ = time_jitted(fn, *args)
        per_ray = run_s / n * 1e9
        base = per_ray if base is None else base
        out.append((name, jnp.dtype(dtype).name, f"{compile_s:.2f}", f"{per_ray:.1f}",
                    f"{per_ray / base:.2f}"))  # fmt: skip
        print(out[-1], flush=True)
    return out


def frames(dtype, repeats: int):
    """Wall time a 1080p frame, R = None, 2D, 1.1D and D/2 (rows of the per-frame
    table): each case's first call (compiling), then `repeats` rounds that time every
    case once in turn, so that a change of the machine's load falls on all of them."""
    import time

    cam = jl.Camera(D, math.radians(60.0), 1920, 1080, supersample=1)
    sky = jl.DefaultSky() + jl.GaussianStar(math.radians(1.0))
    cases = (("None (at infinity)", None), (f"2D = {2 * D:g}", 2 * D),
             (f"1.1D = {1.1 * D:g}", 1.1 * D), (f"D/2 = {D / 2:g}", D / 2))  # fmt: skip
    scenes = [jl.Scene(cam, sky, source_distance=r) for _, r in cases]
    first, times = [], [[] for _ in cases]
    for scene in scenes:
        t = time.perf_counter()
        jl.render(scene, dtype=dtype)
        first.append(time.perf_counter() - t)
    for _ in range(repeats):
        for i, scene in enumerate(scenes):
            t = time.perf_counter()
            jl.render(scene, dtype=dtype)
            times[i].append(time.perf_counter() - t)
    medians = [float(np.median(t)) for t in times]
    out = []
    for (name, _), scene, f, m in zip(cases, scenes, first, medians, strict=True):
        out.append((name, jnp.dtype(dtype).name, jl.plan(scene).geometry, f"{f:.2f}",
                    f"{m:.3f}", f"{m / medians[0]:.2f}"))  # fmt: skip
        print(out[-1], flush=True)
    return out


FRAME_HEADER = ("source_distance", "dtype", "geometry", "first call s", "s a frame",
                "x None")  # fmt: skip
PER_FRAME = "## A 1080p frame"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rays", type=int, default=1_000_000)
    p.add_argument("--repeats", type=int, default=5, help="rounds of frames timed")
    p.add_argument("--frames-only", action="store_true")
    args = p.parse_args(argv)
    path = RESULTS / "source_distance.md"
    load = load_average()
    if args.frames_only:
        text = path.read_text().split(PER_FRAME)[0].rstrip() + "\n"
    else:
        table = rows(args.rays, jnp.float64) + rows(args.rays, jnp.float32)
        text = "# A source at a finite distance: cost per ray\n\n"
        text += machine_markdown()
        text += (
            f"- {args.rays:,} rays uniform in alpha over (0, pi), camera at D = {D:g}; one "
            f"run; 1-minute load average {load:.2f} at the start.\n"
            "- ns per ray: the median wall time of a jitted call over the rays (2 cores); "
            "'x inf': against `escape_angle` in the same precision.\n\n"
        )
        text += markdown_table(("closed form", "dtype", "compile s", "ns per ray", "x inf"),
                               table)  # fmt: skip
        load = load_average()
    frame_rows = frames(jnp.float32, args.repeats)
    load_end = load_average()
    frame_rows += frames(jnp.float64, args.repeats)
    text += f"\n{PER_FRAME}\n\n"
    text += machine_markdown()
    text += (
        f"- `jl.render` of a 1920 x 1080 frame, one ray a pixel, camera at D = {D:g}, FOV "
        "60 deg, sky `DefaultSky() + GaussianStar(1 deg)`; 1-minute load average "
        f"{load:.2f} at the start, {load_end:.2f} after the float32 rows, "
        f"{load_average():.2f} at the end.\n"
        "- 'first call s': the first render (compiling; for a table also building the ray "
        "map, kept for the next frames); 's a frame': the median of "
        f"{args.repeats} rounds, each timing every case once in turn; 'x None': against "
        "the sky at infinity in the same precision and run. geometry: the plan's source "
        "of the escape angles or crossings.\n\n"
    )
    text += markdown_table(FRAME_HEADER, frame_rows)
    path.write_text(text)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
