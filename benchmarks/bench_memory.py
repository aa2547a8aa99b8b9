"""Peak memory of large images: a render with every effect against the bare scene, and
a ring fit.

The scene (`SCENE_TOML` below, and the same built in Python): a camera on a circular
orbit (`CircularOrbit`) at D = 20 R_S, FOV 60 deg, one sample a pixel, float32 pixels
(ray maps in float64), the default procedural sky plus a Gaussian star, with
`Redshift()` (spectral) and a thin `Disk()` (r 3 ... 12, 80 deg, 3 crossings); the
*bare* scene is the same camera and sky with no effects. Each is rendered at
4096 x 4096:

- through the Python API, `jl.render(scene, dtype=float32, progress=True)` (compiled
  blocks of at most `chunk_samples` area samples, a progress bar on stderr); the first
  call (compile included) and one warm call are timed;
- through the CLI, `jaxlens render scene.toml -o out.exr --size 4096x4096` (the
  `jaxlens` entry point beside the running Python), timed as a whole process
  (start-up, compile, render, writing the EXR).

Every case runs in a fresh process, so its peak resident set is its own: `ru_maxrss`
of that child (`os.wait4`), and for the API cases also the child's own `VmHWM` before
and after the renders. The report gives the ratios effects / bare, and XLA's memory
accounting of one compiled block (`jl.block_memory`) of each scene.

The fit case: a 4096 x 4096 Einstein ring (`jl.ring_image`, D = 20 R_S, FOV 40 deg,
sigma 0.03 rad, floor 0.05, 2 x 2 area samples a pixel, Gaussian noise 0.01) is drawn
by one fresh process and saved; another loads it and runs `jl.fit_ring` on it, its
peak resident set `ru_maxrss` (`os.wait4`) and its own `VmHWM` before the fit. With
`--baseline DIR` the same fit runs again with `jaxlens` imported from DIR (a copy of
another commit's tree, e.g. `git archive <commit> | tar -x -C DIR`): before and after
a change, on the same image and machine.

Results: `benchmarks/results/memory.md` (or `$JAXLENS_BENCH_RESULTS/memory.md`);
`--quick` renders 512 x 512 and writes to a temporary folder unless `--out` is given;
`--case render` or `--case fit` runs one of the two and keeps the other's section of
the existing file.

    .venv/bin/python benchmarks/bench_memory.py [--size 4096] [--quick] [--out FILE]
        [--case all|render|fit] [--baseline DIR]
"""

import argparse
import json
import math
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import _common

SCENE_TOML = """\
accuracy = 1e-8

[camera]
distance = 20.0
fov_deg = 60.0
width = {size}
height = {size}
supersample = 1

[[sky]]
type = "default"

[[sky]]
type = "star"
sigma_deg = 1.0
"""

EFFECTS_TOML = """
[effects.motion]
type = "orbit"

[effects.redshift]

[effects.disk]
"""

# The API case, run by a fresh interpreter: argv = root, size, effects (0/1), toml path,
# warm repeats. Prints one JSON line.
_CHILD = r"""
import json, math, sys, time
sys.path.insert(0, sys.argv[1] + "/benchmarks")


def hwm():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024  # MiB
    return float("nan")


t_start = time.perf_counter()
from _common import jax, np  # noqa: E402  (float64 enabled)
import equinox as eqx  # noqa: E402
import jaxlens as jl  # noqa: E402

size, effects, toml, warm = int(sys.argv[2]), sys.argv[3] == "1", sys.argv[4], int(sys.argv[5])
cam = jl.Camera(20.0, math.radians(60.0), size, size, supersample=1, dtype=np.float32)
sky = jl.DefaultSky() + jl.GaussianStar(math.radians(1.0), 1.0)
kw = dict(motion=jl.CircularOrbit(), redshift=jl.Redshift(), disk=jl.Disk()) if effects else {}
scene = jl.Scene(cam, sky, **kw)
same = bool(eqx.tree_equal(scene, jl.load_scene(toml, dtype=np.float32)))
base = hwm()
t = time.perf_counter()
img = jl.render(scene, dtype=np.float32, progress=True)
first = time.perf_counter() - t
warm_s = []
for _ in range(warm):
    del img
    t = time.perf_counter()
    img = jl.render(scene, dtype=np.float32, progress=True)
    warm_s.append(time.perf_counter() - t)
assert img.shape == (size, size, 3) and bool(np.all(np.isfinite(img)))
plan = jl.plan(scene)
print(json.dumps({
    "first_s": first, "warm_s": float(np.median(warm_s)) if warm_s else None,
    "process_s": time.perf_counter() - t_start, "base_mib": base, "hwm_mib": hwm(),
    "same_as_toml": same, "blocks": plan.blocks, "stages": list(plan.stages),
    "plan": str(plan), "mean": float(img.mean()),
}))
"""


