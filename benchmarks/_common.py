"""Shared pieces of the benchmarks: ray sets, the exact reference, timing, the machine.

Every benchmark measures on this machine in one run, so the numbers it writes are
ratios one can trust even when the absolute speed drifts (a shared machine): warm-up
first, `block_until_ready()`, compile time apart, medians of repeats.
"""

import datetime
import os
import pathlib
import platform
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
# Where result files go: `benchmarks/results/`, or `$JAXLENS_BENCH_RESULTS` (a smoke run
# on a loaded machine writes there, so the committed figures are left alone).
RESULTS = pathlib.Path(os.environ.get("JAXLENS_BENCH_RESULTS") or ROOT / "benchmarks" / "results")
# The figures that docs/ shows: `docs/images/`, or the results folder when it is redirected.
DOCS_IMAGES = RESULTS if os.environ.get("JAXLENS_BENCH_RESULTS") else ROOT / "docs" / "images"
if str(ROOT) not in sys.path:  # run from a checkout without `pip install -e .`
    sys.path.insert(0, str(ROOT))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxlens  # noqa: E402

ESCAPED, CAPTURED, UNRESOLVED = jaxlens.ESCAPED, jaxlens.CAPTURED, jaxlens.UNRESOLVED

# Camera distances of the ray sets (units of R_S).
NEAR_DISTANCES = (1.2, 1.6, 3.0, 10.0, 100.0, 1e3, 1e5)
FAR_DISTANCES = (1e4, 1e5, 1e6, 1e7, 1e8)


# ---------------------------------------------------------------------------
# The machine


def machine() -> dict:
    """What ran the benchmark: CPU model, cores, versions, date, commit."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    try:
        commit = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(ROOT), "status", "--porcelain", "--", "jaxlens"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        if dirty:
            commit += " + uncommitted changes in jaxlens/"
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    versions = {"python": platform.python_version(), "jax": jax.__version__}
    for mod in ("jaxlib", "numpy", "scipy", "diffrax", "equinox"):
        try:
            versions[mod] = __import__(mod).__version__
        except ImportError:
            pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "usable_cores": usable,
        "devices": ", ".join(str(d) for d in jax.devices()),
        "versions": versions,
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "commit": commit,
    }


def load_average() -> float:
    """The 1-minute load average (NaN where the OS has none): wall times move with it."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def machine_markdown(info: dict | None = None) -> str:
    """The machine as a few markdown lines."""
    info = machine() if info is None else info
    versions = ", ".join(f"{k} {v}" for k, v in info["versions"].items())
    return (
        f"- Machine: {info['cpu']}, {info['cores']} cores ({info['usable_cores']} usable); "
        f"JAX devices: {info['devices']}\n"
        f"- Software: {versions}\n"
        f"- Date: {info['date']}; jaxlens commit {info['commit']}\n"
    )


# ---------------------------------------------------------------------------
# Ray sets


def ray_sets(n: int, seed: int = 0) -> dict:
    """The three ray sets, each of `n` rays (float64 NumPy arrays).

    - `moderate`: D = 20, alpha uniform in [0.001, 0.5] rad (a quarter is captured).
    - `near-critical`: D in `NEAR_DISTANCES` (1.2 ... 1e5), alpha = alpha_sh (1 + delta),
      |delta| log-uniform in [1e-10, 1e-2], either sign (half captured).
    - `far camera`: D in `FAR_DISTANCES` (1e4 ... 1e8), alpha = sqrt(2/D) 10^U(-0.5, 0.5),
      around the Einstein ring.

    **Returns:** `{name: {"alpha", "distance", "delta"}}`; `delta` is the relative offset
    from the shadow edge, $\\alpha/\\alpha_{sh} - 1$ (radians / radians).
    """
    rng = np.random.default_rng(seed)
    sets = {}
    alpha = rng.uniform(0.001, 0.5, n)
    dist = np.full(n, 20.0)
    sets["moderate"] = {"alpha": alpha, "distance": dist}
    dist = np.asarray(NEAR_DISTANCES)[np.arange(n) % len(NEAR_DISTANCES)]
    delta = rng.choice([-1.0, 1.0], n) * 10.0 ** rng.uniform(-10.0, -2.0, n)
    alpha = np.asarray(jaxlens.shadow_angle(dist)) * (1.0 + delta)
    sets["near-critical"] = {"alpha": alpha, "distance": dist}
    dist = np.asarray(FAR_DISTANCES)[np.arange(n) % len(FAR_DISTANCES)]
    alpha = np.sqrt(2.0 / dist) * 10.0 ** rng.uniform(-0.5, 0.5, n)
    sets["far camera"] = {"alpha": alpha, "distance": dist}
    for s in sets.values():
        sh = np.asarray(jaxlens.shadow_angle(s["distance"]))
        s["delta"] = s["alpha"] / sh - 1.0
    return sets


# ---------------------------------------------------------------------------
# The reference


@jax.jit
def _exact12(alpha, distance):
    r = jaxlens.trace(alpha, distance, method=jaxlens.Exact(iterations=12))
    return r.phi, r.status


def reference(alpha, distance):
    """Exact escape angle (radians) and status, `Exact(iterations=12)` in float64.

    The inputs are taken as they are (cast to float64 exactly), so a float32 run is
    compared with the exact answer for its own, rounded, rays.
    """
    phi, status = _exact12(np.asarray(alpha, np.float64), np.asarray(distance, np.float64))
    return np.asarray(phi), np.asarray(status)


