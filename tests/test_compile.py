"""The executables the CLI keeps between processes (`jaxlens._compile.Stored`): what
goes into their key, and a kept program that calls JAX's LAPACK kernels loaded by a
fresh process (which has not set them up: calling it unprepared ends the process)."""

import os
import subprocess
import sys

import pytest

from jaxlens import _compile

# Keeps (first run) or loads (second run) a program with a QR decomposition in the
# folder given, and prints a value of its result and whether it was traced.
_CHILD = """
import sys

import pytest
import equinox as eqx, jax, jax.numpy as jnp, numpy as np
from jaxlens import _compile

traced = []

@eqx.filter_jit
def qr_sum(a):
    traced.append(1)
    return jnp.sum(jnp.abs(jnp.linalg.qr(a)[1]))

if "xla" in sys.argv:  # XLA's persistent cache in the same folder, as the CLI sets it
    jax.config.update("jax_compilation_cache_dir", sys.argv[1])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    # A program compiled before the kept one (the CLI compiles several): JAX decides
    # on its first compile whether the process uses the cache at all.
    jax.jit(lambda x: x + 1.0)(np.float32(1.0))
if "written" in sys.argv:  # written to XLA's cache too, as earlier versions did
    import contextlib

    _compile._not_written_to_xla_cache = contextlib.nullcontext
_compile.use_folder(sys.argv[1])
f = _compile.Stored(qr_sum, lambda *_: jax.tree.structure(0))
a = np.arange(16.0, dtype=np.float32).reshape(4, 4) ** 0.5
if "preload" in sys.argv:  # loaded on a thread before the call: the call finds it
    f.preload(a).join()
    assert all(e["compiled"] is not None for e in f._programs.values()), "not loaded"
if "last" in sys.argv:  # the call noted before, loaded before its arguments are known
    thread = f.preload_last("4 x 4")
    if thread is not None:
        thread.join()
    print(len(f._programs), end=" ")
    if "other" in sys.argv:  # a call of another kind: compiled, not waiting for it
        a = np.ones((3, 3), np.float32)
out = float(f(a))
f.note("4 x 4", a)
print(out, bool(traced))
"""


def _run(folder, *more):
    done = subprocess.run([sys.executable, "-c", _CHILD, str(folder), *more],
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    *loaded, value, traced = done.stdout.split()
    return (*map(int, loaded), float(value), traced == "True")


def test_a_kept_program_with_lapack_calls_runs_in_a_fresh_process(tmp_path):
    def run():
        return _run(tmp_path)

    first, traced_first = run()
    assert traced_first and len(list((tmp_path / "jaxlens-programs").glob("*.executable"))) == 1
    again, traced_again = run()
    assert not traced_again and again == first


def test_the_key_holds_xla_flags_and_jax_settings_from_the_environment(monkeypatch):
    def digest():
        _compile._code_digest.cache_clear()
        return _compile._code_digest()

    try:
        monkeypatch.delenv("XLA_FLAGS", raising=False)
        plain = digest()
        monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_fast_math=true")
        flags = digest()
        # The cache's own folder is not part of what decides a program.
        monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(monkeypatch))
        assert plain != flags == digest()
    finally:
        _compile._code_digest.cache_clear()


def test_the_key_holds_the_versions_of_the_traced_libraries(monkeypatch):
    # A new optimistix changes the fit's solver: its kept program must not be loaded.
    def digest():
        _compile._code_digest.cache_clear()
        return _compile._code_digest()

    try:
        installed = digest()
        real = _compile._version

        def older_optimistix(name):
            return "0.0.0" if name == "optimistix" else real(name)

        monkeypatch.setattr(_compile, "_version", older_optimistix)
        assert digest() != installed
    finally:
        _compile._code_digest.cache_clear()


def test_a_program_xla_cached_is_kept_whole(tmp_path):
    # Kept programs gone (a new jaxlens version: new keys, the same program): the
    # program compiled again is kept with its code. One that XLA's cache had served was
    # kept without it, and the next process failed to run it ("Function ... not
    # found"); kept programs are not written to XLA's cache, nor read from it.
    first, _ = _run(tmp_path, "xla")
    assert {p.name.split("-")[0] for p in tmp_path.glob("*-cache")} == {"jit__lambda"}
    for path in (tmp_path / "jaxlens-programs").glob("*.executable"):
        path.unlink()
    again, traced = _run(tmp_path, "xla")
    assert traced and again == first
    loaded, traced = _run(tmp_path, "xla")
    assert not traced and loaded == first


