"""Small helpers every module shares: concrete values, float coercion, fusion barriers.

One of each, so that "is this value known now?" and "make this a float array" mean
the same thing in the camera, the skies, the effects and the disk.
"""

import atexit
import gc
import sys

import jax
import jax.numpy as jnp
import numpy as np


def _exit_quickly() -> None:
    """At the interpreter's exit, every object still alive is left out of its last
    garbage collections (`gc.freeze`): they walk all of JAX's traces and caches, 0.13 s
    at the end of a script that traced 100,000 rays once (0.04 s frozen). Objects are
    still freed by their reference counts; only cyclic garbage left at exit is not
    finalised, which Python does not promise either. Not where OpenImageIO is loaded:
    its binding (nanobind) reports each of its objects left at exit as a leak."""
    if "OpenImageIO" not in sys.modules:
        gc.freeze()


atexit.register(_exit_quickly)


def concrete(x) -> np.ndarray | None:
    """The value of `x` as a NumPy array, or `None` when it is a tracer (inside `jit`,
    `grad`, `vmap`): host-side decisions and eager checks use it."""
    if isinstance(x, jax.core.Tracer):
        return None
    try:
        return np.asarray(x)
    except Exception:  # other abstract values (ShapeDtypeStruct, ...)
        return None


def is_concrete(tree) -> bool:
    """True when every array leaf of `tree` has a concrete value."""
    import equinox as eqx

    return all(concrete(x) is not None for x in jax.tree.leaves(tree) if eqx.is_array(x))


