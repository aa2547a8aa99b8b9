"""What each effect costs, and what the plan's fast paths save.

1. The same star scene rendered through `render_scene` without effects and with each
   effect switched on, one at a time, next to the plain renderer (`render`): a scene
   that names no effect takes the plain renderer's own program, and a stage a scene
   does not name is absent from its compiled program (counted in the lowered text).
2. A disk seen from afar: tracing only the rays that can reach it (the plan's gather)
   against tracing every ray (masked).
3. Sky rays of a view far from the hole at one accuracy (1e-8 rad): the weak-field
   series, the alpha table (build + look-up), and the exact per-ray closed form,
   with their errors against `Exact(iterations=12)`.

Timing: a warm-up call first (compile time reported apart), then the median of
repeats. Results: `benchmarks/results/effects.md`; `--images` also renders the
figures of `docs/effects.md` (`docs/images/effects_*.png`).

    .venv/bin/python benchmarks/bench_effects.py [--quick] [--images]
"""

import argparse
import dataclasses
import math
import re
import sys
import time

import _common
import jax
import jax.numpy as jnp
import numpy as np

import jaxlens as jl
from jaxlens import _compose as C
from jaxlens import _disk as K
from jaxlens import _effects as E
from jaxlens._sky import Checker

ACC = 1e-8


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
    sky = E.BlackbodyStars.random(48, seed=2, sigma=0.01) + jl.Uniform(0.01)
    red_b, red_s = E.Redshift("bolometric"), E.Redshift("spectral")
    disk = K.Disk(3.0, 14.0, math.radians(80.0))
    variants = [
        ("no effects", {}),
        ("+ Redshift(bolometric)", dict(redshift=red_b)),
        ("+ Redshift(spectral)", dict(redshift=red_s)),
        ("+ RadialInfall", dict(motion=E.RadialInfall())),
        ("+ CircularOrbit", dict(motion=E.CircularOrbit())),
        ("+ CircularOrbit + Redshift(spectral)", dict(motion=E.CircularOrbit(), redshift=red_s)),
        ("+ Disk (80 deg, r_out 14)", dict(disk=disk)),
        ("+ Disk + Redshift(spectral)", dict(disk=disk, redshift=red_s)),
    ]
    fns = {"plain renderer `render(camera, sky)`": lambda: jl.render(cam, sky, accuracy=ACC)}
    stages, texts = {"plain renderer `render(camera, sky)`": "-"}, {}
    for name, kw in variants:
        scene = C.EffectScene(cam, sky, accuracy=ACC, **kw)
        key = f"`render_scene`: {name}"
        fns[key] = lambda s=scene: C.render_scene(s)
        text = C.lowered_text(scene)
        texts[name] = text
        found = [st for st in ("aberration", "redshift", "disk") if f"jaxlens.{st}" in text]
        stages[key] = ", ".join(found) or ("(render_array)" if C.plan(scene).bare else "-")
    times = measure(fns)
    return [(k, *times[k], stages[k]) for k in fns], texts


def far_disk(size):
    cam = jl.Camera(300.0, math.radians(20), size, size)
    disk = K.Disk(3.0, 10.0, math.radians(80.0), crossings=2)
    scene = C.EffectScene(cam, jl.Uniform(0.01), redshift=E.Redshift("spectral"), disk=disk)
    p, idx = C._plan(scene)
    rm = C._build_map(cam.distance, ACC)
    nodisk = dataclasses.replace(scene, disk=None)
    runs = {
        "gather the reachable rays (the plan)": (scene, p, C._padded(idx, p)),
        "every ray, masked": (scene, dataclasses.replace(p, disk_rays=None), None),
        "no disk (same scene otherwise)": (nodisk, C.plan(nodisk), None),
    }
    fns = {
        k: (lambda sc=sc, pl=pl, ix=ix: C._program(sc, pl, ix, rm).block_until_ready())
        for k, (sc, pl, ix) in runs.items()
    }
    times = measure(fns)
    return p, [(k, *times[k]) for k in fns]


