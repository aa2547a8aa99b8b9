"""`jaxlens._compile`: programs compiled with their XLA profile, kept between processes
(what goes into their key, the result's structure recorded with the executable, a kept
program that calls JAX's LAPACK kernels loaded by a fresh process, which has not set
them up: calling it unprepared ends the process), options an XLA does not know
dropped, and the compiles a driver asks for ahead."""

import os
import subprocess
import sys
import threading
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxlens import _compile

# Keeps (first run) or loads (second run) a program with a QR decomposition, whose
# result is a dict holding a tuple, in the folder given, and prints a value of its
# result and whether it was traced.
_CHILD = """
import sys

import jax, jax.numpy as jnp, numpy as np
from jaxlens import _compile

traced = []

def qr_sum(a, scale):
    traced.append(1)
    r = jnp.linalg.qr(a)[1]
    return {"sum": jnp.sum(jnp.abs(r)) * scale, "parts": (r[0, 0], r[1, 1])}

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
f = _compile.program(qr_sum, profile="legacy_fusion_o1")
a = np.arange(16.0, dtype=np.float32).reshape(4, 4) ** 0.5
if "ahead" in sys.argv:  # loaded on the driver's thread before the call: it finds it
    with _compile.ahead((f, a, 2.0)):
        pass
    assert all(e.compiled is not None for e in f._kept.values()), "not loaded"
out = f(a, 2.0)
assert sorted(out) == ["parts", "sum"] and isinstance(out["parts"], tuple)
print(float(out["sum"]), bool(traced))
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
entries = [e for f in stored for e in f._kept.values()]
print(float(np.sum(np.asarray(r.phi))), all(e.program is None for e in entries),
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


def test_a_program_loaded_ahead_is_not_traced(tmp_path):
    first, _ = _run(tmp_path)
    again, traced = _run(tmp_path, "ahead")
    assert not traced and again == first


@pytest.mark.parametrize("profile", sorted(_compile.PROFILES))
def test_an_option_xla_does_not_know_is_dropped_not_an_error(monkeypatch, profile):
    # A jaxlib that renamed or removed a flag the profiles use: XLA refuses it by name
    # ("No such compile option"); the program compiles without it, with one warning.
    flag = "xla_jaxlens_test_no_such_option"
    monkeypatch.setitem(_compile.PROFILES, profile, {**_compile.PROFILES[profile], flag: True})
    monkeypatch.setattr(_compile, "_UNKNOWN", set())
    f = _compile.program(lambda x, n: jnp.sin(x) * n, profile=profile, keep=False)
    with pytest.warns(RuntimeWarning, match=flag):
        out = f(jnp.arange(3.0), 2)
    np.testing.assert_allclose(out, np.sin(np.arange(3.0)) * 2, rtol=1e-6)
    assert _compile.options(profile) == ({k: v for k, v in _compile.PROFILES[profile].items()
                                          if k != flag} or None)  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once: the next program compiles without it
        g = _compile.program(lambda x: x + 1, profile=profile, keep=False)
        np.testing.assert_allclose(g(jnp.arange(2.0)), [1.0, 2.0])


def test_every_program_runs_where_xla_knows_none_of_the_profiles_options(tmp_path):
    # Every profile given an option XLA does not know, in a fresh process: `trace`
    # (exact, and a table's build and look-up), a render and a ring fit (its start
    # search, solver and noise check on an image clipped at 0) still run, and give
    # the results they give with the options XLA knows.
    code = """
import math, sys, warnings
import numpy as np, jaxlens as jl
from jaxlens import _compile
if sys.argv[1] == "unknown":
    for name, opts in _compile.PROFILES.items():
        _compile.PROFILES[name] = {**opts, "xla_jaxlens_test_unknown": 1}
with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    a = np.linspace(0.1, 3.0, 2000)
    exact = jl.trace(a, 10.0)
    table = jl.trace(a, 10.0, method="table")
    sky = jl.GaussianStar(math.radians(1.5), 0.8)  # no floor: the noise clipped at 0
    img = jl.render(jl.Camera(20.0, math.radians(60.0), 96, 72, supersample=3), sky)
    noisy = img[..., 0] + 0.01 * np.random.default_rng(1).standard_normal(img.shape[:2])
    fit = jl.fit_ring(np.clip(noisy, 0.0, 1.0), star_sigma=math.radians(1.5))
from jaxlens._fit import objective, starts
ran = [p._scheduled for p in (objective.solve, objective.renoised, starts._candidate_losses)]
assert all(ran), ran
print(len([w for w in seen if "xla_jaxlens_test_unknown" in str(w.message)]),
      float(np.max(np.abs(exact.phi - table.phi))), float(img.sum()), fit.distance)
"""

    def run(mode):
        done = subprocess.run([sys.executable, "-c", code, mode], capture_output=True,
                              text=True, timeout=600, cwd=tmp_path)  # fmt: skip
        assert done.returncode == 0, done.stderr[-3000:]
        warned, diff, lit, distance = done.stdout.split()
        return int(warned), float(diff), float(lit), float(distance)

    warned, diff, lit, distance = run("unknown")
    assert warned == 1 and diff < 1e-4 and lit > 0 and abs(distance / 20.0 - 1) < 0.05
    assert run("known")[1:] == (diff, lit, distance)  # the unknown option changed nothing


def test_a_call_inside_another_trace_is_part_of_it():
    f = _compile.program(lambda x: 2.0 * x, profile="legacy_fusion_o1")
    g = jax.grad(lambda x: jnp.sum(f(x) ** 2))
    np.testing.assert_allclose(g(jnp.arange(3.0)), 8.0 * np.arange(3.0))
    np.testing.assert_allclose(jax.vmap(f)(jnp.ones((2, 3))), 2.0)


def test_ahead_compiles_once_on_a_thread_and_the_call_finds_it():
    events = []
    f = _compile.program(lambda x: jnp.cumsum(jnp.sin(x)) * 3.0, profile="legacy_fusion_o0_side")
    x = jnp.linspace(0.0, 1.0, 37)

    def listen(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            events.append(threading.current_thread().name)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        with _compile.ahead((f, x)):
            pass
        with _compile.ahead((f, x)):  # scheduled before: nothing more to compile
            pass
        out = f(x)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    np.testing.assert_allclose(out, np.cumsum(np.sin(np.linspace(0, 1, 37))) * 3, rtol=1e-5)
    assert events == ["jaxlens-compile"], events


def test_ahead_leaves_a_failure_to_the_call_and_does_not_wait_where_the_block_raises():
    def bad(x):
        raise ValueError("the call's own error")

    f = _compile.program(bad)
    with _compile.ahead((f, jnp.ones(2))):  # nothing compiled: the trace failed
        pass
    with pytest.raises(ValueError, match="the call's own error"):
        f(jnp.ones(2))
    slow = _compile.program(lambda x: x)
    slow._ahead = lambda *args: lambda: time.sleep(2.0)
    t0 = time.perf_counter()
    with pytest.raises(KeyError), _compile.ahead((slow, 1.0)):
        raise KeyError("the block failed")
    assert time.perf_counter() - t0 < 1.0
