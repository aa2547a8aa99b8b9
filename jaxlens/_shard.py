"""Scale-out: ray batches split across all visible devices, and through memory in chunks.

One code path for one CPU, several GPUs or several hosts (after
`jax.distributed.initialize()`): a flat batch of rays is padded to a multiple of
the device count, laid out over a 1-D `jax.sharding.Mesh` (axis `"rays"`) with a
`NamedSharding`, and each device runs the ray function on its own block through
`jax.shard_map` (no communication between devices: a ray's result depends on that
ray alone, so an adaptive loop on one device never waits for another's slow rays).
Batches larger than memory go through a Python loop over chunks of one fixed size,
so the function compiles once; the next chunk is dispatched before the previous one
is copied to the host, so transfers overlap computation.
"""

import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from ._ray_inputs import check_distance
from ._status import TraceResult
from ._trace import trace
from ._units import angle, length

AXIS = "rays"  # name of the mesh axis the rays are split over

# With progress=None a bar is shown from this many chunks on.
_PROGRESS_MIN_CHUNKS = 8


def ray_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D device mesh with axis `"rays"` over all devices (of every process).

    **Arguments:** `devices`: the devices to use, in order; default `jax.devices()`,
    i.e. every device of every process after `jax.distributed.initialize()`.

    **Returns:** a `jax.sharding.Mesh` of shape `(len(devices),)`.
    """
    devices = jax.devices() if devices is None else list(devices)
    if len(devices) == 0:
        raise ValueError("devices=[] is empty: a mesh needs at least one device")
    return Mesh(np.asarray(devices, dtype=object), (AXIS,))


def _to_host(x):
    """Copy a (possibly multi-process) global array into a NumPy array on every process."""
    if jax.process_count() == 1:
        return np.asarray(x)
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.process_allgather(x, tiled=True))


def _put(host, sharding):
    """Place a host array as a global array; each process supplies only its own shards."""
    return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])


@functools.lru_cache(maxsize=64)
def _sharded_jit(fn, mesh, in_specs):
    """`fn` under `shard_map` over `mesh`, jitted; cached so repeated calls compile once."""
    local = jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=P(AXIS), check_vma=False)
    return jax.jit(local)


def shard_map_rays(
    fn: Callable[..., Any],
    *arrays: Any,
    chunk: int | None = None,
    mesh: Mesh | None = None,
    progress: bool | None = None,
) -> Any:
    """Apply a ray-wise function to a batch of rays, split across devices and in chunks.

    `fn` must be ray-wise: output row $i$ depends on input row $i$ only (true of
    `trace` and of any function that is elementwise or `vmap`ped over rays). Then the
    result is bit for bit that of `jax.jit(fn)` on one device on the same rays as one
    flat batch, whatever the device count, the padding or the chunk size. (XLA may
    round differently, by an ulp, when the rays come as a 2-D array or when a scalar
    is folded into the program as a constant.)

    With several processes (after `jax.distributed.initialize()`), every process calls
    this with the same inputs; each one places only its own devices' shards.

    **Arguments:**
    - `fn`: a JAX-traceable function of the arrays; it receives the non-scalar
      arguments as flat 1-D blocks of rays (of one shape `(m,)`) and the scalar ones
      unchanged, and returns a pytree of arrays whose leading axis is the ray axis
      (of length `m`; trailing axes are kept).
    - `*arrays`: the inputs. Arguments of dimension >= 1 are broadcast together to
      one batch shape, flattened and split over the devices; scalars (Python numbers
      keep their weak type, so `fn(alpha32, 20.0)` stays float32) go to every device.
      At least one argument must have dimension >= 1.
    - `chunk`: rays per compiled call; `None` runs the whole batch in one call.
      Rounded up to a multiple of the device count. The last chunk is padded to the
      same size, so `fn` compiles once for any batch size.
    - `mesh`: a 1-D mesh with axis `"rays"`; default `ray_mesh()` (all devices).
    - `progress`: tqdm bar over chunks: `True`, `False`, or `None` to show one when
      there are at least 8 chunks (on process 0 only).

    **Returns:** the pytree `fn` returns, each leaf a NumPy array on the host of shape
    `batch_shape + trailing_shape`, identical on every process.

    Padding repeats the last ray, so padded rays are valid inputs (no spurious
    errors from `eqx.error_if` checks) and are dropped from the result. Not itself
    jittable: it is the host-side driver around one compiled, sharded call.
    """
    if chunk is not None and (isinstance(chunk, bool) or int(chunk) != chunk or chunk < 1):
        raise ValueError(f"chunk={chunk!r} must be a positive integer number of rays (or None)")
    mesh = ray_mesh() if mesh is None else mesh
    if mesh.axis_names != (AXIS,):
        raise ValueError(f"mesh has axes {mesh.axis_names!r}; expected one axis named {AXIS!r}")
    n_dev = mesh.devices.size

    is_batch = [np.ndim(a) >= 1 for a in arrays]
    if not any(is_batch):
        raise ValueError("shard_map_rays needs at least one argument of dimension >= 1 (the rays)")
    batch_shape = np.broadcast_shapes(*(np.shape(a) for a, b in zip(arrays, is_batch) if b))
    n = math.prod(batch_shape)
    # Host copies, flat, in the dtype JAX would give them (float64 -> float32 without x64).
    flat = [
        np.ascontiguousarray(
            np.broadcast_to(
                np.asarray(a, dtype=jax.dtypes.canonicalize_dtype(np.asarray(a).dtype)),
                batch_shape,
            ).reshape(-1)
        )
        if b
        else a
        for a, b in zip(arrays, is_batch)
    ]

    size = n if chunk is None else min(int(chunk), n)
    size = max(n_dev, -(-size // n_dev) * n_dev)  # a whole number of rays per device
    n_chunks = -(-n // size) if n > 0 else 0

    ray_sharding = NamedSharding(mesh, P(AXIS))
    in_specs = tuple(P(AXIS) if b else P() for b in is_batch)
    compiled = _sharded_jit(fn, mesh, in_specs)

    def launch(k):
        lo, hi = k * size, min((k + 1) * size, n)
        args = []
        for a, b in zip(flat, is_batch):
            if not b:
                args.append(a)
                continue
            block = a[lo:hi]
            if hi - lo < size:  # pad with the last ray: valid input, dropped afterwards
                block = np.concatenate([block, np.repeat(block[-1:], size - (hi - lo))])
            args.append(_put(block, ray_sharding))
        return hi - lo, compiled(*args)

    if n_chunks == 0:  # empty batch: trace the shapes only
        empty = [jnp.zeros((0,), a.dtype) if b else a for a, b in zip(flat, is_batch)]
        spec = jax.eval_shape(fn, *empty)
        return jax.tree.map(lambda s: np.zeros(batch_shape + s.shape[1:], s.dtype), spec)

    show = progress if progress is not None else n_chunks >= _PROGRESS_MIN_CHUNKS
    show = show and jax.process_index() == 0
    bar = None
    if show:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, unit="ray", unit_scale=True, desc="rays")

    result = None  # host arrays for the whole batch, filled chunk by chunk
    pending = launch(0)
    for k in range(n_chunks):
        ahead = launch(k + 1) if k + 1 < n_chunks else None  # dispatched asynchronously
        m, out = pending
        host = jax.tree.map(_to_host, out)
        if result is None:
            result = jax.tree.map(lambda x: np.empty((n,) + x.shape[1:], x.dtype), host)
        lo = k * size
        for dst, src in zip(jax.tree.leaves(result), jax.tree.leaves(host)):
            dst[lo : lo + m] = src[:m]
        if bar is not None:
            bar.update(m)
        pending = ahead
    if bar is not None:
        bar.close()
    return jax.tree.map(lambda x: x.reshape(batch_shape + x.shape[1:]), result)


def trace_sharded(
    alpha: Any,
    distance: Any,
    *,
    chunk: int | None = None,
    mesh: Mesh | None = None,
    progress: bool | None = None,
    **trace_kwargs: Any,
) -> TraceResult:
    """`trace` over all visible devices, in chunks of `chunk` rays.

    The same rays give the same `TraceResult` as `jax.jit(trace)` on one device.

    **Arguments:**
    - `alpha`: ray angles from the inward radial direction (radians, or an astropy
      angle Quantity), any shape.
    - `distance`: camera radius $D > 1$ (units of R_S, or a dimensionless Quantity);
      a scalar, or an array that broadcasts with `alpha`.
    - `chunk`, `mesh`, `progress`: as in `shard_map_rays`.
    - `**trace_kwargs`: passed to `trace` (`accuracy`, `method`, `max_windings`).

    **Returns:** a `TraceResult` of NumPy arrays of the broadcast shape.
    """
    alpha = angle(alpha, "alpha")
    distance = length(distance, "distance")
    # The same ValueError as `trace`, raised on the host before anything is compiled.
    check_distance(np.asarray(distance))
    if np.ndim(alpha) == 0 and np.ndim(distance) == 0:
        alpha = np.reshape(alpha, (1,))
        out = trace_sharded(
            alpha, distance, chunk=chunk, mesh=mesh, progress=progress, **trace_kwargs
        )
        return jax.tree.map(lambda x: x.reshape(()), out)

    fn = _trace_fn(**trace_kwargs)
    return shard_map_rays(fn, alpha, distance, chunk=chunk, mesh=mesh, progress=progress)


@functools.lru_cache(maxsize=64)
def _trace_fn_cached(items):
    kwargs = dict(items)

    def fn(a, d):
        return trace(a, d, **kwargs)

    return fn


def _trace_fn(**kwargs):
    """One function object per set of `trace` options, so its compilation is reused."""
    items = tuple(sorted(kwargs.items()))
    try:
        return _trace_fn_cached(items)
    except TypeError:  # an unhashable option: no reuse across calls

        def fn(a, d):
            return trace(a, d, **kwargs)

        return fn
