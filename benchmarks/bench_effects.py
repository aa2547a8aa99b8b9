"""What each effect costs, and what the plan's fast paths save.

1. The same star scene rendered through `render(Scene(...))` without effects and with
   each effect switched on, one at a time, next to the shorthand `render(camera, sky)`:
   one pipeline for all, and a stage a scene does not name is absent from its compiled
   program (the `jaxlens.<stage>` scopes counted in the lowered text of
   `eqx.filter_jit(render_array)`).
2. A disk seen from afar: tracing only the rays that can reach it (the plan's gather,
   `Plan.disk_rays`) against tracing every ray (masked: the same plan with
   `disk_rays=None`), both as `render_array(scene, plan=..., ray_map=...)` compiled
   with `eqx.filter_jit`, the ray map built once.
3. Sky rays of a view far from the hole at one accuracy (1e-8 rad): the weak-field
   series, the alpha table (build + look-up), and the exact per-ray closed form,
   with their errors against `Exact(iterations=12)`.

Timing: a warm-up call first (compile time reported apart), then the median of
repeats. Results: `benchmarks/results/effects.md`; `--images` also renders the
figures of `docs/effects.md` (`docs/images/effects_*.png`). With
`JAXLENS_BENCH_RESULTS=DIR` set, the report and the figures go to DIR instead.

    .venv/bin/python benchmarks/bench_effects.py [--quick] [--images]
"""

import argparse
import dataclasses
import math
import re
import sys
import time

import _common
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxlens as jl

ACC = 1e-8


@eqx.filter_jit
def _image(scene, plan, ray_map):
    """One compiled `render_array` of a scene with a given plan and prebuilt ray map
    (the plan is static: each plan compiles its own program)."""
    return jl.render_array(scene, plan=plan, ray_map=ray_map)


@eqx.filter_jit
def _build_map(distance, accuracy):
    return jl.RayMap.build(distance, accuracy=accuracy)


def whole_plan(scene):
    """The plan of the whole image as one block, as `render_array` takes it (a disk
    scene's blocks hold a quarter of `chunk_samples`)."""
    cam = scene.camera
    plan = jl.plan(scene, chunk_samples=cam.width * cam.height * cam.supersample**2 * 8)
    assert plan.blocks == 1, plan.reasons
    return plan


def lowered_text(scene):
    """The lowered (StableHLO) text of the scene's image program, with its
    `jaxlens.<stage>` scopes (`debug_info=True`)."""
    return eqx.filter_jit(jl.render_array).lower(scene).lowered.as_text(debug_info=True)


def weak_max_samples():
    """The most rays a view the plan takes through the weak-field series, read from
    the reason a plan gives for a view above it (None if the wording changes)."""
    cam = jl.Camera(1e4, math.radians(2.0), 8192, 8192)
    for r in jl.plan(jl.Scene(cam, jl.Uniform(1.0))).reasons:
        m = re.search(r"rays a view > (\d+)", r)
        if m:
            return int(m.group(1))
    return None


def measure(fns, rounds=11):
    """Compile time, then interleaved repeats (one call of each function a round, so a
    change in the machine's load hits all alike) of zero-argument functions.

    **Returns:** `{name: (compile_s, wall_median_s, cpu_median_s, wall_min_s)}`; CPU
    time is this process's (all threads): what a call costs, whatever else runs.
    """
    out, walls, cpus = {}, {}, {}
    for name, fn in fns.items():
        t = time.perf_counter()
        fn()
        first = time.perf_counter() - t
        t = time.perf_counter()
        fn()
        out[name] = max(first - (time.perf_counter() - t), 0.0)
        walls[name], cpus[name] = [], []
    for _ in range(rounds):
        for name, fn in fns.items():
            w, c = time.perf_counter(), time.process_time()
            fn()
            walls[name].append(time.perf_counter() - w)
            cpus[name].append(time.process_time() - c)
    return {
        k: (out[k], float(np.median(walls[k])), float(np.median(cpus[k])), float(min(walls[k])))
        for k in fns
    }


def _ops(text, name):
    return len(re.findall(rf"\bstablehlo\.{name}\b", text))


