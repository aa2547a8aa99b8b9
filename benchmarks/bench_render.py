"""Benchmark: a 1920 x 1080 panorama render, warm and compile time apart, and the check
that every pixel's sky direction is within 0.01 pixel of a per-pixel exact trace.

    .venv/bin/python benchmarks/bench_render.py [--repeats 15] [--skip-check]

Writes benchmarks/results/render.md (or `$JAXLENS_BENCH_RESULTS/render.md`). The sky
is an equirectangular panorama made by code (the procedural `DefaultSky` sampled onto a
4096 x 2048 grid), so nothing is downloaded; the render looks it up bilinearly at every
pixel.

What is timed (`render(camera, Panorama(...))`, float32 pixels, the ray map built in
float64, one pixel a sample):
- *compile*: the first call (tracing and XLA compilation of the ray-map build and of
  the render block) minus one warm call;
- *warm*: the median (and min) of repeated calls, each ending with the image on the
  host as a NumPy array; the breakdown times the parts alone.

The accuracy check: for every pixel the render's own sky direction (`sky_directions`,
the same code path) against a float64 per-pixel trace with `trace(...,
method=Exact(iterations=12))`, its local angle alpha computed in float64 from the pixel
centre. The error is the shift in the image that would produce the direction error:
radial, $|\\Delta\\Phi| / |d\\Phi/d\\alpha|$ converted to pixels by
$d\\rho/d\\alpha = f/\\cos^2\\alpha$; azimuthal, $|\\Delta\\beta|\\,\\rho$. Pixels that
straddle the shadow edge are compared at the alpha the render uses for their escaping
part (their centroid); captured pixels have no direction. The strict angular error
(the direction error over the angle of one pixel, 1/f) is reported as well.
"""

import argparse
import math
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import _common  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxlens as jl  # noqa: E402
from jaxlens import (  # noqa: E402
    Camera,
    DefaultSky,
    Exact,
    Panorama,
    Uniform,
    equirectangular,
    render,
    sky_directions,
    trace,
)

W, H, DISTANCE, FOV_DEG = 1920, 1080, 20.0, 60.0
GOAL_S, GOAL_PX = 0.1, 0.01


def machine() -> str:
    """`_common.machine()` on one line, with the load average (this benchmark's wall
    times move with it)."""
    info = _common.machine()
    load = _common.load_average()
    return (
        f"{info['cpu']}, {info['usable_cores']} cores usable, load average {load:.1f} at the "
        f"start; JAX {info['versions']['jax']} ({jax.default_backend()}), {info['date']}, "
        f"commit {info['commit']}"
    )


@eqx.filter_jit
def build_map(distance):
    """The ray map of a distance, as `render` builds it (float64 under x64)."""
    return jl.RayMap.build(distance, accuracy=1e-8)


@eqx.filter_jit
def image(scene, plan, ray_map):
    """The whole image as one compiled `render_array` with a given plan and ray map."""
    return jl.render_array(scene, plan=plan, ray_map=ray_map)


def timed(f, repeats):
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(f())
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)), float(np.min(ts))


