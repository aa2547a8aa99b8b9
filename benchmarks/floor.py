"""The per-ray floor of `trace`: a minimal table look-up in C and in plain JAX, and
every `trace` path as a ratio of it, all measured in one run.

1,000,000 rays at D = 20, alpha uniform in [0.001, 0.5] rad (seed 2024), accuracy 1e-9,
in float64 and in float32 (the same alphas cast). The table is the one `trace` builds
(`jaxlens._raymap.tabulate(20.0, accuracy=1e-9, max_windings=10, captured=True,
**jaxlens._trace.TABLE_SETTINGS)`; `astype(float32)` for float32). Rows:

1. **C floor**: `floor_lookup.c`, compiled at run time (`cc -O3 -march=native
   -ffast-math -fopenmp-simd`, logs vectorised through libmvec; without those flags
   if that fails, skipped without a compiler), called through ctypes on NumPy arrays,
   one thread: cubic Hermite in tau = ln|alpha - alpha_sh| on both sides of the
   shadow edge, one log a ray.
2. **plain-JAX floor**: the same formula in `jnp`, jitted, the table as arguments.
3. a prebuilt `RayMap`, Phi only: `jax.jit(lambda m, a: m(a).phi)`.
4. a prebuilt `RayMap`, the whole `TraceResult`: `jax.jit(lambda m, a: m(a))`.
5. `jax.jit(lambda a: trace(a, 20.0, accuracy=1e-9).phi)`.
6. `jax.jit(lambda a: trace(a, 20.0, accuracy=1e-9))`, the whole `TraceResult`.
7. eager `trace(a, 20.0, accuracy=1e-9)` as the README calls it, `a` a NumPy array,
   and again with `a` a JAX array.

The cost is CPU-ns per ray (`time.process_time()`: every thread of the process) and
wall-ns per ray, the median of `--repeats` round-robin repeats (each repeat runs every
row of both dtypes in turn, so a shared machine's drift hits all alike) after one
warm-up call each; every output leaf is blocked on. The accuracy of each row: max
|Delta phi| against `Exact(iterations=12)` over rays escaping in both, and the fraction
of statuses that agree (rows that return a whole result); the C floor's Phi is also
compared with the plain-JAX floor's and the `RayMap`'s on escaping and captured rays.

The results state three ratios, each with its target: jitted Phi (row 5) / C floor
<= 2 (row 5 <= 8 CPU-ns a ray where there is no compiler), whole result (row 6) /
Phi (row 5) <= 1.3, eager with a NumPy array (row 7) / jitted (row 6) <= 1.3.

Writes `results/floor.md` and `results/floor.json` (or into `--out`).

    python benchmarks/floor.py [--rays N] [--repeats R] [--out DIR]
"""

import argparse
import ctypes
import json
import os
import pathlib
import shlex
import shutil
import subprocess
import sys
import tempfile
import time

import jax.numpy as jnp
from _common import (
    ESCAPED,
    RESULTS,
    jax,
    jaxlens,
    load_average,
    machine,
    machine_markdown,
    markdown_table,
    np,
    reference,
)

import jaxlens._raymap
import jaxlens._trace

D = 20.0
ACCURACY = 1e-9
MAX_WINDINGS = 10.0
HERE = pathlib.Path(__file__).resolve().parent
C_SOURCE = HERE / "floor_lookup.c"
C_FLAGS = ["-O3", "-march=native", "-ffast-math", "-fPIC", "-shared"]
C_VECTOR_FLAGS = ["-fopenmp-simd"]
# Targets of the three ratios (CPU-ns a ray).
TARGET_FLOOR = 2.0  # jitted Phi / C floor
TARGET_NO_COMPILER_NS = 8.0  # jitted Phi, CPU-ns a ray, where no C compiler is present
TARGET_WHOLE = 1.3  # whole TraceResult / Phi alone
TARGET_EAGER = 1.3  # eager call / jitted

DTYPES = {"float64": np.float64, "float32": np.float32}


