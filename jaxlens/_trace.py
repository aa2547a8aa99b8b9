"""`trace`: camera rays -> escape angle and capture, the single source of truth for Phi."""

import abc
import contextlib
import functools
import math
from typing import ClassVar, final

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from . import _exact, _integrators
from ._integrators import ButcherTableau, integrate, rk_step
from ._orbit import acceleration
from ._compile import Stored
from ._status import CAPTURED, ESCAPED, UNRESOLVED, RayStatus
from ._util import (
    OLDER_CPU_FUSION,
    SIDE_PROGRAM,
    compile_ahead,
    concrete,
    filter_jit_cpu,
    has_tracer,
    to_device,
    tracing,
)


class TraceResult(eqx.Module):
    """Outcome of tracing rays from a static camera.

    **Fields:**
    - `phi`: escape angle, the azimuth swept in the orbital plane from the camera
      to the escaping asymptote (radians; $\\pi - \\alpha$ in flat space). For a
      captured ray, the azimuth at which it crosses the horizon.
    - `status`: per ray, an int8 code: `ESCAPED` (0), `CAPTURED` (1) or
      `UNRESOLVED` (2: beyond the winding budget or the step budget; never painted
      as captured), the positions of the items of `RayStatus`, which holds the
      message of each. An array, not an `eqx.Enumeration` item, so that it indexes,
      shards and compares like the other fields.
    - `r_min`: smallest radius reached (units of R_S; 1 for captured rays).
    """

    phi: Float[Array, "..."]
    status: Int[Array, "..."]
    r_min: Float[Array, "..."]

    @property
    def captured(self):
        """True where the ray falls into the horizon."""
        return self.status == CAPTURED

    @property
    def escaped(self):
        """True where the ray reaches infinity."""
        return self.status == ESCAPED

    @property
    def unresolved(self):
        """True where the ray ran out of its winding or step budget."""
        return self.status == UNRESOLVED

    @property
    def half_turns(self):
        """Number of completed half-turns, $\\lfloor \\phi / \\pi \\rfloor$."""
        return jnp.floor(self.phi / jnp.pi).astype(jnp.int32)


# ---------------------------------------------------------------------------
# Methods. Each is a small immutable object: its settings fix the accuracy.


class AbstractMethod(eqx.Module):
    """A way to compute the escape angle of rays from a static camera."""

    @abc.abstractmethod
    def __call__(self, alpha, distance, max_windings) -> TraceResult:
        """Trace rays at local angles `alpha` (radians) from a camera at `distance`
        (units of R_S, broadcast with `alpha`), with a budget of `max_windings` turns.

        **Returns:** a `TraceResult` of the broadcast shape.
        """


@final
class Exact(AbstractMethod):
    """Closed form through Carlson's $R_F$; `iterations` duplication steps."""

    iterations: int = eqx.field(static=True, default=12)

    def __call__(self, alpha, distance, max_windings):
        phi, status, r_min = _exact.escape_angle(
            alpha, distance, iterations=self.iterations, max_windings=max_windings
        )
        return TraceResult(phi, status, r_min)


