"""`trace`: camera rays -> escape angle and capture, the single source of truth for Phi."""

import abc
import math
from typing import ClassVar, final

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from . import _exact, _integrators
from ._compile import ahead, program
from ._integrators import ButcherTableau, integrate, rk_step
from ._messages import shown
from ._orbit import acceleration
from ._ray_inputs import (
    ALPHA_RANGE,
    bad_alpha,
    check_distance,
    check_dtype,
    check_real,
)
from ._raymap import placeholder, tabulate
from ._status import CAPTURED, ESCAPED, UNRESOLVED, RayStatus, TraceResult
from ._units import angle, length
from ._util import has_tracer, to_device, tracing

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

    def __call__(self, alpha, distance, max_windings, check=None):
        """As `AbstractMethod.__call__`; `check`: `None`, or a zero scalar that carries
        the caller's run-time checks (`eqx.error_if`), tied to the shadow angle, so that
        every ray depends on it at no extra pass over the rays."""
        if jnp.ndim(distance) != 0:
            d = jnp.ravel(distance)[0]
            distance = eqx.error_if(
                d, jnp.any(distance != d), "method='table' needs one distance for all rays"
            )
        # `trace` checked the distance (no second error callback in its program). A
        # distance known when the program is traced gets its table built once and kept
        # (`tabulate`); a traced one, its table built in the program.
        ray_map = tabulate(
            distance, accuracy=self.accuracy, max_windings=max_windings, captured=True,
            **TABLE_SETTINGS,
        )  # fmt: skip
        if check is not None:
            ray_map = eqx.tree_at(lambda m: m.alpha_sh, ray_map, ray_map.alpha_sh + check)
        return ray_map(alpha)


# How the renderer and `trace` build their tables: 6 duplication steps of R_F at the
# knots (3e-14 rad; more compile longer, the accuracy ladder's table errors unchanged
# to 3 digits), slopes from differences of the knot values (`RayMap.build`'s default;
# exact ones compile and run about twice as long).
TABLE_SETTINGS = {"iterations": 6}

_MIN_BUCKET = 1024


def _bucket(n: int) -> int:
    """The padded ray count of an eager call: 2^k or 1.5 * 2^k, at least 1024, so that
    batch sizes share a few compiled programs (at most a third of the rays wasted)."""
    m = _MIN_BUCKET
    while m < n:
        m = m * 3 // 2 if m & (m - 1) == 0 else m * 4 // 3
    return m


@program(profile="legacy_fusion_o1")
def _compiled(method, alpha, distance, max_windings):
    return method(alpha, distance, max_windings)


@program(profile="xla")
def _through_map(ray_map, alpha):
    return ray_map(alpha)


def _table_rays(method: "Table", alpha, distance, max_windings):
    """An eager `Table` trace of padded rays at one distance, driven from the host: the
    table built by its own program (kept for the next call at that distance, see
    `RayMap.build`), then the rays looked up in it. On a first call the look-up's
    program compiles on the second core while the table's compiles and runs."""
    settings = dict(accuracy=method.accuracy, max_windings=float(max_windings),
                    captured=True, **TABLE_SETTINGS)  # fmt: skip
    with ahead((_through_map, placeholder(alpha.dtype, **settings), alpha)):
        ray_map = tabulate(distance, **settings)  # checked by `trace`
    return _through_map(ray_map, alpha)