# ---------------------------------------------------------------------------
# The C floor


def compile_floor(workdir: pathlib.Path) -> tuple[ctypes.CDLL | None, dict]:
    """`floor_lookup.c` compiled into `workdir` and loaded.

    Tries the full flags with libmvec first (vectorised logs), then without
    `-fopenmp-simd` and `-lmvec`.

    **Returns:** `(library or None, info)`; `info` has the compiler, the command that
    built the library, whether its logs are vectorised (it calls libmvec's `_ZGV...`
    variants) and a note when something was left out.
    """
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    info = {"compiler": None, "command": None, "vectorised_log": False, "note": ""}
    if cc is None:
        info["note"] = "no C compiler found: the C floor row is skipped"
        return None, info
    try:
        version = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30)
        info["compiler"] = version.stdout.splitlines()[0] if version.stdout else cc
    except (OSError, subprocess.SubprocessError):
        info["compiler"] = cc
    out = workdir / "floor_lookup.so"
    attempts = (
        ([*C_FLAGS, *C_VECTOR_FLAGS], ["-lm", "-lmvec"]),
        (C_FLAGS, ["-lm"]),
    )
    errors = []
    for flags, libs in attempts:
        argv = [cc, *flags, str(C_SOURCE), "-o", str(out), *libs]
        try:
            done = subprocess.run(argv, capture_output=True, text=True, timeout=120)
        except (OSError, subprocess.SubprocessError) as e:
            errors.append(f"{shlex.join(argv)}: {e}")
            continue
        if done.returncode != 0:
            errors.append(f"{shlex.join(argv)}: {done.stderr.strip()[-500:]}")
            continue
        try:
            lib = ctypes.CDLL(str(out))
        except OSError as e:
            errors.append(f"{shlex.join(argv)}: loading failed: {e}")
            continue
        info["command"] = shlex.join([pathlib.Path(cc).name, *argv[1:]])
        info["command"] = info["command"].replace(str(C_SOURCE), "benchmarks/floor_lookup.c")
        info["command"] = info["command"].replace(str(out), "floor_lookup.so")
        info["vectorised_log"] = b"_ZGV" in out.read_bytes()
        if not info["vectorised_log"]:
            info["note"] = "the C floor's logs are not vectorised (no libmvec call in the build)"
        if errors:
            info["note"] += ("; " if info["note"] else "") + "first try failed: " + errors[0]
        for name, real in (("lookup_f64", ctypes.c_double), ("lookup_f32", ctypes.c_float)):
            fn = getattr(lib, name)
            ptr = ctypes.c_void_p
            fn.argtypes = [ptr, ptr, ctypes.c_size_t, *[real] * 5, ptr, ptr,
                           ctypes.c_int32, ctypes.c_int32]  # fmt: skip
            fn.restype = None
        return lib, info
    info["note"] = "the C floor failed to build, row skipped: " + " | ".join(errors)
    return None, info


# ---------------------------------------------------------------------------
# The table and the plain-JAX floor


def floor_table(ray_map) -> dict:
    """The two sides of `ray_map` (built with `captured=True`) as the floors take them:
    `alpha_sh`; `tau0`, `dtau` (escaping side, captured side); `phi`, `slope` (the
    escaping knots, then the captured ones, as NumPy arrays); `n0`, `n1` (knots a side).
    """
    tau_in, dtau_in, phi_in, slope_in = ray_map.inner
    dtype = np.asarray(ray_map.phi).dtype
    return {
        "alpha_sh": np.asarray(ray_map.alpha_sh, dtype),
        "tau0": np.asarray([ray_map.tau[0], tau_in[0]], dtype),
        "dtau": np.asarray([ray_map.dtau, dtau_in], dtype),
        "phi": np.concatenate([np.asarray(ray_map.phi), np.asarray(phi_in)]).astype(dtype),
        "slope": np.concatenate([np.asarray(ray_map.slope), np.asarray(slope_in)]).astype(dtype),
        "n0": int(ray_map.phi.shape[0]),
        "n1": int(phi_in.shape[0]),
    }