class AbstractIntegrator(AbstractMethod):
    """Integrate the orbit equation $u'' = 1.5 u^2 - u$ in azimuth with a Runge-Kutta
    tableau. A subclass only names its tableau and its settings.

    **Fields:**
    - `tableau` (class variable): the `ButcherTableau`; adaptive stepping if it has
      an error estimate (`b_error`).
    - `dphi`: the step (fixed tableau) or the first trial step (adaptive), radians.
    - `tol`: per-step tolerance on the error relative to $|u| + |u'|$ (adaptive), or
      `None` (fixed step).
    - `max_steps`: step budget a ray; rays beyond it are `UNRESOLVED`.
    """

    tableau: eqx.AbstractClassVar[ButcherTableau]
    dphi: eqx.AbstractVar[float]
    tol: eqx.AbstractVar[float | None]
    max_steps: eqx.AbstractVar[int]

    def step(self, u: ArrayLike, v: ArrayLike) -> tuple[Array, Array]:
        """One step of size `dphi` (radians) along an orbit, without step-size control.

        **Arguments:**
        - `u, v`: $u = 1/r$ (units of $1/R_S$) and $du/d\\phi$, arrays of one shape.

        **Returns:** `(u, v)` after the step.
        """
        u1, v1, _ = rk_step(self.tableau, acceleration, jnp.asarray(u), jnp.asarray(v), self.dphi)
        return u1, v1

    def __call__(self, alpha, distance, max_windings):
        alpha, distance = jnp.broadcast_arrays(alpha, distance)
        u0 = 1.0 / distance
        root = u0 * jnp.sqrt((distance - 1.0) / distance)
        sa = jnp.abs(jnp.sin(alpha))
        # Near-radial rays (b < 1e-3): u' -> infinity makes the orbit equation in phi
        # stiff; the series of the exact integral is accurate to O(b^5) there.
        b = sa / root
        radial = b < 1e-3
        inward = jnp.cos(alpha) > 0
        v0 = root * jnp.cos(alpha) / jnp.where(radial, 1.0, sa)
        v0 = jnp.where(radial, 0.0, v0)
        phi, outcome, r_min, _ = integrate(
            u0, v0, self.tableau, dphi=self.dphi, tol=self.tol, max_steps=self.max_steps
        )
        x, y = jnp.where(inward, 1.0, u0), jnp.where(inward, u0, 0.0)
        dxy = jnp.where(inward, (distance - 1.0) / distance, u0)
        phi = jnp.where(radial, _exact.small_b_integral(x, y, dxy, b), phi)
        outcome = jnp.where(radial, jnp.where(inward, 1, 0), outcome)
        cap = 2.0 * jnp.pi * max_windings
        over = (outcome == 2) | (phi > cap)
        status = jnp.where(over, UNRESOLVED, jnp.where(outcome == 1, CAPTURED, ESCAPED)).astype(
            jnp.int8
        )
        r_min = jnp.where(status == CAPTURED, 1.0, jnp.minimum(r_min, distance))
        return TraceResult(jnp.minimum(phi, cap), status, r_min.astype(alpha.dtype))


@final
class Euler(AbstractIntegrator):
    """Semi-implicit (symplectic) Euler with fixed step `dphi` (radians): the
    original C++ program's scheme, kept for comparison. First order; at most
    `max_steps` steps a ray."""

    tableau: ClassVar[ButcherTableau] = _integrators.EULER
    tol: ClassVar[None] = None
    dphi: float = eqx.field(static=True, default=0.003)
    max_steps: int = eqx.field(static=True, default=50_000)


@final
class RK4(AbstractIntegrator):
    """Classical Runge-Kutta with fixed step `dphi` (radians). Fourth order; at most
    `max_steps` steps a ray."""

    tableau: ClassVar[ButcherTableau] = _integrators.RK4
    tol: ClassVar[None] = None
    dphi: float = eqx.field(static=True, default=0.01)
    max_steps: int = eqx.field(static=True, default=20_000)


@final
class DormandPrince(AbstractIntegrator):
    """Adaptive Dormand-Prince 5(4): tolerance `tol` per step on the error relative
    to $|u| + |u'|$, first trial step `dphi` (radians), at most `max_steps` steps
    (rejected ones included) a ray."""

    tableau: ClassVar[ButcherTableau] = _integrators.DOPRI5
    tol: float = eqx.field(static=True, default=1e-10)
    dphi: float = eqx.field(static=True, default=0.05)
    max_steps: int = eqx.field(static=True, default=20_000)


# The accuracy ladder, measured by benchmarks/accuracy_ladder.py (and, for Exact, on
# near-critical rays D = 1.2 ... 1e5 at relative 1e-10 ... 1 from alpha_sh: 4 steps
# give 6e-5, 5 give 1.4e-9, 6 give 3e-14): each entry is the cheapest setting whose
# max error in phi (float64, well-conditioned rays) stayed below the accuracy.
_EXACT_LADDER = ((1e-3, 4), (1e-8, 5), (1e-13, 6))
_RK4_ERR_COEF = 250.0  # max |error| ~ coef * dphi^4 (223 measured, near-critical set)
_DOPRI_ERR_COEF = 5e4  # max |error| ~ coef * tol (4.6e4 measured, near-critical; far camera 0.44)


