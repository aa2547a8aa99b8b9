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


def run_now():
    """A context in which JAX calls on concrete values run at once, also inside a
    caller's trace (`jit`, `grad`, ...), their results concrete: for a table built once
    and read as a constant of the caller's program. Unlike `jax.ensure_compile_time_eval`
    it does not also fold the constants of the programs it runs, op by op."""
    try:
        from jax._src import core

        return core.eval_context()
    except (ImportError, AttributeError):  # not in this JAX
        return jax.ensure_compile_time_eval()


def is_zero(x) -> bool:
    """True when `x` is concretely zero (False for tracers)."""
    c = concrete(x)
    return c is not None and bool(np.all(c == 0))


def to_device(x, dtype=None) -> jax.Array:
    """A host value (number, list, NumPy array) as a device array, in `dtype` if given:
    converted on the host and placed (`jnp.asarray` compiles a small program for each
    new shape and dtype)."""
    return jax.device_put(np.asarray(x, dtype))


def as_float(x, dtype=None) -> jax.Array:
    """`x` (array, tracer, list, number) as a floating-point JAX array: in `dtype` if
    given, else its own float dtype (integers and Python numbers take the default
    float dtype, float64 under `jax_enable_x64`). Used as the `converter=` of fields."""
    if not isinstance(x, jax.Array):
        # Host values are converted on the host and placed on the device: `jnp.asarray`
        # compiles a small program for each new shape).
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