def jax_floor(alpha, alpha_sh, tau0, dtau, phi, slope, n0, n1):
    """The C floor's formula in `jnp`: Phi (radians) at `alpha` (radians) by cubic
    Hermite in $\\tau = \\ln|\\alpha - \\alpha_{sh}|$ on the side's uniform knots."""
    gap = alpha - alpha_sh
    side = gap < 0
    x = (jnp.log(jnp.abs(gap)) - jnp.where(side, tau0[1], tau0[0])) * jnp.where(
        side, 1.0 / dtau[1], 1.0 / dtau[0]
    )
    i = jnp.clip(x.astype(jnp.int32), 0, jnp.where(side, n1 - 2, n0 - 2))
    t = x - i.astype(x.dtype)
    h = jnp.where(side, dtau[1], dtau[0])
    i = i + jnp.where(side, n0, 0)
    p0, p1, m0, m1 = phi[i], phi[i + 1], slope[i] * h, slope[i + 1] * h
    t2 = t * t
    t3 = t2 * t
    return (
        (2 * t3 - 3 * t2 + 1) * p0
        + (t3 - 2 * t2 + t) * m0
        + (3 * t2 - 2 * t3) * p1
        + (t3 - t2) * m1
    )


# ---------------------------------------------------------------------------
# The rows


def rows_for(dtype_name: str, alpha64: np.ndarray, lib) -> tuple[list[dict], dict]:
    """The rows of one dtype: each a dict with `name`, `what`, `call` (no arguments,
    returns the output), `whole` (returns a `TraceResult`).

    **Returns:** `(rows, context)`; `context` holds the rays and the table's floor form.
    """
    dtype = DTYPES[dtype_name]
    alpha_np = alpha64.astype(dtype)
    alpha_jx = jax.device_put(alpha_np)
    m64 = jaxlens._raymap.tabulate(
        np.float64(D), accuracy=ACCURACY, max_windings=MAX_WINDINGS, captured=True,
        **jaxlens._trace.TABLE_SETTINGS,
    )  # fmt: skip
    ray_map = m64 if dtype is np.float64 else m64.astype(jnp.float32)
    tab = floor_table(ray_map)
    rows = []

    if lib is not None:
        fn = lib.lookup_f64 if dtype is np.float64 else lib.lookup_f32
        out = np.empty_like(alpha_np)
        args = (alpha_np.ctypes.data, out.ctypes.data, alpha_np.size, tab["alpha_sh"],
                tab["tau0"][0], tab["dtau"][0], tab["tau0"][1], tab["dtau"][1],
                tab["phi"].ctypes.data, tab["slope"].ctypes.data, tab["n0"], tab["n1"])  # fmt: skip

        def c_call():
            fn(*args)
            return out

        what = "`floor_lookup.c` through ctypes, one thread, NumPy in and out"
        rows.append({"name": "1. C floor", "call": c_call, "whole": False, "what": what})

    n0, n1 = tab["n0"], tab["n1"]
    floor_fn = jax.jit(lambda a, *t: jax_floor(a, *t, n0, n1))
    targs = tuple(jax.device_put(tab[k]) for k in ("alpha_sh", "tau0", "dtau", "phi", "slope"))
    phi_of_map = jax.jit(lambda m, a: m(a).phi)
    whole_of_map = jax.jit(lambda m, a: m(a))
    phi_of_trace = jax.jit(lambda a: jaxlens.trace(a, D, accuracy=ACCURACY).phi)
    whole_of_trace = jax.jit(lambda a: jaxlens.trace(a, D, accuracy=ACCURACY))
    rows += [
        {"name": "2. plain-JAX floor", "whole": False,
         "call": lambda: floor_fn(alpha_jx, *targs),
         "what": "the same formula in `jnp` (`jnp.log`, both sides), jitted, table as arguments"},
        {"name": "3. RayMap, Phi", "whole": False,
         "call": lambda: phi_of_map(ray_map, alpha_jx),
         "what": "`jax.jit(lambda m, a: m(a).phi)`, the map prebuilt"},
        {"name": "4. RayMap, whole result", "whole": True,
         "call": lambda: whole_of_map(ray_map, alpha_jx),
         "what": "`jax.jit(lambda m, a: m(a))`, the map prebuilt"},
        {"name": "5. trace, Phi, jitted", "whole": False,
         "call": lambda: phi_of_trace(alpha_jx),
         "what": "`jax.jit(lambda a: trace(a, 20.0, accuracy=1e-9).phi)`"},
        {"name": "6. trace, whole result, jitted", "whole": True,
         "call": lambda: whole_of_trace(alpha_jx),
         "what": "`jax.jit(lambda a: trace(a, 20.0, accuracy=1e-9))`"},
        {"name": "7. trace, eager, NumPy rays", "whole": True,
         "call": lambda: jaxlens.trace(alpha_np, D, accuracy=ACCURACY),
         "what": "`trace(a, 20.0, accuracy=1e-9)`, `a` a NumPy array (as the README)"},
        {"name": "7b. trace, eager, JAX rays", "whole": True,
         "call": lambda: jaxlens.trace(alpha_jx, D, accuracy=ACCURACY),
         "what": "the same, `a` a JAX array"},
    ]  # fmt: skip
    # Relative offset from the shadow edge, alpha / alpha_sh - 1, of the rays as rounded.
    delta = alpha_np.astype(np.float64) / np.asarray(m64.alpha_sh, np.float64) - 1.0
    return rows, {"alpha": alpha_np, "table": tab, "delta": delta}