# With one distance and at least this many rays, "auto" builds a RayMap (two sides of
# ~5,000 knots each at 1e-9: the cost of ~20,000 exact rays) and interpolates.
_TABLE_MIN_RAYS = 50_000


def exact_for(accuracy: float) -> Exact:
    """The cheapest `Exact` setting whose measured error is below `accuracy` (radians)."""
    for acc, n in _EXACT_LADDER:
        if accuracy >= acc:
            return Exact(iterations=n)
    return Exact(iterations=7)


@final
class Table(AbstractMethod):
    """Interpolate a `RayMap` built for the (scalar) distance: cheapest per ray when
    many rays share one camera. `accuracy`: interpolation error, radians."""

    accuracy: float = eqx.field(static=True, default=1e-10)

    def __call__(self, alpha, distance, max_windings):
        from ._raymap import tabulate

        if jnp.ndim(distance) != 0:
            d = jnp.ravel(distance)[0]
            distance = eqx.error_if(
                d, jnp.any(distance != d), "method='table' needs one distance for all rays"
            )
        # Tie the distance to the rays (x * 0.0 is not folded for floats), so that a
        # constant distance does not let XLA fold away the fusion boundary that keeps
        # the knots from being recomputed per ray (see RayMap.build).
        distance = distance + 0.0 * jnp.ravel(alpha)[0]
        # `trace` checked the distance (no second error callback in its program).
        ray_map = tabulate(
            distance, accuracy=self.accuracy, max_windings=max_windings, captured=True,
            **TABLE_SETTINGS,
        )  # fmt: skip
        return ray_map(alpha)


# How the renderer and `trace` build their tables. Duplication steps of R_F at the
# knots: 6 (3e-14 rad) compiled in 3.7 s where 8 took 4.5 s (100,000 rays), the
# accuracy ladder's table errors unchanged to 3 digits. Slopes from differences of the
# knot values (`RayMap.build`'s default), against exact ones: the first `trace` of
# 100,000 rays 1.13 s instead of 1.95 s, a render's table program 0.66 s instead of
# 1.43 s to compile and 1.8 ms instead of 4.4 ms to run.
TABLE_SETTINGS = {"iterations": 6}

_MIN_BUCKET = 1024


def _bucket(n: int) -> int:
    """The padded ray count of an eager call: 2^k or 1.5 * 2^k, at least 1024, so that
    batch sizes share a few compiled programs (at most a third of the rays wasted)."""
    m = _MIN_BUCKET
    while m < n:
        m = m * 3 // 2 if m & (m - 1) == 0 else m * 4 // 3
    return m


@functools.partial(filter_jit_cpu, options=OLDER_CPU_FUSION)
def _compiled(method, alpha, distance, max_windings):
    return method(alpha, distance, max_windings)


# Kept between processes where the CLI keeps its cache (the fit traces arcs' rays).
_compiled = Stored(_compiled, lambda *_: jax.tree.structure(TraceResult(0, 0, 0)))


# Compiled on a thread while the table's program is traced on the main one, which then
# keeps a core (its trace 0.12 s instead of 0.21 s; the look-up compiles in the same
# 0.22 s).
@functools.partial(filter_jit_cpu, options=SIDE_PROGRAM)
def _through_map(ray_map, alpha):
    return ray_map(alpha)


_through_map = Stored(_through_map, lambda *_: jax.tree.structure(TraceResult(0, 0, 0)))

# The kinds of `_through_map` compiled ahead (while their first table was built).
_AHEAD: set = set()


