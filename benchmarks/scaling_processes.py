"""Scaling over processes: one ray batch traced, and one animation rendered, by 1, 2
and 4 local processes joined by `jax.distributed` (the code path of a cluster), each
with one CPU device.

Every process calls `trace_sharded` on the same rays (D = 20, alpha uniform in
[0.001, 0.5] rad, float64, `accuracy=1e-9`, chunks of 2^21 rays over all devices); each
computes its devices' shards and the results are gathered on every process. The
program is compiled on one chunk first; the time is the batch after it, on process 0.
The animation is `jaxlens animate --frames 48 --processes N` (the default approach,
480 x 270, 2 x 2 samples a pixel), timed as the whole command: cold (no persistent
compilation cache) and with the cache a previous run of the same command filled.
Writes `results/processes.md` (and `.json`).

    python benchmarks/scaling_processes.py                       # 1e8 rays, 48 frames
    python benchmarks/scaling_processes.py --rays 1e6 --frames 6  # a smoke run
"""

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import textwrap
import time

from _common import RESULTS, machine, machine_markdown, markdown_table

CHUNK = 1 << 21

WORKER = textwrap.dedent(
    """
    import json, sys, time
    import numpy as np
    import jax

    pid, nproc, port, n, chunk, out = sys.argv[1:7]
    pid, nproc, n, chunk = int(pid), int(nproc), int(float(n)), int(chunk)
    jax.config.update("jax_enable_x64", True)
    if nproc > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(f"127.0.0.1:{port}", num_processes=nproc, process_id=pid,
                                   initialization_timeout=300)
    import jaxlens as jl

    alpha = np.linspace(0.001, 0.5, n)
    t = time.perf_counter()
    jl.trace_sharded(alpha[:chunk], 20.0, chunk=chunk, accuracy=1e-9, progress=False)
    first = time.perf_counter() - t
    t = time.perf_counter()
    r = jl.trace_sharded(alpha, 20.0, chunk=chunk, accuracy=1e-9, progress=False)
    run = time.perf_counter() - t
    if pid == 0:
        json.dump({"processes": nproc, "devices": jax.device_count(), "rays": n,
                   "first_s": first, "run_s": run,
                   "captured": int(np.sum(r.status == jl.CAPTURED))}, open(out, "w"))
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(nproc: int, rays: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out, port = os.path.join(tmp, "r.json"), str(_free_port())
        env = dict(os.environ, JAXLENS_CACHE_DIR="")
        env.pop("XLA_FLAGS", None)  # one CPU device a process
        chunk = min(CHUNK, rays)
        procs = [
            subprocess.Popen([sys.executable, "-c", WORKER, str(i), str(nproc), port, str(rays),
                              str(chunk), out], env=env)
            for i in range(nproc)
        ]  # fmt: skip
        codes = [p.wait() for p in procs]
        if any(codes):
            raise SystemExit(f"{nproc} processes: exit codes {codes}")
        with open(out) as f:
            return json.load(f)


def animate(nproc: int, frames: int, cache: str) -> float:
    """Wall seconds of `jaxlens animate --frames FRAMES` as `nproc` processes."""
    with tempfile.TemporaryDirectory() as tmp:
        argv = [sys.executable, "-m", "jaxlens", "animate", "-o", os.path.join(tmp, "a.gif"),
                "--frames", str(frames)]  # fmt: skip
        if nproc > 1:
            argv += ["--processes", str(nproc)]
        env = dict(os.environ, JAXLENS_CACHE_DIR=cache)
        env.pop("XLA_FLAGS", None)
        t = time.perf_counter()
        done = subprocess.run(argv, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t
        if done.returncode:
            raise SystemExit(f"{nproc} processes: {done.stderr[-2000:]}")
        return wall


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rays", type=float, default=1e8, help="rays in the batch (default 1e8)")
    p.add_argument("--frames", type=int, default=48, help="frames of the animation (default 48)")
    p.add_argument("--processes", type=int, nargs="+", default=[1, 2, 4])
    args = p.parse_args(argv)
    RESULTS.mkdir(parents=True, exist_ok=True)
    info = machine()
    load = os.getloadavg()
    print(machine_markdown(info), flush=True)
    records = []
    for n in args.processes:
        r = run(n, int(args.rays))
        print(r, flush=True)
        records.append(r)
    movies = []
    for n in args.processes:
        with tempfile.TemporaryDirectory() as cache:
            cold = animate(n, args.frames, "")
            animate(n, args.frames, cache)  # fills the cache
            warm = animate(n, args.frames, cache)
        movies.append({"processes": n, "frames": args.frames, "cold_s": cold, "warm_s": warm})
        print(movies[-1], flush=True)
    base = records[0]["run_s"] * records[0]["processes"]
    rows = [
        [r["processes"], r["devices"], f"{r['rays']:.3g}", f"{r['run_s']:.2f}",
         f"{r['rays'] / r['run_s']:.3g}", f"{base / r['run_s']:.2f}",
         f"{base / r['run_s'] / r['processes']:.2f}", f"{r['first_s']:.2f}"]
        for r in records
    ]  # fmt: skip
    text = (
        "# Scaling over processes: a ray batch and an animation, 1 to 4 local processes\n\n"
        + machine_markdown(info)
        + f"- Load average (1 min) before the run: {load[0]:.2f}\n"
        "- Rays: D = 20, alpha uniform in [0.001, 0.5] rad, float64, `trace_sharded(..., "
        f"accuracy=1e-9, chunk={CHUNK})` on every process, joined by "
        "`jax.distributed` on localhost (gloo collectives), one CPU device a process; "
        "results gathered on every process. `first s`: the first call, on one chunk "
        "(compiling); `run s`: the whole batch after it, on process 0. Speed-up: "
        "one process's time over this one's; efficiency: speed-up / processes. "
        f"Command: `python benchmarks/scaling_processes.py --rays {args.rays:g}`.\n\n"
        + markdown_table(
            [
                "processes",
                "devices",
                "rays",
                "run s",
                "rays/s",
                "speed-up",
                "efficiency",
                "first s",
            ],
            rows,
        )  # fmt: skip
        + "\nOn this 2-core machine one process already uses both cores (XLA's CPU "
        "backend runs a device's work on a thread pool), so more processes share the "
        "same two cores: the speed-up measures the overhead of splitting and gathering, "
        "not a gain. On a machine (or cluster) with a core set or a GPU per process, each "
        "process adds its own compute: the rays are independent, and what is "
        "communicated is only the results, gathered chunk by chunk.\n"
    )
    one = movies[0]
    text += (
        f"\n## An animation of {args.frames} frames\n\n"
        f"`jaxlens animate -o a.gif --frames {args.frames} --processes N` (the default "
        "approach, 480 x 270, 2 x 2 samples a pixel; one process: no `--processes`), the "
        "whole command's wall time: start-up, compiling (every process compiles its own "
        "programs; with the cache filled by a previous run they are loaded), rendering "
        "(each process every N-th group of frames, saved beside the output), and process "
        "0 writing the GIF. Speed-up and efficiency as above, from the warm times.\n\n"
        + markdown_table(
            ["processes", "frames", "cold s", "warm cache s", "speed-up", "efficiency"],
            [
                [
                    m["processes"],
                    m["frames"],
                    f"{m['cold_s']:.2f}",
                    f"{m['warm_s']:.2f}",
                    f"{one['warm_s'] / m['warm_s']:.2f}",
                    f"{one['warm_s'] / m['warm_s'] / m['processes']:.2f}",
                ]
                for m in movies
            ],
        )  # fmt: skip
        + "\nThe same two cores again: each extra process adds its own start-up (loading "
        "JAX, tracing, compiling or loading the programs) and takes cores from the "
        "others' rendering. With a core set or a GPU a process, the frames' rendering "
        "divides among them and the start-up is paid once a process, in parallel.\n"
    )
    (RESULTS / "processes.md").write_text(text)
    (RESULTS / "processes.json").write_text(
        json.dumps({"rays": records, "animation": movies}, indent=1)
    )
    print(f"wrote {RESULTS / 'processes.md'}")


if __name__ == "__main__":
    main()