def test_a_program_served_by_xla_cache_is_not_kept(tmp_path):
    # Served by XLA's cache all the same (an entry written by an older version, its
    # kept file gone): the result is used and the executable is not kept.
    first, _ = _run(tmp_path, "xla", "written")
    (kept,) = (tmp_path / "jaxlens-programs").glob("*.executable")
    kept.unlink()
    for _ in range(2):
        again, traced = _run(tmp_path, "xla")
        assert traced and again == first and not kept.exists()


# `jaxlens.keep_programs` in a script: the first process keeps `trace`'s programs, the
# next loads them (their entries have no program to compile) and gives the same rays.
_KEEP = """
import sys

import pytest
import numpy as np
import jaxlens as jl
from jaxlens import _raymap, _trace

folder = jl.keep_programs(sys.argv[1])
r = jl.trace(np.linspace(0.05, 3.0, int(sys.argv[2])), 10.0)
stored = (_trace._compiled, _trace._through_map, _raymap._tabulated_compiled)
entries = [e for f in stored for e in f._programs.values()]
print(float(np.sum(np.asarray(r.phi))), all(e["program"] is None for e in entries),
      len(entries), folder)
"""


@pytest.mark.parametrize("rays, programs", [(2000, 1), (60_000, 2)])  # exact; table
def test_keep_programs_lets_the_next_process_load_trace(tmp_path, rays, programs):
    def run():
        done = subprocess.run([sys.executable, "-c", _KEEP, str(tmp_path), str(rays)],
                              capture_output=True, text=True, timeout=300)  # fmt: skip
        assert done.returncode == 0, done.stderr[-2000:]
        value, loaded, count, folder = done.stdout.split()
        assert count == str(programs) and folder == str(tmp_path)
        return float(value), loaded == "True"

    first, loaded_first = run()
    assert not loaded_first
    assert len(list((tmp_path / "jaxlens-programs").glob("*.executable"))) == programs
    again, loaded_again = run()
    assert loaded_again and again == first


def test_keep_programs_with_an_empty_folder_keeps_nothing(monkeypatch):
    import jax

    before = (_compile._FOLDER, jax.config.jax_compilation_cache_dir)
    assert _compile.keep_programs("") is None
    monkeypatch.setenv("JAXLENS_CACHE_DIR", "")
    assert _compile.keep_programs() is None
    assert (_compile._FOLDER, jax.config.jax_compilation_cache_dir) == before


def test_keep_programs_takes_the_folder_jax_was_given(tmp_path):
    code = (
        "import jax, jaxlens as jl\n"
        f"jax.config.update('jax_compilation_cache_dir', {str(tmp_path)!r})\n"
        "print(jl.keep_programs())\n"
    )
    env = {k: v for k, v in os.environ.items()
           if k not in ("JAXLENS_CACHE_DIR", "JAX_COMPILATION_CACHE_DIR")}  # fmt: skip
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == [str(tmp_path)]


def test_a_preloaded_program_is_loaded_before_its_call(tmp_path):
    first, _ = _run(tmp_path)
    again, traced = _run(tmp_path, "preload")
    assert not traced and again == first


def test_the_last_call_noted_is_loaded_before_its_arguments_are_known(tmp_path):
    # Nothing noted yet: nothing loaded; the call compiles and notes its key.
    none, first, traced = _run(tmp_path, "last")
    assert none == 0 and traced
    # Noted: loaded ahead (one entry before the call), and the call finds it.
    one, again, traced = _run(tmp_path, "last")
    assert one == 1 and not traced and again == first
    # A call of another kind: the noted program loaded in vain, the call compiled.
    one, other, traced = _run(tmp_path, "last", "other")
    assert one == 1 and traced and other != first


def test_is_kept_says_whether_a_call_would_load_its_program(tmp_path):
    import jax
    import jax.numpy as jnp

    from jaxlens._util import filter_jit_cpu

    f = _compile.Stored(filter_jit_cpu(lambda x: 2.0 * x, options={}),
                         lambda *_: jax.tree.structure(0))  # fmt: skip
    x = jnp.arange(3.0)
    assert not f.is_kept(x)  # no folder: nothing is kept
    _compile.use_folder(tmp_path)
    try:
        assert not f.is_kept(x)
        f(x)  # compiled and kept
        assert f.is_kept(x)
        assert not f.is_kept(jnp.arange(4.0))  # another shape
        fresh = _compile.Stored(f._fn, f._structure)  # as a new process sees it: the file
        assert fresh.is_kept(x)
    finally:
        _compile.use_folder(None)
