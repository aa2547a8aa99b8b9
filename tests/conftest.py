"""Test configuration: float64 everywhere except where a test module opts out.

The float32 path is checked in tests/test_float32.py with float32 inputs, which keep
every computation in float32 with x64 enabled, so both precisions are exercised in one
session.

Under `pytest -n 2 --dist loadfile` (make test) the files are queued longest first,
by their wall time in the last suite profile (`benchmarks/results/suite.json`, written
by `benchmarks/suite_profile.py`; files it does not list come first, by test count: a
file newer than the profile may be long, and one that ends the run on one worker leaves
the other idle, while a short one at the start costs nothing).
xdist's own order (most tests first) put the notebooks and the fit files (few tests,
the longest of the suite) last, and a worker with two or fewer pending tests takes the
next file: one worker then ran them at the end while the other sat idle (2 minutes of
imbalance measured). Longest first, the run ends on short files. Only the order
changes; every test runs as before.
"""

import math
import os

import jax
import pytest

jax.config.update("jax_enable_x64", True)
# No jaxlens cache: a test that runs the CLI in-process would otherwise point its
# worker's JAX at ~/.cache/jaxlens/xla, and every later compile in that worker would be
# written there (and the suite would depend on the cache's state).
os.environ["JAXLENS_CACHE_DIR"] = ""

# One XLA compilation cache for the run, made empty at its start and removed at its end:
# what one process compiled (a worker, a notebook's kernel, a CLI run in a subprocess)
# the others load instead of compiling it again. The suite still compiles every program
# once, and does not depend on any earlier run.
_SUITE_CACHE = "JAXLENS_SUITE_XLA_CACHE"


def _use_suite_cache(folder):
    os.environ["JAX_COMPILATION_CACHE_DIR"] = folder  # processes started from here
    jax.config.update("jax_compilation_cache_dir", folder)
    # Programs of a tenth of a second or more (the many single operations run eagerly
    # compile in milliseconds, less than the cache's own work).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.1)


def pytest_configure(config):
    if not hasattr(config, "workerinput") and _SUITE_CACHE not in os.environ:
        import tempfile

        # The controller (or a run without xdist): the workers inherit the variable.
        os.environ[_SUITE_CACHE] = config._jaxlens_suite_cache = tempfile.mkdtemp(
            prefix="jaxlens-suite-xla-"
        )
    if os.environ.get(_SUITE_CACHE):
        _use_suite_cache(os.environ[_SUITE_CACHE])
    # The controller schedules: keep the order of the workers' collection (below).
    if getattr(config.option, "dist", "no") == "loadfile" and hasattr(
        config.option, "loadscopereorder"
    ):
        config.option.loadscopereorder = False


def pytest_unconfigure(config):
    folder = getattr(config, "_jaxlens_suite_cache", None)
    if folder:
        import shutil

        shutil.rmtree(folder, ignore_errors=True)


def _recorded_walls(root):
    """Per-file wall seconds of the last suite profile (empty when it is missing)."""
    import json
    import pathlib

    try:
        data = json.loads(pathlib.Path(root, "benchmarks", "results", "suite.json").read_text())
        return {name: float(row.get("wall", 0.0)) for name, row in data["files"].items()}
    except (OSError, ValueError, KeyError, AttributeError):
        return {}


def pytest_collection_modifyitems(config, items):
    if not hasattr(config, "workerinput"):  # not an xdist worker: collection order
        return
    files = {}
    for item in items:
        files.setdefault(item.nodeid.split("::")[0], []).append(item)
    walls = _recorded_walls(config.rootpath)
    # Longest first; stable, so every worker collects the same order and a file's
    # tests keep theirs.
    order = sorted(files.items(), key=lambda kv: (-walls.get(kv[0], math.inf), -len(kv[1])))
    items[:] = [item for _, group in order for item in group]


@pytest.fixture
def free_port() -> int:
    """A TCP port on localhost that nothing listens on (for servers a test starts)."""
    from jaxlens._multi import free_port

    return free_port()


@pytest.fixture
def jax_events():
    """`with jax_events(event) as names:` the programs (`fun_name`) for which JAX
    reported `event` (e.g. "/jax/core/compile/backend_compile_duration") in the block."""
    import contextlib

    import jax.monitoring

    @contextlib.contextmanager
    def record(event_name):
        names, active = [], [True]

        def listen(event, duration, **kwargs):
            if active[0] and event == event_name:
                names.append(kwargs.get("fun_name"))

        jax.monitoring.register_event_duration_secs_listener(listen)
        try:
            yield names
        finally:
            active[0] = False  # older jax versions cannot unregister: the listener goes quiet
            unregister = getattr(jax.monitoring, "unregister_event_duration_listener", None)
            if unregister is not None:
                unregister(listen)

    return record


@pytest.fixture(scope="session")
def wheel_site(tmp_path_factory):
    """`(wheel, site)`: the wheel built from the repository (`pip wheel --no-deps`), and a
    folder it is installed into (`pip install --no-deps --target`; its console scripts
    in `site/bin`). Built once a session: tests/test_wheel.py and tests/test_readme.py
    use it."""
    import pathlib
    import subprocess
    import sys

    root = pathlib.Path(__file__).resolve().parents[1]
    folder = tmp_path_factory.mktemp("wheel")
    wheels, site = folder / "wheels", folder / "site"
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(root)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert build.returncode == 0, build.stderr[-3000:]
    (wheel,) = wheels.glob("jaxlens_bh-*.whl")
    install = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site),
         str(wheel)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert install.returncode == 0, install.stderr[-3000:]
    return wheel, site
