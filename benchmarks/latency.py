"""Time to first result: what a user waits for in a fresh process, against `import jax`.

Each row runs in fresh Python processes (median of `--repeats`, default 3), in one run,
beside the yardstick `python -c "import jax"` timed the same way, so the ratios hold on
a shared machine whose absolute speed drifts. Rows:

- `import jax`, `import jaxlens`, `jaxlens --help`;
- the first `trace` on 1,000 and on 100,000 rays (eager, as the README calls it), and
  on 100,000 in a script that calls `jaxlens.keep_programs()` after one that did;
- `jaxlens render -o out.png` of the default scene, with the persistent compilation
  cache off ("cold") and with it filled by an earlier run ("warm cache");
- `jaxlens fit RING.png --json --star-sigma-deg 1.5` on the fit benchmark's first ring
  (the independent renderer of `bench_fit.py`, its width given as there), cold and
  with a warm cache.

For the jaxlens rows a breakdown comes from the child process itself: importing jax,
importing jaxlens, then JAX's own compile events (`jax.monitoring`: tracing to a jaxpr,
lowering to MLIR, XLA's compile, retrieval from XLA's persistent cache) and the rest
(host set-up, loading the executables the CLI keeps in its cache folder, and running).
Three warm figures are measured inside one process: an eager `trace` on 100,000 rays
called again at the same distance and the same call jitted (each the fastest of 20
calls after one), and the notebook explorer's time from a slider change to its new
image (distance, FOV, star position, the median of five changes after one; each new
distance needs a new ray map).

The XLA option profiles (`jaxlens._compile.PROFILES`): with `--profiles`, the cold rows
(first trace of 100,000 rays, cold render, cold fit) run again for each profile with
its programs compiled under the profile it builds on instead (`BUILDS_ON`: the older
fusion at LLVM level 1 against XLA's defaults, level 0 in one piece against level 1),
in the same run: a profile is kept where it saves more than ~10 % of a row.

Writes `results/latency.md` and `results/latency.json`. `--quick`: one repeat and no
fit rows (a smoke run).
"""

import argparse
import compileall
import json
import math
import os
import pathlib
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
    "/jax/compilation_cache/cache_retrieval_time_sec": "cache",
}
# The profile each profile builds on: the ablation compiles its programs under that one.
BUILDS_ON = {
    "legacy_fusion_o1": "xla",
    "legacy_fusion_o0_side": "legacy_fusion_o1",
}
PARTS = ("import_jax", "import_jaxlens", "trace", "lower", "compile", "cache", "rest")

# --------------------------------------------------------------------- child side


def _child(task: str, arg: str) -> None:
    """Run one task in this (fresh) process and print its breakdown as JSON."""
    t0 = time.perf_counter()
    import jax
    import jax.monitoring

    t_jax = time.perf_counter()
    spent = dict.fromkeys(EVENTS.values(), 0.0)

    def listen(event, duration, **_):
        if event in EVENTS:
            spent[EVENTS[event]] += duration

    jax.monitoring.register_event_duration_secs_listener(listen)
    without = os.environ.get("JAXLENS_BENCH_WITHOUT_PROFILE")
    if without:  # the profile ablation: its programs under the profile it builds on
        from jaxlens import _compile

        _compile.PROFILES[without] = _compile.PROFILES[BUILDS_ON[without]]
    if task in ("render", "fit"):
        from jaxlens.cli import main
    else:
        import jaxlens
    t_lens = time.perf_counter()
    if task.startswith("trace"):
        import numpy as np

        if task == "trace-kept":  # a script that keeps its programs, as the CLI does
            jaxlens.keep_programs()

        n = int(arg)
        alpha = np.linspace(0.05, 3.0, n)
        jax.block_until_ready(jaxlens.trace(alpha, 10.0))
    elif task == "render":
        code = main(["render", "-o", arg])
        assert code == 0, code
    elif task == "fit":
        import contextlib
        import io

        with contextlib.redirect_stdout(io.StringIO()):
            path, sigma_deg = arg.rsplit("|", 1)
            code = main(["fit", path, "--json", "--star-sigma-deg", sigma_deg])
        assert code == 0, code
    t_end = time.perf_counter()
    out = {"import_jax": t_jax - t0, "import_jaxlens": t_lens - t_jax, **spent}
    out["rest"] = t_end - t_lens - sum(spent.values())
    print(json.dumps(out))
    if task in ("render", "fit"):  # the process ends as the `jaxlens` command's does
        from jaxlens.cli import finish

        finish(0)