# The fit case's image, drawn by a fresh interpreter: argv = root, size, .npy path.
_RING_CHILD = r"""
import math, sys
sys.path.insert(0, sys.argv[1] + "/benchmarks")
from _common import np  # noqa: E402  (float64 enabled)
import jaxlens as jl  # noqa: E402

size = int(sys.argv[2])
img = np.asarray(jl.ring_image(20.0, math.radians(40.0), size, size, sigma=0.03,
                               brightness=1.0, floor=0.05, supersample=2))
img = img + 0.01 * np.random.default_rng(1).standard_normal(img.shape)
np.save(sys.argv[3], img)
"""

# The fit case, run by a fresh interpreter: argv = .npy path. `jaxlens` is the one on
# PYTHONPATH (this checkout's, or the baseline's). Prints one JSON line.
_FIT_CHILD = r"""
import json, math, sys, time
t_start = time.perf_counter()
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import jaxlens as jl


def hwm():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024  # MiB
    return float("nan")


img = np.load(sys.argv[1])
base = hwm()
t = time.perf_counter()
f = jl.fit_ring(img)
fit_s = time.perf_counter() - t
# A `Fit` (values in a dict) or an older `RingFit` (values as fields).
v = getattr(f, "values", None) or {n: getattr(f, n) for n in ("distance", "fov", "sigma")}
print(json.dumps({
    "fit_s": fit_s, "process_s": time.perf_counter() - t_start, "base_mib": base,
    "hwm_mib": hwm(), "distance": float(v["distance"]), "fov_deg": math.degrees(v["fov"]),
    "sigma": float(v["sigma"]), "converged": bool(f.converged), "n_pixels": int(f.n_pixels),
    "block": int(f.block), "jaxlens": jl.__file__,
}))
"""


def _run(cmd, env, cwd=None):
    """Run `cmd` (in the folder `cwd`) to completion; its own peak RSS (MiB) from
    `os.wait4`, wall time, and stdout. stderr (the progress bar) goes to ours."""
    with tempfile.TemporaryFile("w+") as out:
        t = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, env=env, cwd=cwd)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        text = out.read()
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(map(str, cmd))} failed (exit {proc.returncode}):\n{text}")
    # ru_maxrss is in KiB on Linux (bytes on macOS).
    peak = usage.ru_maxrss / (2**20 if sys.platform == "darwin" else 1024)
    return peak, wall, text


def cli_path() -> pathlib.Path:
    """The `jaxlens` console script of the running Python environment."""
    exe = pathlib.Path(sys.executable).with_name("jaxlens")
    if not exe.exists():
        raise FileNotFoundError(f"no `jaxlens` entry point beside {sys.executable}")
    return exe