def _table_rays(method: "Table", alpha, distance, max_windings):
    """An eager `Table` trace of padded rays at one distance: the table built by its own
    program (kept for the next call at that distance, see `RayMap.build`), then the
    rays looked up in it. On a first call the look-up's program compiles on a thread
    while the table's compiles and runs."""
    from ._raymap import placeholder, tabulate

    settings = dict(accuracy=method.accuracy, max_windings=float(max_windings),
                    captured=True, **TABLE_SETTINGS)  # fmt: skip
    kind = (method.accuracy, float(max_windings), alpha.shape, alpha.dtype.name)
    ahead = contextlib.nullcontext()
    if kind not in _AHEAD:
        _AHEAD.add(kind)
        # Traced and lowered here, compiled on the thread (two traces on two threads
        # would take turns with the GIL).
        try:
            lowered = _through_map.lower(placeholder(alpha.dtype, **settings), alpha)
            ahead = compile_ahead(lowered.compile)
        except Exception:  # noqa: BLE001 - the call itself reports it
            pass
    with ahead:
        ray_map = tabulate(distance, **settings)  # checked by `trace`
    return _through_map(ray_map, alpha)


def _eager(method, alpha, distance, dtype, max_windings):
    """`method` on concrete rays as one compiled program, not op by op (a table at one
    distance: two, `_table_rays`): the rays are flattened and padded to `_bucket` of
    their count (with a ray that escapes), so every batch size up to the bucket reuses
    the program; the result is cut back. Host arrays are padded on the host (no device
    op to compile); device arrays stay on their device."""
    shape = jnp.broadcast_shapes(jnp.shape(alpha), distance.shape)
    n = math.prod(shape)
    m = _bucket(n)

    def padded(x, fill):
        xp = jnp if isinstance(x, jax.Array) else np
        x = xp.broadcast_to(xp.asarray(x, dtype), shape).ravel()
        return xp.concatenate([x, xp.full(m - n, fill, dtype)]) if m > n else x

    a = padded(alpha, 0.5 * math.pi)
    if isinstance(method, Table) and distance.ndim == 0:
        out = _table_rays(method, a, distance, max_windings)
    else:
        d = distance if distance.ndim == 0 else padded(distance, 10.0)
        out = _compiled(method, a, d, max_windings)
    if m == n:
        return jax.tree.map(lambda x: x.reshape(shape), out)
    if jax.default_backend() == "cpu":
        # Cut on the host (shared memory on CPU): each of the device's slices is a
        # program of its own, compiled on a process's first call (~0.05 s), and so is
        # `jnp.asarray` of each result (~0.02 s): placed with `to_device`.
        return jax.tree.map(lambda x: to_device(np.asarray(x)[:n].reshape(shape)), out)
    return jax.tree.map(lambda x: x[:n].reshape(shape), out)


METHODS = ("auto", "exact", "table", "euler", "rk4", "dopri5")