# -------------------------------------------------------------------- parent side


def _jaxlens_exe() -> str:
    return str(pathlib.Path(sys.executable).with_name("jaxlens"))


def _timed(argv, env=None) -> tuple[float, dict | None]:
    """Wall time of one fresh process, and the breakdown it printed (if any)."""
    t0 = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"{argv} failed:\n{done.stderr[-2000:]}")
    last = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else ""
    return wall, (json.loads(last) if last.startswith("{") else None)


def _child_argv(task, arg=""):
    return [sys.executable, str(pathlib.Path(__file__).resolve()), "--child", task, arg]


def _row(name, runs):
    """Median wall and the median of each part over the runs."""
    walls = [w for w, _ in runs]
    row = {"name": name, "wall": statistics.median(walls), "walls": walls}
    parts = [p for _, p in runs if p]
    if parts:
        row["parts"] = {k: statistics.median(p[k] for p in parts) for k in PARTS}
    return row


def _ring_png(folder: pathlib.Path) -> str:
    """The fit benchmark's first ring (independent renderer) written as its PNG:
    `"PATH|SIGMA_DEG"`, the fit child's argument."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_fit
    import numpy as np

    d, fov, w, h, sig, amp, floor, noise, bits, _ = bench_fit.CASES[0]
    clean = bench_fit.ring_image(d, math.radians(fov), w, h, math.radians(sig), amp, floor)
    path = folder / "ring.png"
    rng = np.random.default_rng(2026)
    bench_fit.write_png(path, clean + noise * rng.standard_normal(clean.shape), bits)
    return f"{path}|{sig!r}"  # the child's argument: the image and the star's width


def _in_process():
    """Warm figures inside one process: eager trace again at one distance, jitted, and
    the explorer's slider-to-image times; in float64, as the README's example (run
    first, before this process renders the fit's ring, which sets float64 too)."""
    import jax
    import numpy as np

    import jaxlens

    jax.config.update("jax_enable_x64", True)

    alpha = np.linspace(0.05, 3.0, 100_000)
    out = {}

    def best(f, n=20):
        f()
        ts = []
        for _ in range(n):
            t = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t)
        return min(ts)

    out["trace_eager_again"] = best(lambda: jax.block_until_ready(jaxlens.trace(alpha, 10.0)))
    jitted = jax.jit(lambda a: jaxlens.trace(a, 10.0))
    out["trace_jitted"] = best(lambda: jax.block_until_ready(jitted(alpha)))
    try:
        from jaxlens._explorer import Explorer
    except ImportError:
        return out
    ex = Explorer()
    moves = {
        "distance": (ex.distance, (25.0, 30.0, 40.0, 50.0, 60.0, 70.0)),
        "fov": (ex.fov, (50.0, 55.0, 65.0, 70.0, 75.0, 80.0)),
        "star position": (ex.star_lon, (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)),
    }
    for label, (slider, values) in moves.items():
        ts = []
        for v in values:
            t = time.perf_counter()
            slider.value = v  # the callback renders and encodes the PNG
            ts.append(time.perf_counter() - t)
        out[f"explorer_{label}"] = statistics.median(ts[1:])  # the first may compile
    out["explorer_size"] = f"{ex.width}x{ex.height}"
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="one repeat, no fit rows")
    ap.add_argument("--profiles", action="store_true",
                    help="the cold rows again without each XLA option profile")  # fmt: skip
    args = ap.parse_args()
    if args.child:
        _child(*args.child)
        return
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import _common

    n = 1 if args.quick else args.repeats
    # jaxlens's own modules byte-compiled, as pip does for an installed wheel and Python
    # does at a first import (unless PYTHONDONTWRITEBYTECODE is set, as on some CI
    # machines): otherwise each child compiles ~40 modules from source (~0.1 s) while
    # `import jax` reads its byte code.
    compileall.compile_dir(ROOT / "jaxlens", quiet=1)
    load = os.getloadavg()[0]
    inproc = _in_process()
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="jaxlens-latency-"))
    off = dict(os.environ, JAXLENS_CACHE_DIR="", JAX_COMPILATION_CACHE_DIR="")
    rows = []

    def run(name, argv, env=off, prime=None):
        runs = []
        for _ in range(n):
            if prime:
                prime()
            runs.append(_timed(argv, env))
        rows.append(_row(name, runs))
        print(f"{name}: {rows[-1]['wall']:.2f} s", flush=True)

    run("import jax", [sys.executable, "-c", "import jax"])
    run("import jaxlens", [sys.executable, "-c", "import jaxlens"])
    run("jaxlens --help", [_jaxlens_exe(), "--help"])
    run("first trace, 1,000 rays", _child_argv("trace", "1000"))
    run("first trace, 100,000 rays", _child_argv("trace", "100000"))
    png = tmp / "out.png"
    run("jaxlens render (default scene), cold", _child_argv("render", str(png)))
    cache = tmp / "cache"
    warm = dict(os.environ, JAXLENS_CACHE_DIR=str(cache), JAX_COMPILATION_CACHE_DIR="")
    _timed(_child_argv("render", str(png)), warm)  # fills the cache
    run("jaxlens render (default scene), warm cache", _child_argv("render", str(png)), warm)
    kept = _child_argv("trace-kept", "100000")
    _timed(kept, warm)  # keeps trace's program
    run("first trace, 100,000 rays, programs kept (`keep_programs`)", kept, warm)
    if not args.quick:
        ring = _ring_png(tmp)
        run("jaxlens fit (benchmark ring), cold", _child_argv("fit", str(ring)))
        _timed(_child_argv("fit", str(ring)), warm)
        run("jaxlens fit (benchmark ring), warm cache", _child_argv("fit", str(ring)), warm)
    ablation = []
    if args.profiles:
        cold = [
            ("first trace, 100,000 rays", _child_argv("trace", "100000")),
            ("jaxlens render (default scene), cold", _child_argv("render", str(png))),
        ]
        if not args.quick:
            cold.append(("jaxlens fit (benchmark ring), cold", _child_argv("fit", str(ring))))
        for profile in BUILDS_ON:
            env = dict(off, JAXLENS_BENCH_WITHOUT_PROFILE=profile)
            for name, argv in cold:
                runs = [_timed(argv, env) for _ in range(n)]
                ablation.append({"profile": profile, **_row(name, runs)})
                print(f"without {profile}: {name}: {ablation[-1]['wall']:.2f} s", flush=True)
    shutil.rmtree(tmp, ignore_errors=True)
    write_report(rows, inproc, load, _common, ablation)