def _aligned(m: int, dtype) -> np.ndarray:
    """An uninitialised host array of `m` values whose data starts on a 64-byte
    boundary: the CPU device adopts such an array without copying it."""
    item = np.dtype(dtype).itemsize
    buf = np.empty(m + 64 // item, dtype)
    start = (-buf.ctypes.data % 64) // item
    return buf[start : start + m]


def _eager(method, alpha, distance, dtype, max_windings):
    """`method` on concrete rays as one compiled program, not op by op (a table at one
    distance: two, `_table_rays`): the rays are flattened and padded to `_bucket` of
    their count (with a ray that escapes), so every batch size up to the bucket reuses
    the program; the result is cut back. Host arrays (and, on CPU, device arrays, which
    are host memory there) are padded on the host into an aligned buffer that the
    device adopts without a copy (no device op to compile); device arrays elsewhere are
    padded on their device."""
    shape = jnp.broadcast_shapes(jnp.shape(alpha), distance.shape)
    n = math.prod(shape)
    m = _bucket(n)

    host = jax.default_backend() == "cpu"  # device arrays are host memory there

    def padded(x, fill):
        if isinstance(x, jax.Array) and not host:
            x = jnp.broadcast_to(x.astype(dtype), shape).ravel()
            return jnp.concatenate([x, jnp.full(m - n, fill, dtype)]) if m > n else x
        x = np.asarray(x, dtype)
        if m == n and x.shape == shape:
            out = x.ravel()  # adopted without a copy where it is aligned
        else:
            out = _aligned(m, dtype)
            np.copyto(out[:n].reshape(shape), x)
            out[n:] = fill
        # Placed here, not by the program's call, which would copy a host array.
        return to_device(out)

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
        # program of its own, compiled on a process's first call, and so is
        # `jnp.asarray` of each result: placed with `to_device`.
        return jax.tree.map(lambda x: to_device(np.asarray(x)[:n].reshape(shape)), out)
    return jax.tree.map(lambda x: x[:n].reshape(shape), out)


METHODS = ("auto", "exact", "table", "euler", "rk4", "dopri5")


def _check_number(name: str, value, valid: str, ok) -> None:
    """ValueError (TypeError for a non-number) unless `value` is a finite real number
    for which `ok(value)` holds; `valid` says the range."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise TypeError(f"{name}={shown(value)} must be a real number {valid}")
    if not (math.isfinite(value) and ok(value)):
        raise ValueError(f"{name}={shown(value)} must be finite and {valid}")


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
        f"method={shown(name)} is not one of {', '.join(map(repr, METHODS))} "
        "(or an AbstractMethod instance)"
    )


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
      in $[0, \\pi]$ (0 points at the hole, $\\pi$ straight away), or an astropy
      angle Quantity (converted before the trace).
    - `distance`: camera radius $1 < D \\le 10^{30}$ (units of R_S, `MAX_DISTANCE`;
      also > 1 after rounding to the rays' dtype). Broadcasts with `alpha`. A
      dimensionless astropy Quantity is read as R_S; a length in metres, km, ... is
      refused (`jaxlens.schwarzschild_radii` converts it with the hole's mass).
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
    distances are kept for the next call at one of them. Under `jit`, a distance known
    when the program is traced (a number, not a traced argument) gets its table built
    then, once (and kept with those), as a constant of the program; a traced distance
    has its table built inside the program, on every call. Asking for `phi` alone
    under `jit` skips the rest (`benchmarks/results/floor.md` gives the costs).
    """
    accuracy = angle(accuracy, "accuracy")
    _check_number("accuracy", accuracy, "> 0 (radians)", lambda v: v > 0)
    _check_number("max_windings", max_windings, "> 0 (turns)", lambda v: v > 0)
    if not isinstance(method, str | AbstractMethod):
        raise TypeError(
            f"method={shown(method)} must be one of {', '.join(map(repr, METHODS))} or an "
            "AbstractMethod instance (e.g. jl.RK4(dphi=0.01))"
        )
    alpha = check_real("alpha", angle(alpha, "alpha"))
    distance = check_real("distance", length(distance, "distance"))
    dtype = check_dtype(jnp.result_type(float, alpha, distance), "dtype of alpha and distance")
    distance = check_distance(distance, dtype)
    alpha_bad = bad_alpha(alpha)
    traced = tracing() or has_tracer(alpha, distance)
    # Host distances stay on the host (padded there by `_eager`, nothing compiled).
    distance = (jnp if isinstance(distance, jax.Array) else np).asarray(distance, dtype)
    if isinstance(method, str):
        if method == "auto" and distance.ndim == 0 and np.size(alpha) >= _TABLE_MIN_RAYS:
            method = "table"  # many rays, one camera: tabulate once, interpolate
        method = method_for(method, accuracy)
    if traced:  # part of the caller's program
        alpha = jnp.asarray(alpha, dtype)
        if alpha_bad is None:
            result = method(alpha, distance, max_windings)
        else:
            # Raised through a zero the rays depend on (`error_if` on a result would
            # copy it and split the passes that share it): the table's shadow angle
            # takes it, other methods the rays (the addition joins their first pass).
            message = "alpha must be " + ALPHA_RANGE
            check = eqx.error_if(jnp.zeros((), dtype), alpha_bad, message)
            if isinstance(method, Table):
                result = method(alpha, distance, max_windings, check=check)
            else:
                result = method(alpha + check, distance, max_windings)
    else:  # host rays are padded on the host, not copied to the device first
        result = _eager(method, alpha, distance, dtype, max_windings)
    if throw:
        unresolved = jnp.any(result.unresolved)
        phi = result.phi + RayStatus.unresolved.error_if(jnp.zeros((), dtype), unresolved)
        result = eqx.tree_at(lambda r: r.phi, result, phi)
    return result
