"""Every snippet of the README and of the docs pages (docs/*.md) runs where a user runs
it: in an empty folder, with the package installed from its wheel, and in the page's
order. A page's Python blocks run in one interpreter (one namespace, as in one session),
its `pycon` blocks as doctests (their printed output compared) in the same namespace,
and its bash blocks with bash, between them, in the same folder: `jaxlens ...` is the
wheel's console script. No file is made beforehand: a snippet's inputs are made by the
lines the page shows before it.

The interpreter is a subprocess whose `PYTHONPATH` puts the wheel's folder first (the
dependencies come from this environment) and whose `PATH` has the wheel's `bin` first;
it checks that `jaxlens` is the wheel's. It keeps compiled programs in a folder the
pages share (`jl.keep_programs`, and `JAXLENS_CACHE_DIR` for the commands), as a user's
later runs do.

Not run: the set-up itself (`SET_UP`: `pip install ...`, `make ...`: it installs what is
tested, or runs this suite), and the lines in `SKIPPED`, each with its reason.

The README's results are checked further: its files and nothing else, the image of the
camera's size, its fit within 1 % of the rendered distance and field of view or flagged,
by `fit_ring` and by `jaxlens fit --json`.
"""

import json
import math
import os
import re
import resource
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = ["README.md"] + sorted(f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md"))
RUN = ("python", "pycon", "bash")

# The set-up itself: installs the package tested here, or runs this suite.
SET_UP = re.compile(r"\s*(pip install|make)\s")

# Other lines not run here: (page, the line's start): why.
SKIPPED = {
    ("docs/scale-out.md", "srun "): "Slurm's launcher: there is no cluster here",
    ("docs/scale-out.md", "jaxlens render -o big.exr --size 16384x16384"): (
        "268 million pixels: gigabytes of output and CPU-minutes, the scale the line is "
        "about; the other `--processes` lines of the page run"
    ),
}


def _blocks(page: str) -> list[tuple[str, str, int]]:
    """(language, code, line number) of each fenced block of a Markdown page."""
    text = (ROOT / page).read_text()
    return [
        (m.group(1), m.group(2), text.count("\n", 0, m.start()) + 1)
        for m in re.finditer(r"^```(\w*)\n(.*?)^```", text, flags=re.M | re.S)
    ]


def _runnable(page: str, code: str) -> tuple[str, list[str]]:
    """A bash block without the lines not run here, and those lines."""
    kept, left_out, skipping = [], [], False
    for line in code.splitlines():
        if not skipping and (
            SET_UP.match(line) or any(line.startswith(s) for p, s in SKIPPED if p == page)
        ):
            skipping = True
        (left_out if skipping else kept).append(line)
        skipping = skipping and line.endswith("\\")  # a continued line goes with it
    return "\n".join(kept) + "\n", left_out


# Runs a page's blocks in order: argv = blocks.json, results.json, checks.py (code run in
# the page's namespace at the end, filling `results`).
DRIVER = textwrap.dedent(
    """
    import doctest, json, os, subprocess, sys, time
    from pathlib import Path

    import jaxlens

    site = Path(os.environ["JAXLENS_TEST_SITE"]).resolve()
    assert Path(jaxlens.__file__).resolve().is_relative_to(site), jaxlens.__file__
    jaxlens.keep_programs(os.environ["JAXLENS_CACHE_DIR"])

    blocks = json.loads(Path(sys.argv[1]).read_text())
    namespace = {"__name__": "__main__"}
    results = {"bash": [], "seconds": []}
    for lang, code, where in blocks:
        t = time.perf_counter()
        if lang == "python":
            exec(compile(code, where, "exec"), namespace)
        elif lang == "pycon":
            test = doctest.DocTestParser().get_doctest(code, namespace, where, where, 0)
            runner = doctest.DocTestRunner(optionflags=doctest.NORMALIZE_WHITESPACE)
            runner.run(test, clear_globs=False)
            assert not runner.failures, f"{where}: the output differs (above)"
        else:
            run = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", code],
                                 stdout=subprocess.PIPE, text=True)
            print(run.stdout, end="")
            assert run.returncode == 0, f"{where}: exit status {run.returncode}"
            results["bash"].append(run.stdout)
        results["seconds"].append([where, time.perf_counter() - t])
        print(f"{where}: {time.perf_counter() - t:.1f} s", file=sys.stderr, flush=True)
    namespace["results"] = results
    exec(Path(sys.argv[3]).read_text(), namespace)
    Path(sys.argv[2]).write_text(json.dumps(results))
    """
)

# What the test reads back from a page's namespace (run after its blocks).
CHECKS = {
    "README.md": """
results["image_shape"] = list(image.shape)
results["fit"] = [float(fit.distance), float(fit.fov_deg), bool(fit.valid), fit.message]
results["distance_m"] = float(fit.distance_m(4.3e6)[0])
""",
}


@pytest.fixture(scope="module")
def programs(tmp_path_factory):
    """A folder of compiled programs the pages' processes share: the suite's compilation
    cache (tests/conftest.py), where the suite has one, else a new folder."""
    return os.environ.get("JAXLENS_SUITE_XLA_CACHE") or tmp_path_factory.mktemp("programs")


def _run_page(page, folder, wheel_site, programs):
    """Run `page`'s snippets in the empty `folder`; the results of the checks."""
    _, site = wheel_site
    blocks, left_out = [], []
    for lang, code, line in _blocks(page):
        if lang not in RUN:
            continue
        if lang == "bash":
            code, skipped = _runnable(page, code)
            left_out += skipped
            if not code.strip():
                continue
        blocks.append((lang, code, f"{page}:{line}"))
    work = folder / "work"
    work.mkdir()
    (folder / "blocks.json").write_text(json.dumps(blocks))
    (folder / "checks.py").write_text(CHECKS.get(page, ""))
    (folder / "driver.py").write_text(DRIVER)
    path = os.pathsep.join([str(site / "bin"), str(Path(sys.executable).parent),
                            os.environ.get("PATH", "")])  # fmt: skip
    env = dict(os.environ, PYTHONPATH=str(site), PATH=path, JAXLENS_TEST_SITE=str(site),
               JAXLENS_CACHE_DIR=str(programs))  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    run = subprocess.run(
        [sys.executable, str(folder / "driver.py"), str(folder / "blocks.json"),
         str(folder / "results.json"), str(folder / "checks.py")],
        cwd=work, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert run.returncode == 0, f"{page}\n{run.stdout[-3000:]}\n{run.stderr[-6000:]}"
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = sum(getattr(after, f) - getattr(before, f) for f in ("ru_utime", "ru_stime"))
    print(f"{run.stderr}{page}: {cpu:.1f} CPU seconds")  # and each block's (pytest -s)
    results = json.loads((folder / "results.json").read_text())
    results["left_out"] = left_out
    return work, results


def _within_1_percent_or_flagged(distance, fov_deg, valid, message):
    close = abs(distance / 20.0 - 1) < 0.01 and abs(fov_deg / 60.0 - 1) < 0.01
    assert close or (not valid and message), (distance, fov_deg, valid, message)
    return close


def test_readme_snippets(tmp_path, wheel_site, programs):
    work, results = _run_page("README.md", tmp_path, wheel_site, programs)
    left_out = results["left_out"]
    assert left_out and all(SET_UP.match(line) for line in left_out), left_out  # the set-up
    assert len(results["seconds"]) >= 3  # render, fit, the command lines

    # The files the README makes, and nothing else (no temporaries, no frame folder).
    made = sorted(str(p.relative_to(work)) for p in work.rglob("*"))
    assert made == ["out", "out/approach.gif", "out/ring.png", "ring.png"], made
    # The Python render: the image it wrote, of the camera's size.
    assert results["image_shape"] == [360, 480, 3]
    # The fit of the README's own render: 1 % or flagged, in Python and on the CLI.
    distance, fov_deg, valid, message = results["fit"]
    _within_1_percent_or_flagged(distance, fov_deg, valid, message)
    assert results["distance_m"] == pytest.approx(distance * 4.3e6 * 2953.25, rel=1e-6)
    out = json.loads(results["bash"][-1].strip().splitlines()[-1])
    _within_1_percent_or_flagged(out["distance"], out["fov_deg"], out["valid"], out["message"])
    assert out["distance"] == pytest.approx(distance, rel=1e-6)
    assert out["distance_m"] == pytest.approx(out["distance"] * 4.3e6 * 2953.25, rel=1e-6)
    assert math.isfinite(out["distance_err"]) and out["transfer"] == "srgb"


DOCS = [p for p in PAGES[1:] if any(lang in RUN for lang, _, _ in _blocks(p))]


@pytest.mark.parametrize("page", DOCS)
def test_docs_snippets(tmp_path, wheel_site, programs, page):
    _, results = _run_page(page, tmp_path, wheel_site, programs)  # every block ran
    # Each line of `SKIPPED` is on its page and was left out (a stale entry is removed).
    listed = [s for p, s in SKIPPED if p == page]
    assert all(any(line.startswith(s) for line in results["left_out"]) for s in listed)


def test_every_block_is_run_or_marked_as_text():
    """A block a reader might take for a command (no language, or a shell's) is fenced
    as what it is: python, pycon or bash is run; text, toml or console is not."""
    shown = (*RUN, "text", "toml", "console")
    unmarked = [f"{page}:{line} ({lang or 'no language'})" for page in PAGES
                for lang, _, line in _blocks(page) if lang not in shown]  # fmt: skip
    assert not unmarked, unmarked