def _check_number(name: str, value, valid: str, ok) -> None:
    """ValueError (TypeError for a non-number) unless `value` is a finite real number
    for which `ok(value)` holds; `valid` says the range."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise TypeError(f"{name}={_show(value)} must be a real number {valid}")
    if not (math.isfinite(value) and ok(value)):
        raise ValueError(f"{name}={_show(value)} must be finite and {valid}")


def method_for(name: str, accuracy: float) -> AbstractMethod:
    """Resolve a method name and a requested accuracy (radians) into a setting."""
    if name in ("auto", "exact"):
        return exact_for(accuracy)
    if name == "table":
        return Table(accuracy=accuracy)
    if name == "euler":
        return Euler()
    if name == "rk4":
        dphi = min(0.1, (accuracy / _RK4_ERR_COEF) ** 0.25)
        return RK4(dphi=dphi, max_steps=int(math.ceil(200.0 / dphi)))
    if name == "dopri5":
        return DormandPrince(tol=max(accuracy / _DOPRI_ERR_COEF, 1e-14))
    raise ValueError(
        f"method={_show(name)} is not one of {', '.join(map(repr, METHODS))} "
        "(or an AbstractMethod instance)"
    )


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


def _show(value, limit: int = 80) -> str:
    """`value` as an error message shows it: its repr, cut to `limit` characters."""
    if isinstance(value, np.ndarray | np.generic) and value.ndim == 0:
        value = value.item()  # np.float64(2.0) shown as 2.0
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _check_real(name: str, x):
    """`x` if it holds real numbers (a list or tuple as a NumPy array), else a TypeError
    naming `name` and the value (integers are converted; complex, bool, text and
    objects are not)."""
    if isinstance(x, list | tuple):
        try:
            x = np.asarray(x)
        except (TypeError, ValueError):  # ragged
            x = np.asarray(x, dtype=object)
    try:
        kind = np.dtype(x.dtype if hasattr(x, "dtype") else np.asarray(x).dtype)
    except (TypeError, ValueError):
        kind = np.dtype(object)
    if kind.kind not in "iuf":
        raise TypeError(f"{name}={_show(x)} must be real numbers (float or int), got dtype {kind}")
    return x


def _check_dtype(dtype, what: str = "dtype") -> np.dtype:
    """The float dtype rays are computed in, or a TypeError naming `what` (e.g.
    "dtype", or "alpha and distance"): float32 or float64 only."""
    try:
        dt = np.dtype(dtype)
    except TypeError:
        dt = None
    if dt is None or dt.name not in FLOAT_DTYPES:
        shown = dt.name if dt is not None else _show(dtype)
        raise TypeError(
            f"{what}: {shown} is not supported, use float32 or float64 (the geometry "
            "overflows in lower precisions; float64 needs jax_enable_x64)"
        )
    return dt


def _check_distance(distance, dtype=None):
    """ValueError for a concrete bad distance: not finite, <= 1, beyond `MAX_DISTANCE`,
    or > 1 as given but rounded to the horizon in `dtype` (the dtype the rays are traced
    in); eqx.error_if under jit."""
    try:
        d = np.asarray(distance)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        d = None
    if d is not None:
        _check_real("distance", d)
        top = _MAX_COMPARED
        d = d.astype(np.float64)
        bad = ~np.isfinite(d) | ~(d > 1.0)
        if np.any(bad):
            raise ValueError(
                f"distance={_show(d[bad].flat[0])} is not a valid camera radius: it must be "
                + _DISTANCE_RANGE
            )
        if np.any(d > top):
            raise ValueError(
                f"distance={_show(d[d > top].flat[0])} is beyond the largest "
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
    return eqx.error_if(distance, _distance_bad(distance), DISTANCE_MESSAGE)


DISTANCE_MESSAGE = (
    "distance must be finite and > 1 (units of R_S, the horizon is at 1), and at most "
    f"{MAX_DISTANCE:g}"
)


def _distance_bad(distance):
    """Where a traced `distance` is out of range (the predicate of `_check_distance`)."""
    return ~jnp.isfinite(distance) | ~(distance > 1.0) | (distance > _MAX_COMPARED)


_ALPHA_RANGE = "in [0, pi] radians (0 points at the hole, pi straight away)"
# The top of that range as checked: pi rounded to float32 (8.7e-8 above pi), so that a
# float32 pi, widened to float64, is still straight away.
_ALPHA_TOP = float(np.float32(np.pi))


def _bad_alpha(alpha):
    """ValueError for a concrete local angle outside [0, pi] (NaN included); for traced
    ones, the predicate (one comparison a ray) that `trace` puts on its result with
    `eqx.error_if`, so that the rays do not wait for the check. `None` when checked."""
    a = concrete(alpha)
    if a is not None:
        bad = ~((a >= 0) & (a <= _ALPHA_TOP))
        if np.any(bad):
            raise ValueError(
                f"alpha={_show(a[bad].flat[0])} is not a valid local angle: it must be "
                + _ALPHA_RANGE
            )
        return None
    return jnp.any(~((alpha >= 0) & (alpha <= _ALPHA_TOP)))


def trace(
    alpha: ArrayLike,
    distance: ArrayLike,
    *,
    accuracy: float = 1e-6,
    method: str | AbstractMethod = "auto",
    max_windings: float = 10.0,
    throw: bool = False,
) -> TraceResult:
    """Trace rays from a static camera to their escape angle, or to capture.

    **Arguments:**
    - `alpha`: local angle of each ray from the inward radial direction, radians
      in $[0, \\pi]$ (0 points at the hole, $\\pi$ straight away).
    - `distance`: camera radius $1 < D \\le 10^{30}$ (units of R_S, `MAX_DISTANCE`;
      also > 1 after rounding to the rays' dtype). Broadcasts with `alpha`.
    - `accuracy`: target absolute error of `phi` (radians, finite, > 0); picks the cheapest
      setting of the method that met it in the measured ladder. Rays within
      relative $\\delta$ of the critical angle are limited by conditioning to
      about $\\epsilon / \\delta$ whatever the method.
    - `method`: `"auto"` (`"table"` for one distance and >= 50,000 rays, else
      `"exact"`), `"exact"`, `"table"` (one distance for all
      rays: interpolate a `RayMap`), `"euler"`, `"rk4"`, `"dopri5"`, or an
      `AbstractMethod` instance (e.g. `RK4(dphi=0.01)`).
    - `max_windings`: budget of windings (finite, > 0); rays sweeping more than
      $2\\pi \\times$ this are `UNRESOLVED`.
    - `throw`: if True, raise (eagerly, or at run time under `jit`, through
      `eqx.error_if`) with the message of `RayStatus.unresolved` when any ray is
      unresolved. The default keeps the outcome as data in `status`.

    **Returns:** a `TraceResult` (`phi`, `status`, `r_min`, and the properties
    `captured`, `escaped`, `unresolved`, `half_turns`) of the broadcast shape.

    Bad values raise: a `TypeError` for a complex, boolean or text `alpha` or
    `distance`, a lower precision than float32, or a `method` that is not a name or
    an `AbstractMethod`; a `ValueError` naming the value for one out of range, eagerly,
    and under `jit` at run time (`eqx.error_if`: one comparison a ray for `alpha`).

    Works under `jit`, `vmap` and `grad` (both modes) for escaping rays, in
    float32 and float64 (the dtype of the inputs; float64 needs
    `jax_enable_x64`). Called eagerly, it runs as one compiled program, kept for
    later calls with the same method and dtype and a ray count in the same bucket
    (counts are padded to 2^k or 1.5 x 2^k, at least 1024); the table method at one
    distance as two, the table's and the look-up's, and the tables of the last 16
    distances are kept for the next call at one of them.
    """
    _check_number("accuracy", accuracy, "> 0 (radians)", lambda v: v > 0)
    _check_number("max_windings", max_windings, "> 0 (turns)", lambda v: v > 0)
    if not isinstance(method, str | AbstractMethod):
        raise TypeError(
            f"method={_show(method)} must be one of {', '.join(map(repr, METHODS))} or an "
            "AbstractMethod instance (e.g. jl.RK4(dphi=0.01))"
        )
    alpha = _check_real("alpha", alpha)
    distance = _check_real("distance", distance)
    dtype = _check_dtype(jnp.result_type(float, alpha, distance), "dtype of alpha and distance")
    distance = _check_distance(distance, dtype)
    bad_alpha = _bad_alpha(alpha)
    traced = tracing() or has_tracer(alpha, distance)
    # Host distances stay on the host (padded there by `_eager`, nothing compiled).
    distance = (jnp if isinstance(distance, jax.Array) else np).asarray(distance, dtype)
    if isinstance(method, str):
        if method == "auto" and distance.ndim == 0 and np.size(alpha) >= _TABLE_MIN_RAYS:
            method = "table"  # many rays, one camera: tabulate once, interpolate
        method = method_for(method, accuracy)
    if traced:  # part of the caller's program
        result = method(jnp.asarray(alpha, dtype), distance, max_windings)
    else:  # host rays are padded on the host, not copied to the device first
        result = _eager(method, alpha, distance, dtype, max_windings)
    if bad_alpha is not None:
        phi = eqx.error_if(result.phi, bad_alpha, "alpha must be " + _ALPHA_RANGE)
        result = eqx.tree_at(lambda r: r.phi, result, phi)
    if throw:
        phi = RayStatus.unresolved.error_if(result.phi, jnp.any(result.unresolved))
        result = eqx.tree_at(lambda r: r.phi, result, phi)
    return result
