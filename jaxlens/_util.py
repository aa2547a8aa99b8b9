"""Small helpers every module shares: concrete values, float coercion, fusion barriers.

One of each, so that "is this value known now?" and "make this a float array" mean
the same thing in the camera, the skies, the effects and the disk.
"""

import jax
import jax.numpy as jnp
import numpy as np


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


class compile_ahead:
    """Compile a jitted function (`jax.jit` or `eqx.filter_jit`) for `args` on a
    background thread; `with compile_ahead(f, *args): ...` runs the block meanwhile and
    waits for the compile at its end (not when the block raises).

    XLA compiles without holding the GIL, so a program the caller needs next compiles
    while the current one compiles or runs (on a fresh process the two compiles overlap
    instead of following each other); the later call `f(*args)` (same shapes, dtypes
    and static values) finds it in `f`'s cache. A failed compile is left to that call
    to report. The thread compiles under the caller's `jax_enable_x64` (a context sets
    it for the calling thread only).
    """

    def __init__(self, f, *args):
        from concurrent.futures import ThreadPoolExecutor

        x64 = jax.config.read("jax_enable_x64")

        def run():
            with jax.enable_x64(x64):
                f.lower(*args).compile()

        pool = ThreadPoolExecutor(1, thread_name_prefix="jaxlens-compile")
        self._future = pool.submit(run)
        pool.shutdown(wait=False)

    def __enter__(self):
        return self

    def __exit__(self, kind, value, tb):
        if kind is not None:  # the block failed (or Ctrl-C): no reason to wait
            return False
        try:
            self._future.result()
        except Exception:  # noqa: BLE001, S110 - the call itself compiles and reports it
            pass
        return False