def phi_mpmath(alpha: float, distance: float, dps: int = 40):
    """Independent reference: the escape angle by mpmath quadrature, or None if captured.

    $\\Phi = \\int du / \\sqrt{G(u)}$, $G = 1/b^2 - u^2 + u^3$, along the ray; through a
    turning point $u_2$ with the substitution $u = u_2 - s^2$, which removes the
    inverse square root: $du/\\sqrt G = 2 ds / \\sqrt{(u - u_1)(u_3 - u)}$. `dps` decimal
    digits; the float inputs are taken exactly.

    **Returns:** $\\Phi$ (radians) as a float, or None for a captured ray.
    """
    import mpmath as mp

    with mp.workdps(dps):
        a, d = mp.mpf(float(alpha)), mp.mpf(float(distance))
        u0 = 1 / d
        b = d * abs(mp.sin(a)) / mp.sqrt(1 - 1 / d)
        c = 1 / (b * b)
        inward = mp.cos(a) > 0

        def g(u):
            return c - u * u + u * u * u

        def free(lo, hi):  # no root of G in [lo, hi]; split at the near-double root 2/3
            pts = [lo] + ([mp.mpf(2) / 3] if lo < mp.mpf(2) / 3 < hi else []) + [hi]
            return mp.quad(lambda u: 1 / mp.sqrt(g(u)), pts)

        if b * b > mp.mpf(27) / 4:  # three real roots u1 < 0 < u2 <= u3
            roots = sorted(
                mp.re(r) for r in mp.polyroots([1, -1, 0, c], maxsteps=400, extraprec=200)
            )
            u1, u2, u3 = roots
            if u0 >= u3:
                return None  # inside the photon sphere, heading to the horizon

            def to_turn(y):  # int_y^u2 du / sqrt(G)
                smax = mp.sqrt(u2 - y)
                if smax == 0:
                    return mp.mpf(0)
                pts = [0, smax]
                w = mp.sqrt(u3 - u2)
                if w < smax:
                    pts = [0, w, smax]
                return mp.quad(lambda s: 2 / mp.sqrt((u2 - s * s - u1) * (u3 - u2 + s * s)), pts)

            phi = to_turn(u0) + to_turn(mp.mpf(0)) if inward else to_turn(mp.mpf(0)) - to_turn(u0)
            return float(phi)
        if inward:
            return None
        return float(free(mp.mpf(0), u0))


# ---------------------------------------------------------------------------
# Errors


def error_stats(phi, status, ref_phi, ref_status, delta=None, kappa_max=1e5) -> dict:
    """Error of a method against the reference, over rays that escape in both.

    **Returns:** `median`, `max` |phi - phi_ref| (radians) over escaping rays;
    `max_wc`, the max over well-conditioned rays only ($1/|\\delta| \\le$ `kappa_max`:
    $\\Phi$ changes by about $\\epsilon/|\\delta|$ when the ray angle is rounded, so no
    method can do better there); `max_far`, the max over rays with $|\\delta| \\ge 10^{-2}$,
    away from the shadow edge; `agree`, the fraction of rays whose status
    (escaped / captured / unresolved) matches; `n_esc`, the number compared.
    """
    phi = np.asarray(phi, np.float64)
    status, ref_status = np.asarray(status), np.asarray(ref_status)
    both = (status == ESCAPED) & (ref_status == ESCAPED)
    err = np.abs(phi - ref_phi)[both]
    out = {
        "median": float(np.median(err)) if err.size else float("nan"),
        "max": float(np.max(err)) if err.size else float("nan"),
        "agree": float(np.mean(status == ref_status)),
        "n_esc": int(both.sum()),
    }
    for key, kmax in (("max_wc", kappa_max), ("max_far", 1e2)):
        if delta is None:
            out[key] = out["max"]
            continue
        sel = both & (np.abs(delta) >= 1.0 / kmax)
        e = np.abs(phi - ref_phi)[sel]
        out[key] = float(np.max(e)) if e.size else float("nan")
    return out


# ---------------------------------------------------------------------------
# Timing


def _block(x):
    return jax.tree.map(
        lambda y: y.block_until_ready() if hasattr(y, "block_until_ready") else y, x
    )


def time_jitted(fn, *args, target_s: float = 1.5, min_repeats: int = 3, max_repeats: int = 15):
    """Compile time and median run time of a `jax.jit`-wrapped `fn` on `args`.

    Compilation is `fn.lower(*args).compile()` (tracing included), timed apart; then
    one warm-up call, then repeats until `target_s` seconds or `max_repeats`.

    **Returns:** `(compile_s, median_s, outputs)`.
    """
    t = time.perf_counter()
    compiled = fn.lower(*args).compile()
    compile_s = time.perf_counter() - t
    out = _block(compiled(*args))
    return (
        compile_s,
        *_repeat(lambda: _block(compiled(*args)), target_s, min_repeats, max_repeats, out),
    )


def time_call(fn, *args, target_s: float = 1.5, min_repeats: int = 3, max_repeats: int = 15):
    """Median run time of a plain Python function (one warm-up call first).

    **Returns:** `(first_s, median_s, outputs)`; `first_s` is the warm-up call.
    """
    t = time.perf_counter()
    out = _block(fn(*args))
    first = time.perf_counter() - t
    return (first, *_repeat(lambda: _block(fn(*args)), target_s, min_repeats, max_repeats, out))


def _repeat(call, target_s, min_repeats, max_repeats, out):
    times = []
    start = time.perf_counter()
    while len(times) < min_repeats or (
        len(times) < max_repeats and time.perf_counter() - start < target_s
    ):
        t = time.perf_counter()
        out = call()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def fmt(x, digits: int = 2) -> str:
    """A number for a table: scientific, or '-' for NaN/None."""
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    if isinstance(x, int | np.integer):
        return str(x)
    return f"{x:.{digits}e}"


def markdown_table(header, rows) -> str:
    """A GitHub markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"