# Pause before each timed call: XLA's CPU thread pool spins for a while after its last
# task, and that spin would be charged to the next row's CPU time (a C floor timed right
# after a JAX row showed 1.4x its wall time on one thread).
SETTLE_S = 0.03


def _timed(call) -> tuple[float, float, float, object]:
    """CPU seconds (all threads of the process), wall seconds, CPU seconds of the calling
    thread alone, and the output of `call()`, every output leaf blocked on."""
    time.sleep(SETTLE_S)
    c, w, t = time.process_time(), time.perf_counter(), time.thread_time()
    out = jax.block_until_ready(call())
    c, w, t = time.process_time() - c, time.perf_counter() - w, time.thread_time() - t
    return c, w, t, out


def _phi(out):
    return np.asarray(out.phi if hasattr(out, "phi") else out, np.float64)


def _accuracy(row, out, ctx, ref_phi, ref_status) -> dict:
    """Max |phi - phi_ref| (radians) over rays escaping in both (`max_err`; also over
    well-conditioned rays, $|\\delta| \\ge 10^{-5}$, `max_err_wc`, where
    $\\delta = \\alpha/\\alpha_{sh} - 1$ and rounding alpha moves phi by about
    $\\epsilon/|\\delta|$), the $\\delta$ of the worst ray, and (for a whole result)
    the fraction of statuses that agree."""
    phi = _phi(out)
    esc = (ref_status == ESCAPED) & (ctx["alpha"] > ctx["table"]["alpha_sh"])
    agree = None
    if row["whole"]:
        status = np.asarray(out.status)
        esc &= status == ESCAPED
        agree = float(np.mean(status == ref_status))
    err = np.where(esc, np.abs(phi - ref_phi), -1.0)
    wc = np.where(np.abs(ctx["delta"]) >= 1e-5, err, -1.0)
    worst = int(np.argmax(err))
    return {
        "max_err": float(err[worst]) if esc.any() else float("nan"),
        "max_err_wc": float(wc.max()) if (wc >= 0).any() else float("nan"),
        "worst_delta": float(ctx["delta"][worst]),
        "agree": agree,
        "n_compared": int(esc.sum()),
    }