def measure(size: int, warm: int, folder: pathlib.Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(_common.ROOT), env.get("PYTHONPATH", "")])
    out = {}
    for effects in (False, True):
        name = "effects" if effects else "bare"
        toml = folder / f"{name}.toml"
        toml.write_text(SCENE_TOML.format(size=size) + (EFFECTS_TOML if effects else ""))
        print(f"--- API, {name}, {size} x {size}", file=sys.stderr, flush=True)
        cmd = [sys.executable, "-c", _CHILD, str(_common.ROOT), str(size), str(int(effects)),
               str(toml), str(warm)]  # fmt: skip
        peak, wall, text = _run(cmd, env)
        rec = json.loads(text.strip().splitlines()[-1])
        rec.update(peak_mib=peak, wall_s=wall)
        out[("api", name)] = rec
        print(f"--- CLI, {name}, {size} x {size}", file=sys.stderr, flush=True)
        exr = folder / f"{name}.exr"
        cmd = [str(cli_path()), "render", str(toml), "-o", str(exr), "--size", f"{size}x{size}"]
        peak, wall, text = _run(cmd, env)
        out[("cli", name)] = {"peak_mib": peak, "wall_s": wall, "said": text.strip(),
                              "exr_mib": exr.stat().st_size / 2**20}  # fmt: skip
        exr.unlink()
    return out


def measure_fit(size: int, folder: pathlib.Path, baseline: pathlib.Path | None) -> dict:
    """The fit case: the ring image drawn once, then fitted by this checkout's jaxlens
    and (with `baseline`) by the baseline's, each in a fresh process."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(_common.ROOT), env.get("PYTHONPATH", "")])
    npy = folder / "ring.npy"
    print(f"--- fit: drawing the {size} x {size} ring", file=sys.stderr, flush=True)
    draw_peak, draw_s, _ = _run([sys.executable, "-c", _RING_CHILD, str(_common.ROOT),
                                 str(size), str(npy)], env)  # fmt: skip
    out = {"draw": {"peak_mib": draw_peak, "wall_s": draw_s}}
    sources = [("this checkout", _common.ROOT)]
    if baseline is not None:
        sources.append((f"baseline ({baseline.name})", baseline.resolve()))
    for name, root in sources:
        print(f"--- fit: jl.fit_ring, jaxlens from {root}", file=sys.stderr, flush=True)
        run_env = dict(
            env, PYTHONPATH=os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])
        )
        # Run in `root`: `python -c` puts the working folder first on the path.
        peak, wall, text = _run([sys.executable, "-c", _FIT_CHILD, str(npy)], run_env, root)
        rec = json.loads(text.strip().splitlines()[-1])
        if not rec["jaxlens"].startswith(str(root)):
            raise RuntimeError(f"the fit imported {rec['jaxlens']}, not jaxlens from {root}")
        rec.update(peak_mib=peak, wall_s=wall)
        out[name] = rec
    return out


def block_accounting(size: int) -> dict:
    """XLA's memory accounting of one compiled block of each scene (in this process)."""
    import numpy as np

    import jaxlens as jl

    cam = jl.Camera(20.0, math.radians(60.0), size, size, supersample=1, dtype=np.float32)
    sky = jl.DefaultSky() + jl.GaussianStar(math.radians(1.0), 1.0)
    scenes = {
        "bare": jl.Scene(cam, sky),
        "effects": jl.Scene(
            cam, sky, motion=jl.CircularOrbit(), redshift=jl.Redshift(), disk=jl.Disk()
        ),
    }
    return {k: jl.block_memory(s, dtype=np.float32) for k, s in scenes.items()}


def _ratio(a, b):
    return f"{a / b:.2f}" if a and b else "-"


_MARK = "<!-- section: {} -->"


