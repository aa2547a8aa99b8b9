"""Where the test suite's time goes: wall, XLA compile, tracing and lowering per test file.

    .venv/bin/python benchmarks/suite_profile.py [pytest selection ...]

Runs `make test`'s command (`pytest -n 2 --dist loadfile --nbmake -m "not benchmark"
tests notebooks`, or the given selection with the same options) with this module as a
pytest plugin. Each worker records, per test, its wall time and JAX's own compile
events (`jax.monitoring`: tracing to a jaxpr, lowering to MLIR, XLA's compile, each
with the program's name), and the run writes `results/suite.md` and
`results/suite.json` (the figures per file, test and program): the run's wall time
and load average, a row per test file (tests, wall, compile, tracing, lowering, the
rest), the programs by total compile time, and the slowest tests. A notebook runs in
its own kernel process, so its row has its wall time
only. The suite's budget (the set-up contract) is 10 minutes on 2 idle cores.
"""

import collections
import json
import os
import pathlib
import shlex
import subprocess
import sys
import tempfile
import time

import pytest

_EVENTS = {
    "/jax/core/compile/backend_compile_duration": "compile",
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
}
_current = {"test": "(collection and imports)"}
_rows: list[tuple[str, str, str, float]] = []  # (test, kind, program, seconds)


def _listener(event, duration, **kwargs):
    kind = _EVENTS.get(event)
    if kind is not None:
        _rows.append((_current["test"], kind, kwargs.get("fun_name", "?"), float(duration)))


def pytest_configure(config):
    if os.environ.get("JAXLENS_SUITE_PROFILE"):
        import jax

        jax.monitoring.register_event_duration_secs_listener(_listener)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _current["test"] = item.nodeid
    start = time.perf_counter()
    yield
    _rows.append((item.nodeid, "wall", "", time.perf_counter() - start))


def pytest_sessionfinish(session):
    folder = os.environ.get("JAXLENS_SUITE_PROFILE")
    if folder:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        pathlib.Path(folder, f"{worker}.json").write_text(json.dumps(_rows))


def _summarise(rows):
    files = collections.defaultdict(collections.Counter)
    tests = collections.defaultdict(collections.Counter)
    programs = collections.defaultdict(list)
    for test, kind, program, seconds in rows:
        name = test.split("::")[0]
        files[name][kind] += seconds
        tests[test][kind] += seconds
        if kind == "wall":
            files[name]["tests"] += 1
        if kind == "compile":
            programs[program].append(seconds)
    return files, tests, programs


def _record(files, tests, programs, wall, load, rc):
    """The report's figures for `suite.json`: per file and per test the seconds of each
    kind, per program its compiles (count, total, largest)."""
    return {
        "wall_s": wall,
        "load": list(load),
        "exit": rc,
        "files": {k: dict(v) for k, v in files.items()},
        "tests": {k: dict(v) for k, v in tests.items()},
        "programs": {k: [len(v), sum(v), max(v)] for k, v in programs.items()},
    }


def _markdown(files, tests, programs, wall, load, rc, argv):
    from _common import machine_markdown

    small = {name: t for name, t in programs.items() if max(t) < 0.5}
    total = collections.Counter()
    for row in files.values():
        total.update(row)
    lines = [
        "# Test suite: where the time goes",
        "",
        machine_markdown().rstrip(),
        f"- Command: `pytest {shlex.join(argv)}` (exit status {rc})",
        f"- Wall time {wall / 60:.1f} min; 1-minute load average {load[0]:.2f} before, "
        f"{load[1]:.2f} after (the budget: 10 min on 2 idle cores)",
        "",
        f"Summed over the workers: {total['wall']:.0f} s in tests, of which XLA compile "
        f"{total['compile']:.0f} s, tracing {total['trace']:.0f} s, lowering "
        f"{total['lower']:.0f} s (notebooks: wall only, their kernels are other processes). "
        "The rest is the wall time less the three: running, and host work; it is negative "
        "where a compile happens while a function is traced (both count that time).",
        "",
        f"Programs whose every compile took under 0.5 s (mostly single operations run "
        f"eagerly, compiled once a shape and dtype): {len(small)} programs, "
        f"{sum(len(t) for t in small.values())} compiles, "
        f"{sum(sum(t) for t in small.values()):.0f} s.",
        "",
        "| file | tests | wall s | compile s | tracing s | lowering s | rest s |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, row in sorted(files.items(), key=lambda kv: -kv[1]["wall"]):
        rest = row["wall"] - row["compile"] - row["trace"] - row["lower"]
        lines.append(
            f"| {name} | {row['tests']:.0f} | {row['wall']:.1f} | {row['compile']:.1f} | "
            f"{row['trace']:.1f} | {row['lower']:.1f} | {rest:.1f} |"
        )
    lines += [
        "",
        "## Programs by total compile time",
        "",
        "| program | compiles | total s | largest s |",
        "| --- | ---: | ---: | ---: |",
    ]
    for name, times in sorted(programs.items(), key=lambda kv: -sum(kv[1]))[:25]:
        lines.append(f"| `{name}` | {len(times)} | {sum(times):.1f} | {max(times):.1f} |")
    lines += [
        "",
        "## Slowest tests",
        "",
        "| test | wall s | compile s |",
        "| --- | ---: | ---: |",
    ]
    for name, row in sorted(tests.items(), key=lambda kv: -kv[1]["wall"])[:30]:
        lines.append(f"| `{name}` | {row['wall']:.1f} | {row['compile']:.1f} |")
    return "\n".join(lines) + "\n"


def main(selection):
    from _common import RESULTS  # benchmarks/, the script's folder, is on sys.path

    root = pathlib.Path(__file__).resolve().parents[1]

    argv = ["-n", "2", "--dist", "loadfile", "--nbmake", "-m", "not benchmark", "-q"]
    argv += selection or ["tests", "notebooks"]
    with tempfile.TemporaryDirectory() as folder:
        env = dict(os.environ, JAXLENS_SUITE_PROFILE=folder)
        env["PYTHONPATH"] = os.pathsep.join(
            [str(root / "benchmarks"), env.get("PYTHONPATH", "")]
        ).rstrip(os.pathsep)
        load0 = os.getloadavg()[0]
        start = time.perf_counter()
        rc = subprocess.call(
            [sys.executable, "-m", "pytest", "-p", "suite_profile", *argv], cwd=root, env=env
        )
        wall = time.perf_counter() - start
        load1 = os.getloadavg()[0]
        rows = []
        for path in pathlib.Path(folder).glob("*.json"):
            rows += json.loads(path.read_text())
    files, tests, programs = _summarise(rows)
    text = _markdown(files, tests, programs, wall, (load0, load1), rc, argv)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "suite.md").write_text(text)
    (RESULTS / "suite.json").write_text(
        json.dumps(_record(files, tests, programs, wall, (load0, load1), rc))
    )
    print(text)
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