def effect_costs(size):
    cam = jl.Camera(30.0, math.radians(60), size, size)
    sky = jl.BlackbodyStars.random(48, seed=2, sigma=0.01) + jl.Uniform(0.01)
    red_b, red_s = jl.Redshift("bolometric"), jl.Redshift("spectral")
    disk = jl.Disk(3.0, 14.0, math.radians(80.0))
    variants = [
        ("no effects", {}),
        ("+ Redshift(bolometric)", dict(redshift=red_b)),
        ("+ Redshift(spectral)", dict(redshift=red_s)),
        ("+ RadialInfall", dict(motion=jl.RadialInfall())),
        ("+ CircularOrbit", dict(motion=jl.CircularOrbit())),
        ("+ CircularOrbit + Redshift(spectral)", dict(motion=jl.CircularOrbit(), redshift=red_s)),
        ("+ Disk (80 deg, r_out 14)", dict(disk=disk)),
        ("+ Disk + Redshift(spectral)", dict(disk=disk, redshift=red_s)),
    ]
    shorthand = "shorthand `render(camera, sky)`"
    fns = {shorthand: lambda: jl.render(cam, sky, accuracy=ACC)}
    stages, texts = {shorthand: "-"}, {}
    for name, kw in variants:
        scene = jl.Scene(cam, sky, accuracy=ACC, **kw)
        key = f"`render(Scene)`: {name}"
        fns[key] = lambda s=scene: jl.render(s)
        text = lowered_text(scene)
        texts[name] = text
        found = [st for st in ("aberration", "redshift", "disk") if f"jaxlens.{st}" in text]
        stages[key] = ", ".join(found) or "-"
    times = measure(fns)
    return [(k, *times[k], stages[k]) for k in fns], texts


def far_disk(size):
    cam = jl.Camera(300.0, math.radians(20), size, size)
    disk = jl.Disk(3.0, 10.0, math.radians(80.0), crossings=2)
    scene = jl.Scene(cam, jl.Uniform(0.01), redshift=jl.Redshift("spectral"), disk=disk)
    p = whole_plan(scene)
    rm = _build_map(cam.distance, ACC)
    nodisk = dataclasses.replace(scene, disk=None)
    runs = {
        "gather the reachable rays (the plan)": (scene, p),
        "every ray, masked": (scene, dataclasses.replace(p, disk_rays=None)),
        "no disk (same scene otherwise)": (nodisk, whole_plan(nodisk)),
    }
    fns = {
        k: (lambda sc=sc, pl=pl: _image(sc, pl, rm).block_until_ready())
        for k, (sc, pl) in runs.items()
    }
    fns["`render(scene)` (blocks, the plan's gather)"] = lambda: jl.render(scene)
    times = measure(fns)
    return p, [(k, *times[k]) for k in fns]


def geometry_paths(size):
    cam = jl.Camera(1e4, math.radians(2.0), size, size, yaw=math.radians(5.0))
    alpha = cam.rays()[0].reshape(-1)
    d = cam.distance
    ref = np.asarray(jax.jit(lambda a: jl.trace(a, d, method=jl.Exact(iterations=12)).phi)(alpha))
    weak = jax.jit(lambda a: jl.weak_field_escape_angle(a, d)[0])
    look = jax.jit(lambda m, a: m.escape_angle(a))
    exact = jax.jit(lambda a: jl.trace(a, d, accuracy=ACC, method="exact").phi)
    rm = _build_map(d, ACC)
    fns = {
        "weak-field series": lambda: weak(alpha).block_until_ready(),
        "alpha table: build": lambda: jax.block_until_ready(_build_map(d, ACC)),
        "alpha table: look-up": lambda: look(rm, alpha).block_until_ready(),
        "exact per ray (`trace`, accuracy 1e-8)": lambda: exact(alpha).block_until_ready(),
    }
    times = measure(fns)
    errs = {
        "weak-field series": weak(alpha),
        "alpha table: look-up": look(rm, alpha),
        "exact per ray (`trace`, accuracy 1e-8)": exact(alpha),
    }
    errs = {k: float(np.max(np.abs(np.asarray(v) - ref))) for k, v in errs.items()}
    bound = float(jnp.max(jl.weak_field_escape_angle(alpha, d)[1]))
    rows = [(k, *times[k], errs.get(k)) for k in fns]
    star = jl.GaussianStar(0.002, 1.0, lon=math.radians(5.5), lat=0.002)
    scenes = {
        m: jl.Scene(cam, star, redshift=jl.Redshift("bolometric"), method=m)
        for m in ("weak_field", "table", "trace")
    }
    rtimes = measure({m: (lambda s=s: jl.render(s)) for m, s in scenes.items()})
    renders = [(m, *rtimes[m]) for m in scenes]
    auto = jl.plan(jl.Scene(cam, star, redshift=jl.Redshift("bolometric")))
    n = alpha.size
    # break-even of the series against the table: CPU time, series minus look-up a ray
    extra = (times["weak-field series"][2] - times["alpha table: look-up"][2]) / n
    crossover = times["alpha table: build"][2] / extra if extra > 0 else float("inf")
    return n, rows, bound, renders, auto, extra, crossover


