"""The inputs every tracer checks, in one place below them all: real numbers, the float
dtypes rays are traced in, the camera distance and the local angle. Each check raises
eagerly on a concrete value and gives the predicate (or an `eqx.error_if`) under `jit`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._messages import real_array, shown
from ._util import concrete

# The largest camera distance accepted (units of R_S), in float32 and float64: the bound
# of the CLI and of scene files (`_schema.MAGNITUDE_MAX`). Both dtypes' geometry is
# finite and accurate up to it (tests/test_checks.py); float32 fails near 1e37, where
# 1/D leaves its normal range, float64 near 1e300. 1e30 R_S is 3e36 m for a solar mass.
MAX_DISTANCE = 1e30
# The bound as compared: 1e30 as float32 rounds it (1.0000000150e30), in every dtype, so
# that a float32 camera at 1e30 keeps working once its distance is widened to float64.
_MAX_COMPARED = float(np.float32(MAX_DISTANCE))

# The dtypes rays are traced in (float16 and bfloat16 overflow in the closed forms).
FLOAT_DTYPES = ("float32", "float64")

_DISTANCE_RANGE = (
    f"finite, > 1 and <= {MAX_DISTANCE:g} (units of R_S: the horizon is at 1, "
    f"{MAX_DISTANCE:g} is the largest supported)"
)


def check_real(name: str, x):
    """`x` if it holds real numbers (a list or tuple as a NumPy array), else a TypeError
    naming `name` and the value (integers are converted; complex, bool, text and
    objects are not)."""
    checked = real_array(name, x)
    return checked if isinstance(x, list | tuple) else x


def check_dtype(dtype, what: str = "dtype") -> np.dtype:
    """The float dtype rays are computed in, or a TypeError naming `what` (e.g.
    "dtype", or "alpha and distance"): float32 or float64 only."""
    try:
        dt = np.dtype(dtype)
    except TypeError:
        dt = None
    if dt is None or dt.name not in FLOAT_DTYPES:
        named = dt.name if dt is not None else shown(dtype)
        raise TypeError(
            f"{what}: {named} is not supported, use float32 or float64 (the geometry "
            "overflows in lower precisions; float64 needs jax_enable_x64)"
        )
    return dt


def check_distance(distance, dtype=None):
    """ValueError for a concrete bad distance: not finite, <= 1, beyond `MAX_DISTANCE`,
    or > 1 as given but rounded to the horizon in `dtype` (the dtype the rays are traced
    in); eqx.error_if under jit."""
    try:
        d = np.asarray(distance)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        d = None
    if d is not None:
        check_real("distance", d)
        top = _MAX_COMPARED
        d = d.astype(np.float64)
        bad = ~np.isfinite(d) | ~(d > 1.0)
        if np.any(bad):
            raise ValueError(
                f"distance={shown(d[bad].flat[0])} is not a valid camera radius: it must be "
                + _DISTANCE_RANGE
            )
        if np.any(d > top):
            raise ValueError(
                f"distance={shown(d[d > top].flat[0])} is beyond the largest "
                f"supported, {MAX_DISTANCE:g} R_S (float32 and float64): it must be "
                + _DISTANCE_RANGE
            )
        rounded = d if dtype is None else d.astype(dtype)
        if np.any(~(rounded > 1.0)):
            i = int(np.argmin(rounded > 1.0))
            raise ValueError(
                f"distance={float(d.flat[i])!r} rounds to {float(rounded.flat[i])!r} (the "
                f"horizon) in {jnp.dtype(dtype).name}: pass float64 inputs with "
                "jax_enable_x64 on for a camera this close"
            )
        return distance
    return eqx.error_if(distance, distance_bad(distance), DISTANCE_MESSAGE)


DISTANCE_MESSAGE = (
    "distance must be finite and > 1 (units of R_S, the horizon is at 1), and at most "
    f"{MAX_DISTANCE:g}"
)


def distance_bad(distance):
    """Where a traced `distance` is out of range (the predicate of `check_distance`)."""
    return ~jnp.isfinite(distance) | ~(distance > 1.0) | (distance > _MAX_COMPARED)


ALPHA_RANGE = "in [0, pi] radians (0 points at the hole, pi straight away)"
# The top of that range as checked: pi rounded to float32 (8.7e-8 above pi), so that a
# float32 pi, widened to float64, is still straight away.
_ALPHA_TOP = float(np.float32(np.pi))


def bad_alpha(alpha):
    """ValueError for a concrete local angle outside [0, pi] (NaN included); for traced
    ones, the predicate (one comparison a ray) that `trace` puts on its result with
    `eqx.error_if`, so that the rays do not wait for the check. `None` when checked."""
    a = concrete(alpha)
    if a is not None:
        # Two reductions, no array of flags (a NaN is the minimum and the maximum).
        if a.size == 0 or (np.min(a) >= 0 and np.max(a) <= _ALPHA_TOP):
            return None
        bad = ~((a >= 0) & (a <= _ALPHA_TOP))
        if np.any(bad):
            raise ValueError(
                f"alpha={shown(a[bad].flat[0])} is not a valid local angle: it must be "
                + ALPHA_RANGE
            )
        return None
    return jnp.any(~((alpha >= 0) & (alpha <= _ALPHA_TOP)))
