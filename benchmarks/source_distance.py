"""What a source at a finite distance costs per ray, against a source at infinity.

    .venv/bin/python benchmarks/source_distance.py [--rays N]

The exact closed forms on the same rays (uniform in alpha over (0, pi), a camera at
D = 20) in one run, each jitted, compile timed apart, the median of repeats:
`escape_angle` (the sky at infinity), `radius_crossings` to a sphere beyond the camera
(R = 50) and inside its radius (R = 10, where rays cross it twice), and the public
`radius_crossings` with a radius array that mixes finite and infinite values (both
programs run). float64 and float32. Writes `results/source_distance.md`.

The ray map (the renderer's table) at a finite distance is not built yet: these are
the closed forms the table would be tabulated from, and the exact image solve
(`point_source_images_at`) evaluates.
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

D = 20.0


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


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rays", type=int, default=1_000_000)
    args = p.parse_args(argv)
    load = load_average()
    table = rows(args.rays, jnp.float64) + rows(args.rays, jnp.float32)
    text = "# A source at a finite distance: cost per ray\n\n"
    text += machine_markdown()
    text += (
        f"- {args.rays:,} rays uniform in alpha over (0, pi), camera at D = {D:g}; one "
        f"run; 1-minute load average {load:.2f} at the start.\n"
        "- ns per ray: the median wall time of a jitted call over the rays (2 cores); "
        "'x inf': against `escape_angle` in the same precision.\n\n"
    )
    text += markdown_table(("closed form", "dtype", "compile s", "ns per ray", "x inf"), table)
    (RESULTS / "source_distance.md").write_text(text)
    print(f"wrote {RESULTS / 'source_distance.md'}")


if __name__ == "__main__":
    main()