def _c_check(outs: dict, ctx) -> dict | None:
    """Max |Phi_C - Phi_row| (radians) on escaping and on captured rays, against the
    plain-JAX floor and the prebuilt `RayMap`."""
    if "1. C floor" not in outs:
        return None
    c = _phi(outs["1. C floor"])
    esc = ctx["alpha"] > ctx["table"]["alpha_sh"]
    out = {}
    for name in ("2. plain-JAX floor", "3. RayMap, Phi"):
        d = np.abs(c - _phi(outs[name]))
        out[name] = {
            "escaping": float(d[esc].max()) if esc.any() else float("nan"),
            "captured": float(d[~esc].max()) if (~esc).any() else float("nan"),
        }
    return out


# ---------------------------------------------------------------------------
# The report


def _ratio(a, b):
    return a / b if b and np.isfinite(a) and np.isfinite(b) else float("nan")


def _verdict(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def ratios(med: dict) -> list[dict]:
    """The three ratios of CPU-ns a ray (and of wall-ns), each with its target."""
    cpu, wall = med["cpu"], med["wall"]
    phi5, whole6, eager7 = (
        "5. trace, Phi, jitted",
        "6. trace, whole result, jitted",
        "7. trace, eager, NumPy rays",
    )
    out = []
    if "1. C floor" in cpu:
        r = _ratio(cpu[phi5], cpu["1. C floor"])
        out.append({"what": "jitted Phi (row 5) / C floor (row 1)", "ratio": r,
                    "wall_ratio": _ratio(wall[phi5], wall["1. C floor"]),
                    "target": f"<= {TARGET_FLOOR:g}", "pass": bool(r <= TARGET_FLOOR)})  # fmt: skip
    else:
        v = cpu[phi5]
        out.append({"what": "jitted Phi (row 5), CPU-ns a ray (no C compiler)", "ratio": v,
                    "wall_ratio": float("nan"), "target": f"<= {TARGET_NO_COMPILER_NS:g} ns",
                    "pass": bool(v <= TARGET_NO_COMPILER_NS)})  # fmt: skip
    r = _ratio(cpu[whole6], cpu[phi5])
    out.append({"what": "whole result (row 6) / Phi alone (row 5)", "ratio": r,
                "wall_ratio": _ratio(wall[whole6], wall[phi5]),
                "target": f"<= {TARGET_WHOLE:g}", "pass": bool(r <= TARGET_WHOLE)})  # fmt: skip
    r = _ratio(cpu[eager7], cpu[whole6])
    out.append({"what": "eager, NumPy rays (row 7) / jitted (row 6)", "ratio": r,
                "wall_ratio": _ratio(wall[eager7], wall[whole6]),
                "target": f"<= {TARGET_EAGER:g}", "pass": bool(r <= TARGET_EAGER)})  # fmt: skip
    return out


def _table_md(res: dict) -> str:
    cpu, wall = res["median"]["cpu"], res["median"]["wall"]
    c_floor, j_floor = cpu.get("1. C floor"), cpu["2. plain-JAX floor"]
    lines = []
    for row in res["rows"]:
        n = row["name"]
        acc = row["accuracy"]
        lines.append([
            n,
            f"{cpu[n]:.2f}",
            f"{wall[n]:.2f}",
            f"{cpu[n] / c_floor:.2f}x" if c_floor else "-",
            f"{cpu[n] / j_floor:.2f}x",
            f"{acc['max_err']:.2e}",
            f"{acc['agree']:.6f}" if acc["agree"] is not None else "-",
            row["what"],
        ])  # fmt: skip
    head = ["row", "CPU-ns/ray", "wall-ns/ray", "vs C floor", "vs plain-JAX floor",
            "max err (rad)", "status agree", "what"]  # fmt: skip
    out = markdown_table(head, lines) + "\n"
    for r in res["ratios"]:
        wall_r = f" (wall {r['wall_ratio']:.2f})" if np.isfinite(r["wall_ratio"]) else ""
        out += (f"- {r['what']}: **{r['ratio']:.2f}**{wall_r}, target {r['target']}: "
                f"**{_verdict(r['pass'])}**\n")  # fmt: skip
    wc = [f"{r['name'].split('.')[0]}: {r['accuracy']['max_err_wc']:.1e}" for r in res["rows"]]
    worst = max(res["rows"], key=lambda r: r["accuracy"]["max_err"])["accuracy"]
    out += (f"- Max err over well-conditioned rays, |alpha/alpha_sh - 1| >= 1e-5 (rad), "
            f"by row: {', '.join(wc)}; the max err column's worst ray lies at "
            f"alpha/alpha_sh - 1 = {worst['worst_delta']:.1e}\n")  # fmt: skip
    if res["c_check"]:
        parts = [f"{k}: {v['escaping']:.1e} escaping, {v['captured']:.1e} captured"
                 for k, v in res["c_check"].items()]  # fmt: skip
        out += f"- C floor's Phi against {'; '.join(parts)} (max |diff|, rad)\n"
    return out + "\n"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rays", type=int, default=1_000_000)
    p.add_argument("--repeats", type=int, default=9, help="round-robin repeats (median)")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS, help="results folder")
    p.add_argument("--runs", type=int, default=1, help="fresh processes, one after another")
    args = p.parse_args(argv)
    if args.rays < 1 or args.repeats < 1 or args.runs < 1:
        p.error(f"--rays, --repeats and --runs must be >= 1, got {args.rays}, "
                f"{args.repeats}, {args.runs}")  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    command = "python benchmarks/floor.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    if args.runs > 1:
        return _runs(args, command)
    info = machine()
    print(machine_markdown(info), flush=True)
    load_before = os.getloadavg() if hasattr(os, "getloadavg") else (load_average(),) * 3

    alpha = np.random.default_rng(2024).uniform(0.001, 0.5, args.rays)
    with tempfile.TemporaryDirectory(prefix="jaxlens-floor-") as tmp:
        lib, cinfo = compile_floor(pathlib.Path(tmp))
        print(f"C floor: {cinfo}", flush=True)
        rows, ctxs, outs, first = [], {}, {}, {}
        for dt in DTYPES:
            rs, ctxs[dt] = rows_for(dt, alpha, lib)
            for r in rs:
                r["dtype"] = dt
                t = time.perf_counter()
                outs[dt, r["name"]] = _timed(r["call"])[3]  # warm-up (compiles)
                first[dt, r["name"]] = time.perf_counter() - t
                print(f"warm-up {dt} {r['name']}: {first[dt, r['name']]:.2f} s", flush=True)
            rows += rs
        times = {(r["dtype"], r["name"]): ([], [], []) for r in rows}
        for _ in range(args.repeats):  # round robin: drift hits every row alike
            for r in rows:
                for series, x in zip(times[r["dtype"], r["name"]], _timed(r["call"])[:3]):
                    series.append(x * 1e9 / args.rays)
    load_after = os.getloadavg() if hasattr(os, "getloadavg") else (load_average(),) * 3

    results = {}
    for dt in DTYPES:
        ctx = ctxs[dt]
        ref_phi, ref_status = reference(ctx["alpha"], np.full(args.rays, D))
        res = {"rows": [], "median": {"cpu": {}, "wall": {}}}
        for r in (r for r in rows if r["dtype"] == dt):
            cpu, wall, thread = times[dt, r["name"]]
            res["median"]["cpu"][r["name"]] = float(np.median(cpu))
            res["median"]["wall"][r["name"]] = float(np.median(wall))
            res["rows"].append({
                "name": r["name"], "what": r["what"], "cpu_ns": cpu, "wall_ns": wall,
                "calling_thread_cpu_ns": thread,
                "warm_up_s": first[dt, r["name"]],
                "accuracy": _accuracy(r, outs[dt, r["name"]], ctx, ref_phi, ref_status),
            })  # fmt: skip
        res["ratios"] = ratios(res["median"])
        res["c_check"] = _c_check({k[1]: v for k, v in outs.items() if k[0] == dt}, ctx)
        res["knots"] = [ctx["table"]["n0"], ctx["table"]["n1"]]
        results[dt] = res
        print(_table_md(res), flush=True)

    payload = {"machine": info, "command": command, "rays": args.rays,
               "repeats": args.repeats, "distance": D, "accuracy": ACCURACY,
               "load_before": list(load_before), "load_after": list(load_after),
               "c_floor": cinfo, **results}  # fmt: skip
    (args.out / "floor.json").write_text(json.dumps(payload, indent=1) + "\n")

    r64 = results["float64"]["ratios"]
    if cinfo["command"]:
        how = "vectorised through libmvec" if cinfo["vectorised_log"] else "NOT vectorised"
        c_line = f"- C floor: `{cinfo['command']}` ({cinfo['compiler']}); logs {how}"
    else:
        c_line = "- C floor: none (the ratio to it is replaced by row 5's CPU-ns a ray)"
    if cinfo["note"]:
        c_line += f". {cinfo['note']}"
    md = [
        "# The per-ray floor of trace: a minimal look-up in C and in JAX, and every "
        "trace path against it\n\n",
        machine_markdown(info),
        f"- Command: `{command}`; load average (1, 5, 15 min) "
        f"{', '.join(f'{x:.2f}' for x in load_before)} before, "
        f"{', '.join(f'{x:.2f}' for x in load_after)} after\n",
        f"- Rays: {args.rays}, D = {D:g}, alpha uniform in [0.001, 0.5] rad (seed 2024), "
        f"accuracy {ACCURACY:g}; the table `trace` builds ({results['float64']['knots'][0]} "
        f"escaping and {results['float64']['knots'][1]} captured knots), "
        "`astype(float32)` for float32.\n",
        f"- Cost: CPU-ns a ray (`time.process_time()`, every thread of the process) and "
        f"wall-ns a ray, the median of {args.repeats} round-robin repeats over all rows of "
        "both dtypes after one warm-up call each; every output leaf blocked on. Ratios "
        "are of CPU-ns.\n",
        c_line + "\n",
        "- Max err: max |Delta phi| (rad) against `Exact(iterations=12)` in float64 (for "
        "float32, of the rounded rays) over rays escaping in both; status agree: the "
        "fraction of rays whose status matches (rows with a whole result).\n\n",
        "**" + "; ".join(f"{r['what']}: {r['ratio']:.2f} ({_verdict(r['pass'])}, "
                         f"target {r['target']})" for r in r64) + ".**\n\n",
        "## float64\n\n",
        _table_md(results["float64"]),
        "## float32\n\n",
        _table_md(results["float32"]),
    ]  # fmt: skip
    (args.out / "floor.md").write_text("".join(md))
    print(f"wrote {args.out / 'floor.md'} and {args.out / 'floor.json'}")
    return results