def geometry_paths(size):
    cam = jl.Camera(1e4, math.radians(2.0), size, size, yaw=math.radians(5.0))
    alpha = cam.rays()[0].reshape(-1)
    d = cam.distance
    ref = np.asarray(jax.jit(lambda a: jl.trace(a, d, method=jl.Exact(iterations=12)).phi)(alpha))
    weak = jax.jit(lambda a: C.weak_field_escape_angle(a, d)[0])
    look = jax.jit(lambda m, a: m.escape_angle(a))
    exact = jax.jit(lambda a: jl.trace(a, d, accuracy=ACC, method="exact").phi)
    rm = C._build_map(d, ACC)
    fns = {
        "weak-field series": lambda: weak(alpha).block_until_ready(),
        "alpha table: build": lambda: jax.block_until_ready(C._build_map(d, ACC)),
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
    bound = float(jnp.max(C.weak_field_escape_angle(alpha, d)[1]))
    rows = [(k, *times[k], errs.get(k)) for k in fns]
    star = jl.GaussianStar(0.002, 1.0, lon=math.radians(5.5), lat=0.002)
    scenes = {
        m: C.EffectScene(cam, star, redshift=E.Redshift("bolometric"), method=m)
        for m in ("weak_field", "table", "trace")
    }
    rtimes = measure({m: (lambda s=s: C.render_scene(s)) for m, s in scenes.items()})
    renders = [(m, *rtimes[m]) for m in scenes]
    auto = C.plan(C.EffectScene(cam, star, redshift=E.Redshift("bolometric")))
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
        "*Stages in the program*: the `jaxlens.<stage>` scopes in the lowered (StableHLO)",
        "text of the program `render_scene` compiled; a scene without effects is handed",
        "to the plain renderer, whose program it is (hence no compile of its own).",
        f"Lowered ops of orbit + spectral without a disk: {plain.count('stablehlo.')} "
        f"({_ops(plain, 'while')} loop: the stars' scan); with the disk: "
        f"{with_disk.count('stablehlo.')} ({_ops(with_disk, 'while')} loops, + the RK4 scans).",
        "",
        f"## 2. A far disk: only the rays that can reach it ({size} x {size}, D = 300,"
        " FOV 20 deg, r_out = 10, 2 crossings; compiled programs, table built once)",
        "",
        f"The plan: {far_plan.disk_rays} of {far_plan.samples} rays can come within r_out.",
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
            f"rays a view (the plan takes it up to `WEAK_MAX_SAMPLES` = {C.WEAK_MAX_SAMPLES}).",
            "",
            "Whole `render_scene` of the view (a Gaussian star, bolometric redshift), path"
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
    names = [r[0].replace("`render_scene`: ", "").replace("`", "") for r in cost_rows]
    axs[0].barh(names[::-1], [r[3] * 1e3 for r in cost_rows][::-1], color="tab:blue")
    axs[0].set_xlabel("CPU ms per image (median)")
    axs[0].set_title("one star scene, each effect on its own", fontsize=10)
    axs[1].bar(["gather", "all rays", "no disk"], [r[3] * 1e3 for r in far_rows],
               color="tab:orange")  # fmt: skip
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
    stars = E.BlackbodyStars.random(400, seed=5, sigma=0.004, brightness=(0.3, 3.0))
    floor = jl.Uniform(0.004)  # a faint floor: the shadow shows
    cam = jl.Camera(40.0, math.radians(36), w, h, supersample=2)
    disk = K.Disk(3.0, 16.0, math.radians(80.0), temperature=7000.0)
    img = C.render_scene(C.EffectScene(cam, stars, redshift=E.Redshift("spectral"), disk=disk))
    jl.write_image(folder / "effects_disk.png", img / np.percentile(img, 99.7))
    cam = jl.Camera(6.0, math.radians(100), w, h, supersample=2)
    sky = stars + Checker(24, 12, brightness=0.08)
    parts = []
    for motion in (None, E.CircularOrbit(0.0)):
        s = C.EffectScene(cam, sky, motion=motion, redshift=E.Redshift("bolometric"))
        parts.append(C.render_scene(s))
    both = np.concatenate([parts[0], np.ones((h, 4, 3), np.float32), parts[1]], axis=1)
    jl.write_image(folder / "effects_orbit.png", both / np.percentile(both, 99.5))
    frames = []
    for d in (1e3, 30.0, 4.0):
        cam = jl.Camera(d, math.radians(90), w // 2, h, supersample=2)
        s = C.EffectScene(
            cam, stars + floor, motion=E.RadialInfall(), redshift=E.Redshift("spectral")
        )
        frames.append(C.render_scene(s))
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
    docs = _common.ROOT / "docs" / "images"
    docs.mkdir(parents=True, exist_ok=True)
    cost_figure(docs / "effects_costs.png", cost_rows, far_rows, geos[1])
    if args.images:
        images(docs, 480)
    print(out.read_text())
    print(f"[bench_effects: {time.perf_counter() - t0:.0f} s]", file=sys.stderr)


if __name__ == "__main__":
    main()
