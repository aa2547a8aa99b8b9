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
from ._programs import Stored
from ._status import CAPTURED, ESCAPED, UNRESOLVED, RayStatus
from ._util import (
    OLDER_CPU_FUSION,
    SIDE_PROGRAM,
    compile_ahead,
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
        from ._raymap import RayMap

        if jnp.ndim(distance) != 0:
            d = jnp.ravel(distance)[0]
            distance = eqx.error_if(
                d, jnp.any(distance != d), "method='table' needs one distance for all rays"
            )
        # Tie the distance to the rays (x * 0.0 is not folded for floats), so that a
        # constant distance does not let XLA fold away the fusion boundary that keeps
        # the knots from being recomputed per ray (see RayMap.build).
        distance = distance + 0.0 * jnp.ravel(alpha)[0]
        ray_map = RayMap.build(
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
    from ._raymap import RayMap, placeholder

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
        ray_map = RayMap.build(distance, **settings)
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
        f"method={name!r} is not one of 'auto', 'exact', 'table', 'euler', 'rk4', 'dopri5' "
        "(or an AbstractMethod instance)"
    )


def _check_distance(distance, dtype=None):
    """ValueError for a concrete bad distance, also one that is > 1 as given but rounds
    to the horizon in `dtype` (the dtype the rays are traced in); eqx.error_if under
    jit."""
    try:
        d = np.asarray(distance)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        d = None
    if d is not None:
        bad = ~np.isfinite(d) | ~(d > 1.0)
        if np.any(bad):
            value = d[bad].flat[0]
            raise ValueError(
                f"distance={value!r} is not a valid camera radius: it must be "
                "finite and > 1 (units of R_S, the horizon is at 1)"
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
    return eqx.error_if(
        distance,
        ~jnp.isfinite(distance) | ~(distance > 1.0),
        "distance must be finite and > 1 (units of R_S, the horizon is at 1)",
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
      in $[0, \\pi]$ (0 points at the hole, $\\pi$ straight away).
    - `distance`: camera radius $D > 1$ (units of R_S). Broadcasts with `alpha`.
    - `accuracy`: target absolute error of `phi` (radians); picks the cheapest
      setting of the method that met it in the measured ladder. Rays within
      relative $\\delta$ of the critical angle are limited by conditioning to
      about $\\epsilon / \\delta$ whatever the method.
    - `method`: `"auto"` (`"table"` for one distance and >= 50,000 rays, else
      `"exact"`), `"exact"`, `"table"` (one distance for all
      rays: interpolate a `RayMap`), `"euler"`, `"rk4"`, `"dopri5"`, or an
      `AbstractMethod` instance (e.g. `RK4(dphi=0.01)`).
    - `max_windings`: budget of windings; rays sweeping more than
      $2\\pi \\times$ this are `UNRESOLVED`.
    - `throw`: if True, raise (eagerly, or at run time under `jit`, through
      `eqx.error_if`) with the message of `RayStatus.unresolved` when any ray is
      unresolved. The default keeps the outcome as data in `status`.

    **Returns:** a `TraceResult` (`phi`, `status`, `r_min`, and the properties
    `captured`, `escaped`, `unresolved`, `half_turns`) of the broadcast shape.

    Works under `jit`, `vmap` and `grad` (both modes) for escaping rays, in
    float32 and float64 (the dtype of the inputs; float64 needs
    `jax_enable_x64`). Called eagerly, it runs as one compiled program, kept for
    later calls with the same method and dtype and a ray count in the same bucket
    (counts are padded to 2^k or 1.5 x 2^k, at least 1024); the table method at one
    distance as two, the table's and the look-up's, and the tables of the last 16
    distances are kept for the next call at one of them.
    """
    if not (accuracy > 0):
        raise ValueError(f"accuracy={accuracy!r} must be > 0 (radians)")
    if not max_windings > 0:
        raise ValueError(f"max_windings={max_windings!r} must be > 0")
    for name, x in (("alpha", alpha), ("distance", distance)):
        kind = np.dtype(x.dtype if hasattr(x, "dtype") else np.asarray(x).dtype)
        if kind.kind not in "iuf":  # integers are converted; complex, bool, text are not
            raise TypeError(f"{name} must be real numbers, got dtype {kind}")
    dtype = jnp.result_type(float, alpha, distance)
    distance = _check_distance(distance, dtype)
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
    if throw:
        phi = RayStatus.unresolved.error_if(result.phi, jnp.any(result.unresolved))
        result = eqx.tree_at(lambda r: r.phi, result, phi)
    return result