# glibc's malloc returns a freed block of more than its (adaptive) threshold to the
# system, so the next call's output buffer of that size is fresh memory, faulted in page
# by page (~1 ms for 8 MB): whether a run pays it depends on the order of its earlier
# allocations, and the same program then costs up to twice as much in one process as in
# the next. These settings keep freed memory in the process (glibc reads them at start).
KEEP_FREED = {"MALLOC_MMAP_THRESHOLD_": str(2**30), "MALLOC_TRIM_THRESHOLD_": str(2**32)}
REGIMES = {"glibc defaults": {}, "freed memory kept": KEEP_FREED}


def _runs(args, command: str) -> list[dict]:
    """`args.runs` fresh processes of one run each under each malloc regime
    (`REGIMES`), one after another. The results show, in full, the run with the median
    jitted Phi / C floor (float64) among those with freed memory kept, and every run's
    three ratios with the median of each over a regime's runs; the verdicts are on
    those medians."""
    runs = []
    with tempfile.TemporaryDirectory(prefix="jaxlens-floor-runs-") as tmp:
        for k in range(args.runs):
            for regime, env in REGIMES.items():
                out = pathlib.Path(tmp) / f"{k}-{len(runs)}"
                argv = [sys.executable, str(pathlib.Path(__file__).resolve()),
                        "--rays", str(args.rays), "--repeats", str(args.repeats),
                        "--out", str(out)]  # fmt: skip
                print(f"run {k + 1} of {args.runs}, {regime}", flush=True)
                subprocess.run(argv, check=True, env={**os.environ, **env})
                runs.append((regime, json.loads((out / "floor.json").read_text()),
                             (out / "floor.md").read_text()))  # fmt: skip
    kept = [i for i, r in enumerate(runs) if r[0] == "freed memory kept"]
    headline = [runs[i][1]["float64"]["ratios"][0]["ratio"] for i in kept]
    shown = kept[int(np.argsort(headline)[len(headline) // 2])]
    _, payload, md = runs[shown]
    payload = dict(payload, command=command, shown_run=shown, runs=[
        {"regime": g, "env": REGIMES[g], **{dt: r[dt]["ratios"] for dt in DTYPES}}
        for g, r, _ in runs])  # fmt: skip
    lines = [
        f"## Every run: {args.runs} fresh processes under each malloc regime\n\n",
        "glibc's malloc gives a freed block above its adaptive threshold back to the "
        "system, so a later output buffer of that size (8 MB here) is faulted in page by "
        "page on every call; whether a process pays it depends on the order of its "
        "earlier allocations, and the same program then costs up to twice as much in one "
        "process as in the next. *freed memory kept*: the runs with "
        + ", ".join(f"`{k}={v}`" for k, v in KEEP_FREED.items())
        + " in the environment, which keep it in the process (any program can set them; "
        "other allocators have their own settings). The tables above are those of run "
        f"{shown // len(REGIMES) + 1} with freed memory kept (the median jitted Phi / C "
        "floor in float64). Each run's ratios of CPU-ns, and the median of each over a "
        "regime's runs, on which the verdicts stand:\n\n",
    ]
    headline = {}
    for dt in DTYPES:
        names = [q["what"] for q in runs[0][1][dt]["ratios"]]
        targets = [q["target"] for q in runs[0][1][dt]["ratios"]]
        body = []
        for regime in REGIMES:
            mine = [r for g, r, _ in runs if g == regime]
            body += [[regime, str(k + 1), *(f"{q['ratio']:.2f}" for q in r[dt]["ratios"])]
                     for k, r in enumerate(mine)]  # fmt: skip
            med = [float(np.median([r[dt]["ratios"][i]["ratio"] for r in mine]))
                   for i in range(len(names))]  # fmt: skip
            cells = [(m, t) for m, t in zip(med, targets, strict=True)]
            body.append([regime, "median", *(f"**{m:.2f}** ({_verdict(_meets(m, t))}, "
                                             f"target {t})" for m, t in cells)])  # fmt: skip
            headline[dt, regime] = "; ".join(
                f"{w}: {m:.2f} ({_verdict(_meets(m, t))}, target {t})"
                for w, (m, t) in zip(names, cells, strict=True))  # fmt: skip
        lines += [f"### {dt}\n\n", markdown_table(["malloc", "run", *names], body), "\n"]
    bold = next(line for line in md.splitlines() if line.startswith("**"))
    md = md.replace(bold, "\n\n".join(
        f"**float64, medians of {args.runs} runs, {regime}: {headline['float64', regime]}.**"
        for regime in REGIMES))  # fmt: skip
    md = md.replace("- Command: `" + runs[shown][1]["command"] + "`",
                    f"- Command: `{command}` (the run shown had "
                    + " ".join(f"{k}={v}" for k, v in KEEP_FREED.items()) + ")")  # fmt: skip
    (args.out / "floor.md").write_text(md + "".join(lines))
    (args.out / "floor.json").write_text(json.dumps(payload, indent=1) + "\n")
    print(f"wrote {args.out / 'floor.md'} and {args.out / 'floor.json'}")
    return payload["runs"]


def _meets(value: float, target: str) -> bool:
    """Whether `value` meets a target written as '<= x' or '<= x ns'."""
    return bool(value <= float(target.split()[1]))


if __name__ == "__main__":
    main()