def _ms(x):
    return "-" if x is None else f"{x * 1e3:.1f}"


def write_report(path, size, cost_rows, texts, far_plan, far_rows, geos):
    head = "| median wall ms | min wall ms | median CPU ms | compile s |"
    rule = "|---:|---:|---:|---:|"

    def cells(r):
        comp, wall, cpu, low = r[1:5]
        return f"| {_ms(wall)} | {_ms(low)} | {_ms(cpu)} | {comp:.1f} |"

    lines = [
        "# Effects: what each costs, and what the fast paths save",
        "",
        "Written by [`benchmarks/bench_effects.py`](../bench_effects.py).",
        "",
        _common.machine_markdown(),
        "",
        "Each function is called once to compile (the extra time of that first call is",
        "*compile s*), then the functions of a table are called in turn, 11 rounds, so a",
        "change in the shared machine's load hits them alike. *CPU ms* is this process's",
        "CPU time (all threads) a call: the cost, whatever else the machine runs.",
        "",
        f"## 1. One star scene, each effect on its own ({size} x {size}, D = 30, FOV 60 deg,"
        " 48 blackbody stars + a floor, accuracy 1e-8)",
        "",
        "| render " + head + " stages in the program |",
        "|---" + rule + "---|",
    ]
    for r in cost_rows:
        lines.append(f"| {r[0]} " + cells(r) + f" {r[5]} |")
    plain = texts["+ CircularOrbit + Redshift(spectral)"]
    with_disk = texts["+ Disk + Redshift(spectral)"]
    lines += [
        "",
        "*Stages in the program*: the effect stages' `jaxlens.<stage>` scopes in the",
        "lowered (StableHLO) text of the scene's program (`eqx.filter_jit(render_array)`);",
        "every scene, effects or not, runs the one block pipeline of `render`, and the",
        "shorthand `render(camera, sky)` is the scene without effects (the same program).",
        f"Lowered ops of orbit + spectral without a disk: {plain.count('stablehlo.')} "
        f"({_ops(plain, 'while')} loop: the stars' scan); with the disk: "
        f"{with_disk.count('stablehlo.')} ({_ops(with_disk, 'while')} loops, + the RK4 scans).",
        "",
        f"## 2. A far disk: only the rays that can reach it ({size} x {size}, D = 300,"
        " FOV 20 deg, r_out = 10, 2 crossings; compiled programs, table built once)",
        "",
        f"The plan: {far_plan.disk_reach} of {far_plan.samples} rays can come within r_out "
        f"(traced in a batch of {far_plan.disk_rays}). The first three rows are",
        "`render_array` of the whole image under `eqx.filter_jit` with that plan, the same",
        "plan with `disk_rays=None` (every ray masked), and the scene without its disk; the",
        "last is `render(scene)` itself, blocks and host copy included.",
        "",
        "| disk rays " + head,
        "|---" + rule,
    ]
    for r in far_rows:
        lines.append(f"| {r[0]} " + cells(r))
    lines += [
        "",
        "## 3. Sky rays far from the hole at accuracy 1e-8 rad (D = 1e4, FOV 2 deg, 5 deg"
        " off the hole)",
        "",
        "The escape angle of every ray of the view; error: max |phi - Exact(iterations=12)|.",
    ]
    for n, rows, bound, renders, auto, extra, crossover in geos:
        lines += [
            "",
            f"### {n} rays (the series' own bound over the view: {bound:.1e} rad)",
            "",
            "| path " + head + " max error rad |",
            "|---" + rule + "---:|",
        ]
        for r in rows:
            err = "-" if r[5] is None else f"{r[5]:.1e}"
            lines.append(f"| {r[0]} " + cells(r) + f" {err} |")
        lines += [
            "",
            f"Break-even: the series costs {extra * 1e9:.0f} ns (CPU) a ray more than a table",
            f"look-up but needs no build, so it is the cheaper path below about {crossover:.2g}",
            f"rays a view (the plan takes it up to {weak_max_samples()} rays a view).",
            "",
            "Whole `render(Scene)` of the view (a Gaussian star, bolometric redshift), path"
            " forced, and the plan's own choice:",
            "",
            "| path " + head,
            "|---" + rule,
        ]
        for r in renders:
            lines.append(f"| {r[0]} " + cells(r))
        lines += ["", "```", str(auto), "```"]
    lines.append("")
    path.write_text("\n".join(lines))