GOALS = {
    "import jaxlens": 1.3,
    "jaxlens render (default scene), cold": 2.8,
    "jaxlens render (default scene), warm cache": 1.8,
    "first trace, 100,000 rays": 1.55,
    "jaxlens fit (benchmark ring), cold": 6.6,
    "jaxlens fit (benchmark ring), warm cache": 3.0,
}


def write_report(rows, inproc, load, common, ablation=()):
    base = rows[0]["wall"]
    lines = [
        "# Latency: time to first result in a fresh process",
        "",
        common.machine_markdown().rstrip(),
        f"- Load average {load:.1f} at the start. Produced by `benchmarks/latency.py` "
        f"(median of {len(rows[0]['walls'])} fresh processes a row; jaxlens's modules "
        "byte-compiled first, as an installed wheel's are).",
        "",
        "Wall: the whole process, Python start-up and exit included (the render and fit "
        "rows end as the `jaxlens` command does, `jaxlens.cli.finish`; the trace rows as a "
        "script does). Ratio: to `import jax` in the "
        "same run. The parts (seconds, medians) are measured inside the process: importing "
        "jax and jaxlens, JAX's tracing, lowering and XLA compilation (its own events), "
        "retrieval from XLA's persistent cache, and the rest (host work, loading the "
        "executables the CLI keeps in its cache folder, and running). render "
        "and fit compile their next program on a second thread while the first compiles or "
        "runs (`jaxlens._compile.ahead`), so the parts can add up to more than the process "
        "took: the rest (what is left of the wall time) is then negative.",
        "",
        "| what | wall s | ratio | goal | " + " | ".join(PARTS) + " |",
        "|---|---|---|---|" + "---|" * len(PARTS),
    ]
    for r in rows:
        goal = GOALS.get(r["name"])
        ratio = r["wall"] / base
        met = goal is not None and ratio <= goal
        mark = "" if goal is None else f"<= {goal}" + (" met" if met else " **not met**")
        parts = r.get("parts")
        cells = [f"{parts[k]:.2f}" for k in PARTS] if parts else ["-"] * len(PARTS)
        lines.append(f"| {r['name']} | {r['wall']:.2f} | {ratio:.2f} | {mark} | "
                     + " | ".join(cells) + " |")  # fmt: skip
    lines += [
        "",
        "Warm, in one process (trace: the fastest of 20 calls after one; explorer: the "
        "median of five changes after one):",
        "",
        f"- `trace(alpha, 10.0)` on 100,000 float64 rays, eager, called again at the same "
        "distance: "
        f"{1e3 * inproc['trace_eager_again']:.1f} ms; the same call jitted: "
        f"{1e3 * inproc['trace_jitted']:.1f} ms.",
    ]
    if "explorer_size" in inproc:
        lines.append(
            f"- Notebook explorer at its default {inproc['explorer_size']}, from a slider "
            "change to the new image (goal: under 0.3 s): "
            + ", ".join(
                f"{k} {inproc[f'explorer_{k}']:.3f} s" for k in ("distance", "fov", "star position")
            )  # fmt: skip
            + "."
        )
    if ablation:
        walls = {r["name"]: r["wall"] for r in rows}
        lines += [
            "",
            "## The XLA option profiles",
            "",
            "Each cold row again with one profile's programs compiled under the profile it "
            "builds on instead, in the same run (medians as above); saved: the wall time "
            "without the profile over the time with it, less one.",
            "",
            "| profile | options | instead | row | wall s with | wall s without | saved |",
            "|---|---|---|---|---|---|---|",
        ]
        from jaxlens import _compile

        for r in ablation:
            opts = ", ".join(f"`{k}={v}`" for k, v in _compile.PROFILES[r["profile"]].items())
            with_ = walls[r["name"]]
            lines.append(f"| {r['profile']} | {opts} | {BUILDS_ON[r['profile']]} | "
                         f"{r['name']} | {with_:.2f} | "
                         f"{r['wall']:.2f} | {100 * (r['wall'] / with_ - 1):+.0f} % |")  # fmt: skip
    res = common.RESULTS
    res.mkdir(parents=True, exist_ok=True)
    blob = {"rows": rows, "warm": inproc, "profiles": list(ablation)}
    (res / "latency.json").write_text(json.dumps(blob, indent=1) + "\n")
    (res / "latency.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {res / 'latency.md'}")


if __name__ == "__main__":
    main()
