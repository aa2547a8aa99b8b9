"""Test configuration: float64 everywhere except where a test module opts out.

The float32 path is checked in tests/test_float32.py with float32 inputs, which keep
every computation in float32 with x64 enabled, so both precisions are exercised in one
session.

Under `pytest -n 2 --dist loadfile` (make test) the notebooks are queued first. xdist
queues files by descending test count, which puts the notebooks (one item each, the
longest items of the suite) last, and a worker with two or fewer pending tests takes
the next file: one worker then ran all three notebooks at the end while the other sat
idle (2 minutes of imbalance measured). Queued first, they run while the other worker
works through the test files, and the run ends on files of a few short tests. Only the
order changes; every test runs as before.
"""

import os

import jax

jax.config.update("jax_enable_x64", True)
# No persistent compilation cache: a test that runs the CLI in-process would otherwise
# point its worker's JAX at ~/.cache/jaxlens/xla, and every later compile in that
# worker would be written there (and the suite would depend on the cache's state).
os.environ["JAXLENS_CACHE_DIR"] = ""


def pytest_configure(config):
    # The controller schedules: keep the order of the workers' collection (below).
    if getattr(config.option, "dist", "no") == "loadfile" and hasattr(
        config.option, "loadscopereorder"
    ):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items):
    if not hasattr(config, "workerinput"):  # not an xdist worker: collection order
        return
    files = {}
    for item in items:
        files.setdefault(item.nodeid.split("::")[0], []).append(item)
    # Notebooks first, then xdist's own order (most tests first); stable, so every
    # worker collects the same order and a file's tests keep theirs.
    order = sorted(
        files.values(), key=lambda group: (not group[0].nodeid.endswith(".ipynb"), -len(group))
    )
    items[:] = [item for group in order for item in group]
