"""How cost grows with the batch: time and peak memory vs number of rays, 1e3 ... 1e7.

`trace(..., accuracy=1e-9)` and RK4 (`RK4(dphi=0.01)`, the integrator's default step)
on the moderate rays (D = 20, alpha uniform in [0.001, 0.5] rad), float64, through
`jaxlens.trace_sharded`: one batch (`chunk=None`), or chunks of a fixed size
that compile once, so a batch larger than memory streams through. Each point runs in
a fresh process, so its peak resident memory (`ru_maxrss`) is its own; the table
gives the peak above the process's footprint after importing JAX and building the
rays, next to the 25 bytes per ray that the inputs and outputs themselves need.

Writes `results/scaling.md` and `results/scaling.png`.

    python benchmarks/scaling.py [--quick] [--rk4-max N] [--max-rays N]
"""

import argparse
import json
import os
import subprocess
import sys

from _common import RESULTS, ROOT, machine, machine_markdown, markdown_table, np

CHUNK = 2**20

_CHILD = r"""
import json, resource, sys, time
sys.path.insert(0, sys.argv[1] + "/benchmarks")
from _common import jax, jaxlens, np
trace_sharded = jaxlens.trace_sharded

n, method, chunk = int(sys.argv[2]), sys.argv[3], sys.argv[4]
chunk = None if chunk == "none" else int(chunk)
kw = {"accuracy": 1e-9} if method == "auto" else {"method": jaxlens.RK4(dphi=0.01)}
rng = np.random.default_rng(0)
alpha = rng.uniform(0.001, 0.5, n)
small = rng.uniform(0.001, 0.5, 8)
trace_sharded(small, 20.0, **kw)  # imports, tracing machinery; not the batch's compile
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
r = trace_sharded(alpha, 20.0, chunk=chunk, progress=False, **kw)
first = time.perf_counter() - t
reps = 3 if first < 5.0 else 1
times = []
for _ in range(reps):
    t = time.perf_counter()
    r = trace_sharded(alpha, 20.0, chunk=chunk, progress=False, **kw)
    times.append(time.perf_counter() - t)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
med = float(np.median(times))
print(json.dumps({"n": n, "method": method, "chunk": chunk, "first_s": first, "run_s": med,
                  "compile_s": max(first - med, 0.0), "base_mib": base / 1024,
                  "peak_mib": peak / 1024, "escaped": int(np.sum(r.status == 0))}))
"""


def run_point(n, method, chunk):
    """One measurement in a fresh process; returns its JSON record."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, str(ROOT), str(n), method, str(chunk or "none")],
        capture_output=True,
        text=True,
        env=env,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"scaling point {n} {method} {chunk} failed:\n{proc.stderr[-3000:]}")
    rec = json.loads(proc.stdout.strip().splitlines()[-1])
    print(
        f"{method:5s} n={n:>9d} chunk={chunk!s:>8s}  run {rec['run_s']:.3f}s "
        f"({n / rec['run_s']:.3g} rays/s)  compile~{rec['compile_s']:.2f}s  "
        f"peak +{rec['peak_mib'] - rec['base_mib']:.0f} MiB",
        flush=True,
    )
    return rec


def plan(quick: bool, rk4_max: int, max_rays: int | None = None):
    """(n, method, chunk) points to measure."""
    top = 10**6 if quick else 10**7
    top = top if max_rays is None else min(top, max_rays)
    ns = [10**k for k in range(3, 8) if 10**k <= top]
    pts = [(n, "auto", None) for n in ns]
    pts += [(n, "auto", CHUNK) for n in ns if n > CHUNK]
    rk4_top = min(rk4_max, 10**5 if quick else rk4_max)
    pts += [(n, "rk4", None) for n in ns if n <= rk4_top]
    return pts


def plot(records, path):
    """Log-log time and added peak memory vs rays."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 5))
    groups = {}
    for r in records:
        label = ("trace(accuracy=1e-9)" if r["method"] == "auto" else "RK4(dphi=0.01)") + (
            f", chunk={r['chunk']}" if r["chunk"] else ", one batch"
        )
        groups.setdefault(label, []).append(r)
    for label, rs in groups.items():
        rs = sorted(rs, key=lambda r: r["n"])
        n = np.array([r["n"] for r in rs])
        ax1.plot(n, [r["run_s"] for r in rs], "o-", label=label)
        ax2.plot(n, [max(r["peak_mib"] - r["base_mib"], 0.1) for r in rs], "o-", label=label)
    n = np.logspace(3, 7, 5)
    ax2.plot(n, 25 * n / 2**20, "k:", label="inputs + outputs (25 B/ray)")
    ax1.set_ylabel("run time, s (compiled, warm)")
    ax2.set_ylabel("peak resident memory above baseline, MiB")
    for ax in (ax1, ax2):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("rays")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("jaxlens scaling (D = 20, float64, this machine)")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="up to 1e6 rays (RK4: 1e5)")
    p.add_argument(
        "--rk4-max", type=float, default=1e6, help="largest RK4 batch (default 1e6; 1e7 ~ 5 min)"
    )
    p.add_argument("--max-rays", type=float, default=None, help="largest batch (a smoke test: 1e4)")
    args = p.parse_args(argv)
    max_rays = None if args.max_rays is None else int(args.max_rays)
    RESULTS.mkdir(parents=True, exist_ok=True)
    info = machine()
    print(machine_markdown(info), flush=True)
    records = [run_point(n, m, c) for n, m, c in plan(args.quick, int(args.rk4_max), max_rays)]
    rows = [
        [
            "trace(accuracy=1e-9)" if r["method"] == "auto" else "RK4(dphi=0.01)",
            r["n"],
            r["chunk"] or "one batch",
            f"{r['run_s']:.4f}",
            f"{r['n'] / r['run_s']:.3g}",
            f"{r['compile_s']:.2f}",
            f"{r['peak_mib'] - r['base_mib']:.0f}",
            f"{25 * r['n'] / 2**20:.1f}",
        ]
        for r in records
    ]
    text = (
        "# Scaling: time and memory vs number of rays\n\n"
        + machine_markdown(info)
        + "- Rays: D = 20, alpha uniform in [0.001, 0.5] rad, float64, through "
        "`trace_sharded` (one device here). Each point in a fresh process; run time is "
        "the median of warm calls (3, or 1 when a call takes over 5 s); `compile` is "
        "first call minus warm call. Memory: peak RSS above the footprint after "
        "importing JAX and making the rays. Command: `python benchmarks/scaling.py"
        f"{' --quick' if args.quick else ''}`.\n\n"
        + markdown_table(
            [
                "method",
                "rays",
                "chunk",
                "run s",
                "rays/s",
                "compile s",
                "peak MiB",
                "in+out MiB",
            ],
            rows,
        )
        + "\n![scaling](scaling.png)\n\nOver several processes (`jax.distributed`), a row "
        "per process count (1, 2, 4) for a 1e8-ray batch and a 48-frame animation: "
        "[`processes.md`](processes.md), from `benchmarks/scaling_processes.py`.\n"
    )
    (RESULTS / "scaling.md").write_text(text)
    (RESULTS / "scaling.json").write_text(json.dumps(records, indent=1))
    plot(records, RESULTS / "scaling.png")
    print(f"wrote {RESULTS / 'scaling.md'}")
    return records


if __name__ == "__main__":
    main()