def cost_figure(path, cost_rows, far_rows, geo):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = geo[1]  # the larger view
    fig, axs = plt.subplots(1, 3, figsize=(13, 3.6), gridspec_kw={"width_ratios": [3, 1.3, 1.6]})
    names = [r[0].replace("`render(Scene)`: ", "").replace("`", "") for r in cost_rows]
    axs[0].barh(names[::-1], [r[3] * 1e3 for r in cost_rows][::-1], color="tab:blue")
    axs[0].set_xlabel("CPU ms per image (median)")
    axs[0].set_title("one star scene, each effect on its own", fontsize=10)
    axs[1].bar(["gather", "all rays", "no disk", "render"][: len(far_rows)],
               [r[3] * 1e3 for r in far_rows], color="tab:orange")  # fmt: skip
    axs[1].set_ylabel("CPU ms per image")
    axs[1].set_title("far disk: rays traced", fontsize=10)
    labels = ["series", "table\nbuild", "table\nlook-up", "exact"]
    axs[2].bar(labels, [r[3] * 1e3 for r in rows], color="tab:green")
    axs[2].set_yscale("log")
    axs[2].set_ylabel("CPU ms (every ray of the view)")
    axs[2].set_title("escape angle at accuracy 1e-8", fontsize=10)
    axs[2].tick_params(axis="x", labelsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def images(folder, size):
    """The figures of docs/effects.md, rendered by the library."""
    folder.mkdir(parents=True, exist_ok=True)
    w, h = size, size * 9 // 16
    stars = jl.BlackbodyStars.random(400, seed=5, sigma=0.004, brightness=(0.3, 3.0))
    floor = jl.Uniform(0.004)  # a faint floor: the shadow shows
    cam = jl.Camera(40.0, math.radians(36), w, h, supersample=2)
    disk = jl.Disk(3.0, 16.0, math.radians(80.0), temperature=7000.0)
    img = jl.render(jl.Scene(cam, stars, redshift=jl.Redshift("spectral"), disk=disk))
    jl.write_image(folder / "effects_disk.png", img / np.percentile(img, 99.7))
    cam = jl.Camera(6.0, math.radians(100), w, h, supersample=2)
    sky = stars + jl.Checker(24, 12, brightness=0.08)
    parts = []
    for motion in (None, jl.CircularOrbit(0.0)):
        s = jl.Scene(cam, sky, motion=motion, redshift=jl.Redshift("bolometric"))
        parts.append(jl.render(s))
    both = np.concatenate([parts[0], np.ones((h, 4, 3), np.float32), parts[1]], axis=1)
    jl.write_image(folder / "effects_orbit.png", both / np.percentile(both, 99.5))
    frames = []
    for d in (1e3, 30.0, 4.0):
        cam = jl.Camera(d, math.radians(90), w // 2, h, supersample=2)
        s = jl.Scene(cam, stars + floor, motion=jl.RadialInfall(), redshift=jl.Redshift("spectral"))
        frames.append(jl.render(s))
    row = np.concatenate(frames, axis=1)
    jl.write_image(folder / "effects_approach.png", row / np.percentile(row, 99.7))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller images")
    ap.add_argument("--images", action="store_true", help="also write docs/images/effects_*.png")
    args = ap.parse_args(argv)
    size = 128 if args.quick else 256
    t0 = time.perf_counter()
    cost_rows, texts = effect_costs(size)
    far_plan, far_rows = far_disk(size)
    geos = [geometry_paths(size // 2), geometry_paths(2 * size)]
    out = _common.RESULTS / "effects.md"
    write_report(out, size, cost_rows, texts, far_plan, far_rows, geos)
    docs = _common.DOCS_IMAGES
    docs.mkdir(parents=True, exist_ok=True)
    cost_figure(docs / "effects_costs.png", cost_rows, far_rows, geos[1])
    if args.images:
        images(docs, 480)
    print(out.read_text())
    print(f"[bench_effects: {time.perf_counter() - t0:.0f} s]", file=sys.stderr)


if __name__ == "__main__":
    main()