def render_section(size, load, res, blocks) -> list[str]:
    """The render case's section of the report (markdown lines)."""
    mib = 2**20
    image_mib = size * size * 3 * 4 / mib
    a_b, a_e = res[("api", "bare")], res[("api", "effects")]
    c_b, c_e = res[("cli", "bare")], res[("cli", "effects")]

    def warm(r):
        return "-" if r["warm_s"] is None else f"{r['warm_s']:.2f}"

    lines = [
        _MARK.format("render"),
        f"## A {size} x {size} render with every effect against the bare scene",
        "",
        f"- Load average at the start: {load:.2f} (1 minute; wall times move with it)",
        _common.machine_markdown().rstrip("\n"),
        "",
        "Scene: a camera on a circular orbit (`CircularOrbit()`) at D = 20 R_S, FOV 60 deg,",
        "one sample a pixel, float32 pixels (ray maps in float64), the default procedural",
        "sky plus a Gaussian star (sigma 1 deg), with `Redshift()` (spectral) and a thin",
        "`Disk()` (r 3 ... 12 R_S, 80 deg, 3 crossings x 48 RK4 steps). *Bare*: the same",
        "camera and sky, no effects. Every case is a fresh process; *peak RSS* is that",
        "process's own maximum resident set (`ru_maxrss` from `os.wait4`). The float32",
        f"image alone is {image_mib:.0f} MiB.",
        "",
        "### Python API: `jl.render(scene, dtype=float32, progress=True)`",
        "",
        "| scene | first render s (compile included) | warm render s | process s |"
        " peak RSS MiB | RSS before the render MiB | blocks | stages |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for name, r in (("bare", a_b), ("effects", a_e)):
        lines.append(
            f"| {name} | {r['first_s']:.2f} | {warm(r)} | {r['wall_s']:.1f} | "
            f"{r['peak_mib']:.0f} | {r['base_mib']:.0f} | {r['blocks']} | "
            f"{', '.join(r['stages'])} |"
        )
    lines.append(
        f"| **effects / bare** | {_ratio(a_e['first_s'], a_b['first_s'])} | "
        f"{_ratio(a_e['warm_s'], a_b['warm_s'])} | {_ratio(a_e['wall_s'], a_b['wall_s'])} | "
        f"**{_ratio(a_e['peak_mib'], a_b['peak_mib'])}** | "
        f"{_ratio(a_e['base_mib'], a_b['base_mib'])} | | |"
    )
    lines += [
        "",
        f"The scene built in Python is the scene the TOML file describes: "
        f"{'yes' if a_e['same_as_toml'] and a_b['same_as_toml'] else 'NO'} "
        "(`eqx.tree_equal` with `jl.load_scene`).",
        "",
        f"### CLI: `jaxlens render scene.toml -o out.exr --size {size}x{size}`",
        "",
        "The whole process: start-up, imports, compile, render, writing the EXR.",
        "",
        "| scene | process s | peak RSS MiB | EXR MiB |",
        "|---|---:|---:|---:|",
    ]
    for name, r in (("bare", c_b), ("effects", c_e)):
        lines.append(f"| {name} | {r['wall_s']:.1f} | {r['peak_mib']:.0f} | {r['exr_mib']:.0f} |")
    lines += [
        f"| **effects / bare** | {_ratio(c_e['wall_s'], c_b['wall_s'])} | "
        f"**{_ratio(c_e['peak_mib'], c_b['peak_mib'])}** | |",
        "",
        "### One compiled block (`jl.block_memory`, XLA's accounting)",
        "",
        "| scene | temp MiB | output MiB | arguments MiB | area samples a block | blocks |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, b in blocks.items():
        p = b["plan"]
        lines.append(
            f"| {name} | {b['temp'] / mib:.1f} | {b['output'] / mib:.1f} | "
            f"{b['arguments'] / mib:.1f} | {p.samples} | {p.blocks} |"
        )
    lines += ["", "The plan of the effects scene:", "", "```", a_e["plan"], "```", ""]
    return lines


def fit_section(size, load, fit) -> list[str]:
    """The fit case's section of the report (markdown lines)."""
    image_mib = size * size * 8 / 2**20
    lines = [
        _MARK.format("fit"),
        f"## A {size} x {size} ring fit: `jl.fit_ring(image)`",
        "",
        f"- Load average at the start: {load:.2f} (1 minute; wall times move with it)",
        _common.machine_markdown().rstrip("\n"),
        "",
        "The image: `jl.ring_image` at D = 20 R_S, FOV 40 deg, sigma 0.03 rad, floor 0.05,",
        f"2 x 2 area samples a pixel, Gaussian noise 0.01; float64, {image_mib:.0f} MiB. Drawn by",
        f"one fresh process (peak RSS {fit['draw']['peak_mib']:.0f} MiB, "
        f"{fit['draw']['wall_s']:.0f} s), saved, and loaded by",
        "each fit's own fresh process: *peak RSS* is the fit process's maximum resident set",
        "(`ru_maxrss` from `os.wait4`), *RSS before the fit* its `VmHWM` once the image is",
        "loaded (imports and the image).",
        "",
        "| jaxlens | process s | fit s | peak RSS MiB | RSS before the fit MiB | D R_S | FOV deg "
        "| sigma rad | converged | compared bins | bin px |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|",
    ]
    for name, r in fit.items():
        if name == "draw":
            continue
        lines.append(
            f"| {name} | {r['wall_s']:.1f} | {r['fit_s']:.1f} | {r['peak_mib']:.0f} | "
            f"{r['base_mib']:.0f} | {r['distance']:.4f} | {r['fov_deg']:.4f} | "
            f"{r['sigma']:.5f} | {'yes' if r['converged'] else 'NO'} | {r['n_pixels']} | "
            f"{r['block']} |"
        )
    lines.append("")
    return lines


def write_report(path, sections: dict):
    """The report: the sections given (`{"render": lines, "fit": lines}`), and for a
    case not run this time its section from the existing file."""
    old = path.read_text() if path.exists() else ""
    parts = [
        "# Peak memory of large images: a render and a fit",
        "",
        "Written by [`benchmarks/bench_memory.py`](../bench_memory.py).",
        "",
    ]
    for case in ("render", "fit"):
        if case in sections:
            parts += sections[case]
            continue
        mark = _MARK.format(case)
        if mark in old:
            kept = old.split(mark, 1)[1].split("<!-- section: ", 1)[0]
            parts += [mark + kept.rstrip("\n"), ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(parts))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=None, help="image side (default 4096)")
    ap.add_argument("--quick", action="store_true",
                    help="512 x 512, report in a temporary folder (a smoke test)")  # fmt: skip
    ap.add_argument("--warm", type=int, default=1, help="warm API renders timed (default 1)")
    ap.add_argument("--out", type=pathlib.Path, default=None, help="the markdown file")
    ap.add_argument("--case", choices=("all", "render", "fit"), default="all",
                    help="the cases run (the other's section of the file is kept)")  # fmt: skip
    ap.add_argument("--baseline", type=pathlib.Path, default=None,
                    help="a tree whose jaxlens the fit also runs (before a change)")  # fmt: skip
    args = ap.parse_args(argv)
    size = args.size or (512 if args.quick else 4096)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="jaxlens-bench-memory-") as tmp:
        tmp = pathlib.Path(tmp)
        sections = {}
        if args.case in ("all", "render"):
            load = _common.load_average()
            res = measure(size, args.warm, tmp)
            sections["render"] = render_section(size, load, res, block_accounting(size))
        if args.case in ("all", "fit"):
            load = _common.load_average()
            sections["fit"] = fit_section(size, load, measure_fit(size, tmp, args.baseline))
        out = args.out
        if out is None:
            out = (tmp / "memory.md") if args.quick else _common.RESULTS / "memory.md"
        write_report(out, sections)
        print(out.read_text())
        if args.quick and args.out is None:
            print("(quick run: the report above was not kept; --out FILE keeps it)")
    print(f"[bench_memory: {time.perf_counter() - t0:.0f} s]", file=sys.stderr)


if __name__ == "__main__":
    main()