def accuracy(camera) -> dict:
    """Per-pixel check of the render's sky directions against an exact float64 trace."""
    n, cover = sky_directions(camera)  # float32, the render's code path
    n = n.astype(np.float64)
    f = W / 2 / math.tan(math.radians(FOV_DEG) / 2)
    x = np.arange(W) + 0.5 - W / 2
    y = H / 2 - (np.arange(H) + 0.5)
    x, y = np.broadcast_arrays(x[None, :], y[:, None])
    rho = np.hypot(x, y)
    alpha = np.arctan2(rho, f)
    alpha_sh = math.asin(1.5 * math.sqrt(3) * math.sqrt(1 - 1 / DISTANCE) / DISTANCE)
    # Straddling pixels: the render looks up the centroid of the escaping part.
    width = np.cos(alpha) ** 2 / f
    cov = np.clip((alpha - alpha_sh) / width + 0.5, 0, 1)
    alpha_used = np.maximum(alpha, alpha_sh + 0.5 * width * (1 - cov))
    escaping = cover > 0

    @jax.jit
    def exact(a):
        fn = lambda a: trace(a, DISTANCE, method=Exact(iterations=12)).phi  # noqa: E731
        return jax.jvp(fn, (a,), (jnp.ones_like(a),))

    phi_ref = np.empty(alpha.shape)
    dphi = np.empty(alpha.shape)
    rows = 128
    for r in range(0, H, rows):
        p, d = exact(jnp.asarray(alpha_used[r : r + rows]))
        phi_ref[r : r + rows], dphi[r : r + rows] = np.asarray(p), np.asarray(d)
    beta = np.arctan2(y, x)
    sp, cp, sb, cb = np.sin(phi_ref), np.cos(phi_ref), np.sin(beta), np.cos(beta)
    ref = np.stack([sp * cb, sp * sb, -cp], -1)
    delta = n - ref
    # Components of the direction error along d n / d Phi and d n / d beta / sin(Phi).
    along_phi = np.abs(delta[..., 0] * cp * cb + delta[..., 1] * cp * sb + delta[..., 2] * sp)
    along_beta = np.abs(-delta[..., 0] * sb + delta[..., 1] * cb)
    radial = along_phi / np.abs(dphi) * f / np.cos(alpha) ** 2  # pixels
    azimuthal = along_beta / np.maximum(np.abs(sp), 1e-300) * rho  # pixels
    shift = np.hypot(radial, azimuthal)[escaping]
    strict = (np.linalg.norm(delta, axis=-1) * f)[escaping]  # direction error / (1/f)
    from_edge = np.abs(rho - f * math.tan(alpha_sh))[escaping]  # pixels from the shadow edge
    over = strict > GOAL_PX
    return {
        "pixels": int(escaping.sum()),
        "straddling": int(((cover > 0) & (cover < 1)).sum()),
        "captured": int((cover == 0).sum()),
        "max_shift": float(shift.max()),
        "p999_shift": float(np.quantile(shift, 0.999)),
        "max_strict": float(strict.max()),
        "strict_over": int(over.sum()),
        "strict_over_edge_px": float(from_edge[over].max()) if over.any() else 0.0,
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--skip-check", action="store_true")
    args = ap.parse_args()
    info = machine()
    print(info)

    t = time.perf_counter()
    pano_img = equirectangular(DefaultSky(), 4096, 2048)
    t_pano = time.perf_counter() - t
    sky = Panorama(pano_img)
    f32 = np.float32
    camera = Camera(f32(DISTANCE), f32(math.radians(FOV_DEG)), W, H)

    t = time.perf_counter()
    img = render(camera, sky)
    first = time.perf_counter() - t
    warm_med, warm_min = timed(lambda: render(camera, sky), args.repeats)
    compile_s = first - warm_min
    # CPU time of this process (all its threads) per warm render: unlike the wall time
    # it does not grow when other programs share the cores.
    c0 = time.process_time()
    for _ in range(args.repeats):
        render(camera, sky)
    cpu = (time.process_time() - c0) / args.repeats
    assert img.shape == (H, W, 3) and np.all(np.isfinite(img))

    # Breakdown: the ray map alone, the geometry alone (a uniform sky needs no look-up),
    # the full block on the device, and the float64 render for comparison. The block is
    # `render_array` with the render's own plan (one block holds this image) and a
    # prebuilt ray map, compiled with `eqx.filter_jit`.
    plan = jl.plan(jl.Scene(camera, sky))
    assert plan.blocks == 1, plan  # else the whole-image block below is not render's
    dist = jnp.asarray(DISTANCE, jnp.float64)
    ray_map = jax.block_until_ready(build_map(dist).astype(jnp.float32))  # compiles
    t_map = timed(lambda: build_map(dist).astype(jnp.float32), args.repeats)

    def block(s):
        return image(jl.Scene(camera, s), plan, ray_map)

    block(Uniform(f32(0.5)))  # compiles (a sky is part of the program: each compiles)
    block(sky)
    t_geom = timed(lambda: block(Uniform(f32(0.5))), args.repeats)
    t_block = timed(lambda: block(sky), args.repeats)
    cam64 = Camera(DISTANCE, math.radians(FOV_DEG), W, H)
    render(cam64, sky)
    t64 = timed(lambda: render(cam64, sky), max(3, args.repeats // 3))
    t_general = None
    oriented = Camera(f32(DISTANCE), f32(math.radians(FOV_DEG)), W, H, roll=f32(1e-30))
    render(oriented, sky)
    t_general = timed(lambda: render(oriented, sky), max(3, args.repeats // 3))

    knots = int(ray_map.phi.shape[0])
    acc = None if args.skip_check else accuracy(camera)
    print(f"warm {warm_med * 1e3:.1f} ms (min {warm_min * 1e3:.1f}), compile {compile_s:.1f} s")
    print(acc)

    lines = [
        "# Render benchmark: 1920 x 1080 panorama",
        "",
        f"Machine: {info}.",
        "",
        f"Scene: static camera at D = {DISTANCE:g} R_S, horizontal FOV {FOV_DEG:g} deg, "
        f"{W} x {H} pixels, one sample a pixel, float32 pixels (ray map built in float64, "
        f"accuracy 1e-8 rad), sky: a {pano_img.shape[1]} x {pano_img.shape[0]} "
        f"equirectangular panorama (the procedural sky sampled by code in {t_pano:.1f} s), "
        "bilinear look-up at every pixel. Produced by `benchmarks/bench_render.py`.",
        "",
        "| what | time |",
        "| --- | --- |",
        f"| **warm render** (median of {args.repeats}; image on the host as NumPy) | "
        f"**{warm_med * 1e3:.1f} ms** (min {warm_min * 1e3:.1f} ms) |",
        f"| CPU time of one warm render, all threads (the machine's load does not inflate "
        f"it; an idle 2-core machine takes about half of it as wall time) | "
        f"{cpu * 1e3:.1f} ms |",
        f"| compile (first call minus a warm call) | {compile_s:.1f} s |",
        f"| of which: ray map for this distance ({knots} knots, float64) | "
        f"{t_map[0] * 1e3:.1f} ms |",
        f"| of which: render block with a uniform sky (geometry and ray map look-ups) | "
        f"{t_geom[0] * 1e3:.1f} ms |",
        f"| of which: render block with the panorama (on the device) | {t_block[0] * 1e3:.1f} ms |",
        f"| for comparison: the same render in float64 | {t64[0] * 1e3:.1f} ms |",
        f"| for comparison: float32 without the mirror symmetry (per-sample rotation "
        f"path) | {t_general[0] * 1e3:.1f} ms |",
        "",
        f"Goal: under {GOAL_S * 1e3:.0f} ms warm: "
        f"**{'met' if warm_med < GOAL_S else 'not met'}** on this run "
        "(a shared machine: timings drift with its load, see the load average above).",
        "",
        "Where the time goes: the lensing itself (pixel angles, the ray-map look-up on one "
        "mirrored half, the sky directions) is the 'uniform sky' line, "
        f"{t_geom[0] / t_block[0] * 100:.0f} % of the block; the ray map is built once per "
        "distance. The rest is the bilinear panorama look-up, four texel gathers a pixel: "
        "XLA's CPU backend compiles a gather inside a fused loop to scalar code (about as "
        "slow for a 64 x 32 texture that sits in L1 as for 4096 x 2048, so it is not "
        "memory), and packing neighbouring texels into wider rows or gathering channels "
        "one by one was slower still. On a GPU the same program runs unchanged.",
        "",
    ]
    if acc is not None:
        ok = acc["max_shift"] < GOAL_PX
        lines += [
            "## Accuracy: every pixel's sky direction against an exact per-pixel trace",
            "",
            f"{acc['pixels']} pixels with a sky direction ({acc['straddling']} of them on the "
            f"shadow edge, compared at the alpha the render uses for them), "
            f"{acc['captured']} captured.",
            "",
            "| measure | value |",
            "| --- | --- |",
            f"| largest image-plane shift of a sky direction | **{acc['max_shift']:.2e} px** |",
            f"| 99.9 % of pixels within | {acc['p999_shift']:.2e} px |",
            f"| largest direction error over the angle of a pixel (1/f) | "
            f"{acc['max_strict']:.2e} |",
            f"| pixels whose direction error exceeds 0.01 of a pixel's angle | "
            f"{acc['strict_over']}, all within {acc['strict_over_edge_px']:.1f} px of the "
            "shadow edge |",
            "",
            f"Goal: every pixel within {GOAL_PX} px: **{'met' if ok else 'not met'}**. The "
            "direction error itself exceeds 0.01 of a pixel's angle only where the sky is "
            "magnified, next to the shadow edge (|dPhi/dalpha| ~ 1/(alpha - alpha_sh)): "
            "there the float32 rounding of alpha (~3e-8 rad) is amplified in Phi, but the "
            "direction is still that of a ray within a tiny fraction of a pixel of the "
            "pixel's own.",
            "",
        ]
    out = _common.RESULTS / "render.md"
    out.parent.mkdir(exist_ok=True)
    out.write_text("\n".join(lines))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
