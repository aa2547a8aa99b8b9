"""Run every benchmark, each in its own process; `make bench` calls this.

    python benchmarks/run_all.py [--quick]

`--quick` (about 8 minutes on 2 cores) uses fewer rays, settings, repeats and fit
cases, and a 512 x 512 bench_memory whose report is not kept; the full run (about 25
minutes, plus bench_memory's 4096 x 4096 renders) writes the tables the README shows.
Results go to `benchmarks/results/` (or `$JAXLENS_BENCH_RESULTS`).
"""

import argparse
import pathlib
import subprocess
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="fewer rays and settings")
    p.add_argument(
        "--only",
        nargs="*",
        choices=(
            "accuracy_ladder",
            "scaling",
            "scaling_processes",
            "speedup",
            "floor",
            "source_distance",
            "bench_render",
            "bench_effects",
            "bench_fit",
            "bench_memory",
            "latency",
        ),
        help="run only these benchmarks",
    )
    args = p.parse_args(argv)
    plan = {
        "speedup": ["--rays", "200000"] if args.quick else [],
        "floor": ["--rays", "200000", "--repeats", "5"] if args.quick else [],
        "source_distance": ["--rays", "200000"] if args.quick else [],
        "accuracy_ladder": ["--quick"] if args.quick else [],
        "scaling": ["--quick"] if args.quick else [],
        "scaling_processes": ["--rays", "1e6"] if args.quick else [],
        "bench_render": ["--repeats", "5", "--skip-check"] if args.quick else [],
        "bench_effects": ["--quick"] if args.quick else [],
        "bench_fit": ["--cases", "3"] if args.quick else [],
        # a fresh process per case; --quick: 512 x 512, report to a temporary folder
        "bench_memory": ["--quick"] if args.quick else [],
        "latency": ["--quick"] if args.quick else [],
    }
    failed = []
    for name, extra in plan.items():
        if args.only and name not in args.only:
            continue
        print(f"=== {name} {' '.join(extra)}", flush=True)
        t = time.perf_counter()
        rc = subprocess.call([sys.executable, str(HERE / f"{name}.py"), *extra])
        print(f"=== {name}: exit {rc} after {time.perf_counter() - t:.0f} s", flush=True)
        if rc != 0:
            failed.append(name)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    print(f"results in {HERE / 'results'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