def has_tracer(*trees) -> bool:
    """Whether any leaf of `trees` is a tracer (part of a `jit`, `vmap` or `grad`
    trace)."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(trees))


def host_driver(name: str, instead: str, *trees) -> None:
    """Raise a `TypeError` when any leaf of `trees` is a tracer: `name` runs on the host
    (numpy, blocks, a solver of its own) and cannot be traced by `jit`, `vmap` or
    `grad`; `instead` says what to call under them."""
    if has_tracer(*trees):
        raise TypeError(f"jaxlens.{name} runs on the host and cannot be traced by jit, "
                        f"vmap or grad: {instead}")  # fmt: skip


def tracing() -> bool:
    """True inside a JAX transformation's trace (`jit`, `grad`, `vmap`, ...), also where
    the caller's own values are concrete (a closure, a static argument): a compiled
    program of ours called there would be a nested jit, its result a constant."""
    try:
        from jax._src import core

        return not core.trace_state_clean()
    except (ImportError, AttributeError):  # not in this JAX: take the traced path
        return True


def is_zero(x) -> bool:
    """True when `x` is concretely zero (False for tracers)."""
    c = concrete(x)
    return c is not None and bool(np.all(c == 0))


def to_device(x, dtype=None) -> jax.Array:
    """A host value (number, list, NumPy array) as a device array, in `dtype` if given:
    converted on the host and placed (`jnp.asarray` compiles a small program for each
    new shape and dtype, ~20-50 ms each in a fresh process)."""
    return jax.device_put(np.asarray(x, dtype))


def as_float(x, dtype=None) -> jax.Array:
    """`x` (array, tracer, list, number) as a floating-point JAX array: in `dtype` if
    given, else its own float dtype (integers and Python numbers take the default
    float dtype, float64 under `jax_enable_x64`). Used as the `converter=` of fields."""
    if not isinstance(x, jax.Array):
        # Host values are converted on the host and placed on the device: `jnp.asarray`
        # compiles a small program for each new shape (~20 ms each in a fresh process).
        a = np.asarray(x)
        if dtype is None:
            dtype = a.dtype if np.issubdtype(a.dtype, np.floating) else jnp.result_type(float)
        return jax.device_put(a.astype(jax.dtypes.canonicalize_dtype(dtype)))
    if dtype is not None:
        return jnp.asarray(x, dtype)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.result_type(float))


def fusion_barrier(tree, anchor):
    """`tree`, materialised: XLA will not fuse the code that made it into its consumers.

    On CPU, XLA fuses cheap-looking producers (the tail of a closed form, a table
    look-up) into every gather or broadcast that reads them and recomputes them per
    element, which made the ray map ~60x slower. `lax.optimization_barrier` is expanded
    away before fusion on CPU, but a `lax.cond` on a runtime predicate is a fusion
    boundary on every backend. `anchor` is a runtime scalar (e.g. the camera distance,
    tied to the data so that XLA cannot fold it); the branch taken returns `tree`, the
    other (taken only for a NaN anchor, which the value checks reject) zeros.
    """
    return jax.lax.cond(
        ~jnp.isnan(anchor),
        lambda t: t,
        lambda t: jax.tree.map(jnp.zeros_like, t),
        tree,
    )


class _Static:
    """The non-array part of a call's arguments (`eqx.partition`), hashable: a static
    argument of `jax.jit`."""

    def __init__(self, tree):
        self.leaves, self.treedef = jax.tree.flatten(tree)
        self._hash = hash((tuple(self.leaves), self.treedef))

    def __hash__(self):
        return self._hash

    def __eq__(self, other):
        return (isinstance(other, _Static) and self.treedef == other.treedef
                and self.leaves == other.leaves)  # fmt: skip

    def tree(self):
        return jax.tree.unflatten(self.treedef, self.leaves)


# XLA's older CPU fusion code generation (`filter_jit_cpu`'s options). It compiles the
# fit's solver in 5 s instead of 9 s, its start search in 2.4 s instead of 3.7 s and
# `trace`'s table program in 0.6 s instead of 0.9 s, each running as fast, and a
# render's ray map in 0.63 s instead of 0.77 s (run: 1.2 ms instead of 0.7 ms); a
# render's block, by contrast, runs twice as long with it, so it keeps the default.
OLDER_CPU_FUSION = {"xla_cpu_use_fusion_emitters": False}

# `OLDER_CPU_FUSION` with LLVM's optimisation at level 1 (XLA's default is 3): code
# that compiles sooner and, for these programs, runs as fast or faster. The fit's
# solver: its solve of the fit benchmark ring (three evaluations of the model and its
# Jacobian) 0.63 s instead of 0.90 s, compiled in 3.25 s instead of 3.67 s (medians of
# 3; the same result to the last bit); the start search compiled in 1.33-1.36 s
# instead of 1.42-1.56 s, running as fast.
FIT_PROGRAM = {**OLDER_CPU_FUSION, "xla_backend_optimization_level": 1}

# The block of a render without effects at LLVM's level 1, XLA's own fusion emitters
# kept: the default scene's block compiles in 0.89-0.95 s instead of 1.01-1.03 s, a
# cold `jaxlens render` 2.64 s instead of 2.83 s (medians of 5 alternating fresh
# processes); warm, the default scene's render 0.25-0.27 s against 0.27-0.29 s, the
# 1080p panorama's CPU time 75-88 ms against 78-89 ms, a 4096 x 4096 default sky
# 1.57-1.60 s against 1.54-1.56 s; the same pixels to the bit. (Effect scenes keep the
# default level: an orbit, redshift and a disk at 4096 x 4096 ran 20 % slower at 1.)
RENDER_PROGRAM = {"xla_backend_optimization_level": 1}

# `FIT_PROGRAM`'s options with the code generated in one piece, not split over the
# cores: for a program that compiles beside another (on a second thread, or on the main
# one while the other compiles or runs), which then keeps the other core. Measured (the
# one piece): `trace`'s look-up beside the table's build (first trace 1.76 s instead of
# 1.85 s), the fit's start search beside its solver (cold fit 9.5 s instead of 9.9 s)
# and the noise check beside the first pass (that solve 1.0-1.1 s instead of 1.3-1.4
# s); each runs as fast. (Level 1: the first eager `trace` of 100,000 rays 0.47-0.49 s
# instead of 0.52-0.58 s, again 3.4-3.5 ms instead of 3.6-3.7 ms.)
SIDE_PROGRAM = {**FIT_PROGRAM, "xla_cpu_parallel_codegen_split_count": 1}

# `SIDE_PROGRAM` without LLVM's optimisations: for a program that runs once or twice on
# little data, whose compile is the longer part. Measured: a table's build (the closed
# form on a few thousand knots; float32 at 1e-6 rad: compiled in 0.16 s instead of
# 0.37 s, run in 1.2 ms instead of 0.5 ms; float64 at 1e-10 rad, 22,000 knots: 26 ms
# instead of 15 ms), the fit's noise check on the benchmark ring's 35,808 bins (0.14 s
# instead of 0.25-0.29 s, run 5-7 ms instead of 3-6 ms, the same bits).
ONCE_PROGRAM = {**SIDE_PROGRAM, "xla_backend_optimization_level": 0}


class filter_jit_cpu:
    """`eqx.filter_jit` (arrays traced, every other argument static) of a function whose
    programs compile with XLA `options` on the CPU backend (`jax.jit`'s
    `compiler_options`; other backends compile as usual), e.g. `OLDER_CPU_FUSION`.
    `options()` gives the options of the current backend, for another jit of the same
    program (`_compile.Stored`).
    """

    def __init__(self, fn, options: dict):
        import functools

        functools.update_wrapper(self, fn)
        self._fn, self._options, self._jits = fn, dict(options), {}

    def options(self) -> dict | None:
        return self._options if jax.default_backend() == "cpu" else None

    def _jitted(self, nested: bool = False):
        """The `jax.jit` of the current backend (`nested`: the one without options, for
        a call inside another trace, where JAX takes options only at the top)."""
        key = "nested" if nested else jax.default_backend()
        if key not in self._jits:
            fn = self._fn

            def call(dynamic, static):
                import equinox as eqx

                return fn(*eqx.combine(dynamic, static.tree()))

            call.__name__ = call.__qualname__ = fn.__name__  # as profiles name it
            options = None if nested else self.options()
            self._jits[key] = jax.jit(call, static_argnums=1, compiler_options=options)
        return self._jits[key]

    def _split(self, args):
        import equinox as eqx

        dynamic, static = eqx.partition(args, eqx.is_array)
        nested = has_tracer(dynamic)
        return self._jitted(nested), dynamic, _Static(static)

    def __call__(self, *args):
        jitted, dynamic, static = self._split(args)
        return jitted(dynamic, static)

    def lower(self, *args):
        jitted, dynamic, static = self._split(args)
        return jitted.lower(dynamic, static)


_PENDING: list = []  # compile_ahead's futures not known to be done
_IDLE: list = []  # when_idle's work, not yet done


def when_idle(fn) -> None:
    """Do `fn()` at the end of the next `compile_ahead` block if its compile is still
    running then, on the core the wait would leave idle (else it is dropped): what a
    later step needs ready, a module imported or a file format's plugin loaded. Its
    errors are left to that later step, which meets them again."""
    _IDLE.append(fn)


class compile_ahead:
    """Compile a jitted function (`jax.jit`, `eqx.filter_jit`, `filter_jit_cpu`) for
    `args` on a background thread; `with compile_ahead(f, *args): ...` runs the block
    meanwhile and waits for the compile at its end (not when the block raises).
    `compile_ahead.calls((f, *args), (g, *args_g), ...)` compiles several, in that
    order, on the one thread; an `f` that is not jitted (no `lower`) is called instead,
    for the programs it compiles (an eager `trace`).

    XLA compiles without holding the GIL, so a program the caller needs next compiles
    while the current one compiles or runs (on a fresh process the two compiles overlap
    instead of following each other); the later call `f(*args)` (same shapes, dtypes
    and static values) finds it in `f`'s cache. A failed compile is left to that call
    to report. The thread compiles under the caller's `jax_enable_x64` (a context sets
    it for the calling thread only).
    """

    def __init__(self, f, *args):
        self._start([(f, *args)])

    @classmethod
    def calls(cls, *calls):
        self = cls.__new__(cls)
        self._start(calls)
        return self

    def _start(self, calls):
        from concurrent.futures import ThreadPoolExecutor

        x64 = jax.config.read("jax_enable_x64")

        def run():
            with jax.enable_x64(x64):
                for f, *args in calls:
                    try:
                        f.lower(*args).compile() if hasattr(f, "lower") else f(*args)
                    except Exception:  # noqa: BLE001, S112 - the call itself reports it
                        continue

        pool = ThreadPoolExecutor(1, thread_name_prefix="jaxlens-compile")
        self._future = pool.submit(run)
        pool.shutdown(wait=False)
        _PENDING[:] = [f for f in _PENDING if not f.done()] + [self._future]

    @staticmethod
    def wait_all() -> None:
        """Wait for every compile still running on a thread (before a quick exit: each
        writes the caches it keeps)."""
        for future in list(_PENDING):
            future.exception()  # waits; a failed compile is the call's to report

    def __enter__(self):
        return self

    def __exit__(self, kind, value, tb):
        if kind is not None:  # the block failed (or Ctrl-C): no reason to wait
            return False
        while _IDLE and not self._future.done():
            try:
                _IDLE.pop(0)()
            except Exception:  # noqa: BLE001, S110 - the step that needs it reports it
                pass
        _IDLE.clear()
        self._future.result()
        return False
