"""The one-dimensional ray map of a static camera: Phi(alpha) tabulated once per distance.

For a static camera the escape angle depends on the local angle alpha alone, so an
image needs Phi on the alphas it contains, not one orbit per pixel. The table is
uniform in $\\tau = \\ln(\\alpha - \\alpha_{sh})$: near the shadow edge Phi grows like
$-\\tau$ (the strong-deflection logarithm), so it is smooth and nearly linear in
$\\tau$, and cubic Hermite interpolation with exact slopes (forward-mode autodiff of
the closed form) reaches $10^{-10}$ rad with a few thousand knots. Below the first
knot the logarithmic law is extrapolated linearly in $\\tau$.

One type serves every consumer: the renderer interpolates it (`escape_angle`, in
float32 through `astype`), `trace(method="table")` calls it, point images solve the
lens equation on it (`solve`), and the fit differentiates it with respect to $D$.
"""

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from . import _exact, _fastmath
from ._compile import program
from ._messages import shown
from ._ray_inputs import check_distance, check_dtype, check_real
from ._status import CAPTURED, ESCAPED, UNRESOLVED, TraceResult
from ._units import angle, length
from ._util import concrete, fusion_barrier, is_concrete, run_now

# Interpolation error of a cubic Hermite spline: h^4 / 384 max|phi''''(tau)|, and
# |phi''''| <= ~pi on the escaping branch (measured by tests/test_raymap.py).
_HERMITE_C = math.pi / 384.0
# Slopes from fourth-order differences of the knot values raise the largest error by up
# to 15 % at equal knots (measured from D = 1.2 to 1e12), and the render benchmark's
# largest sky-direction error by 11 %: 7.8 % more knots make up for both.
_DIFFERENCE_C = 1.35 * _HERMITE_C
_REL_START = 1e-13  # first knot at alpha_sh * (1 + 1e-13): beyond float64 conditioning
_NEWTON = 3  # Newton steps of `solve` on a knot interval's cubic (~1e-6 -> 1e-11 -> 0)


def knots_for(accuracy: float, span: float, exact_slopes: bool = False) -> int:
    """Number of knots for a target interpolation error `accuracy` (radians) over a
    $\\tau$-span `span`, with a safety factor of 10 on the error model, for difference
    or (`exact_slopes=True`) exact slopes."""
    c = _HERMITE_C if exact_slopes else _DIFFERENCE_C
    h = (accuracy / (10.0 * c)) ** 0.25
    return int(min(max(math.ceil(span / h) + 1, 64), 200_000))


def default_knots(accuracy: float, exact_slopes: bool = False) -> int:
    """Knots of `RayMap.build` without `knots`: for `accuracy` over the widest
    $\\tau$-span of any distance (at most ~ln(pi / (alpha_sh 1e-13)), alpha_sh >= b_c/D)."""
    return knots_for(accuracy, 30.0 + 2.0 * math.log(10.0) + 25.0, exact_slopes)


class RayMap(eqx.Module):
    """Escape angle as a function of alpha for one static camera distance.

    Build it with `RayMap.build(distance)`; call it on any array of alphas. It is a
    pytree of arrays, so it can be built inside `jit` and differentiated with respect
    to the distance (gradients flow through the knots and the shadow angle).

    **Fields:** `distance` (units of R_S), `alpha_sh` (shadow angle, radians), the
    knots `tau` ($\\tau_i = \\ln(\\alpha_i - \\alpha_{sh})$, uniform with step `dtau`),
    and the knot values `phi` (radians) and `slope` ($d\\phi/d\\tau$). The knots are
    stored, not recomputed from the first one, so a float32 copy (`astype`) takes each
    interval's position against its own knot and keeps the table's accuracy.
    """

    distance: Float[Array, ""]
    alpha_sh: Float[Array, ""]
    tau: Float[Array, " n"]
    dtau: Float[Array, ""]
    phi: Float[Array, " n"]
    slope: Float[Array, " n"]
    inner: tuple | None = None  # (tau, dtau, phi, slope) of the captured side, if built
    periapsis: tuple | None = None  # (u_min, slope) on the escaping knots, if built
    max_windings: float = eqx.field(static=True, default=10.0)

    @classmethod
    def build(
        cls,
        distance: ArrayLike,
        *,
        accuracy: float = 1e-10,
        knots: int | None = None,
        max_windings: float = 10.0,
        captured: bool = False,
        alpha_max: float = math.pi,
        exact_slopes: bool = False,
        iterations: int = 8,
        radius: ArrayLike | None = None,
    ) -> "RayMap":
        """Tabulate Phi(alpha) for a camera at `distance` (units of R_S, scalar).

        **Arguments:**
        - `distance`: camera radius $D > 1$ (units of R_S, or a dimensionless astropy
          Quantity; a length in metres, km, ... is refused: `schwarzschild_radii`).
        - `accuracy`: target interpolation error of phi (radians); sets the number
          of knots unless `knots` is given.
        - `max_windings`: rays sweeping more than $2\\pi\\times$ this are unresolved.
        - `captured`: also tabulate the captured side (the azimuth at which a
          captured ray crosses the horizon), as `trace` reports it.
        - `alpha_max`: the largest local angle tabulated (radians; $\\pi$: every ray; a
          pinhole camera sees no ray beyond $\\pi/2$). Beyond it the table is not
          meaningful.
        - `exact_slopes`: knot slopes by fourth-order differences of the knot values
          (the default; 7.8 % more knots keep the largest error at or below that of
          exact slopes), or (`True`) by forward-mode autodiff of the closed form. The
          differences compile in half the time and run in less than half, and their
          derivative with respect to the distance needs only first derivatives of the
          closed form: a program that differentiates the table (a fit) compiles
          several times faster.
        - `iterations`: duplication steps of Carlson's $R_F$ in the closed form at the
          knots (8: round-off; 6: 3e-14 rad, `trace`'s ladder).
        - `radius`: `None` (the escape angle), or the radius $R$ of a sphere beyond the
          camera ($R > D$, units of R_S, scalar): the knot values are then the azimuth
          at which each escaping ray crosses $r = R$ (`finite_crossings`; once, after
          its periapsis), as smooth in $\\tau$ as the escape angle. The sky on a sphere
          (`Scene.source_distance`) reads it in place of the escape angle.

        Called with a concrete distance outside a transformation (not under `jit`,
        `grad`, `vmap`), it runs one compiled program a setting and keeps the tables of
        the last 16 distances: a later call with one of them returns the same table.

        A distance that `trace` refuses (not finite, $\\le 1$ or beyond
        `MAX_DISTANCE` = 1e30, complex, float16) is refused here by the same check:
        a `ValueError`/`TypeError` eagerly, an `eqx.error_if` error at run time under
        `jit`.
        """
        distance = check_real("distance", length(distance, "distance"))
        dtype = check_dtype(jnp.result_type(float, distance), "dtype of distance")
        distance = check_distance(distance, dtype)
        if radius is not None:
            radius = check_real("radius", length(radius, "radius"))
            r, d = concrete(radius), concrete(distance)
            if r is not None and d is not None and not np.all(np.asarray(r) > d):
                raise ValueError(f"radius={shown(np.asarray(r))} must be > distance = "
                                 f"{shown(np.asarray(d))} (units of R_S): the table holds "
                                 "the one crossing of a sphere beyond the camera")  # fmt: skip
        return tabulate(
            distance, accuracy=accuracy, knots=knots, max_windings=max_windings,
            captured=captured, alpha_max=alpha_max, exact_slopes=exact_slopes,
            iterations=iterations, cls=cls, radius=radius,
        )  # fmt: skip

    def escape_angle(self, alpha: ArrayLike) -> Float[Array, "..."]:
        """Interpolated escape angle (radians) at `alpha`; meaningful where
        `alpha > alpha_sh` (escaping rays), finite everywhere; `alpha` in radians or an
        astropy angle Quantity."""
        alpha = jnp.asarray(angle(alpha, "alpha"), self.phi.dtype)
        return _look_up(alpha, self.alpha_sh, (self._outer(),))[0]

    def _outer(self) -> tuple:
        return (self.tau, self.dtau, self.phi, self.slope)

    def astype(self, dtype) -> "RayMap":
        """The same table in `dtype` (e.g. float32 for a float32 render of a table built
        in float64); the knots keep their own positions, so interpolation error stays
        the table's own plus the dtype's rounding of alpha."""
        return jax.tree.map(lambda a: a.astype(dtype) if eqx.is_inexact_array(a) else a, self)

    def solve(self, target: ArrayLike, *, with_slope: bool = False):
        """The local angle $\\alpha > \\alpha_{sh}$ (radians) at which the escape angle
        equals `target` (radians, > 0, any shape): the lens equation on the table.

        $\\Phi$ falls monotonically along the knots, so a search finds the knot
        interval (on values held constant), and Newton steps on that interval's cubic
        converge from the linear guess (the cubic is nearly linear in $\\tau$: the guess
        is within ~1e-6, three steps reach round-off). The steps are differentiable in
        the knot values, so the result carries the derivative of the implicit function
        with respect to `target` and the table (hence the distance): works under `jit`,
        `vmap`, `grad` and `jacfwd`.

        **Returns:** $\\alpha$ (radians, the shape of `target`); with `with_slope`, also
        $d\\Phi/d\\alpha$ there (per radian).
        """
        target = jnp.asarray(target, self.phi.dtype)
        t0 = jax.lax.stop_gradient(target)
        fixed = jax.lax.stop_gradient(self.phi)
        n = fixed.shape[0]
        # phi[i] >= target > phi[i + 1] (few targets, e.g. a fit's rings: one vector
        # compare; many: a log n search)
        if t0.size <= 64:
            count = jnp.sum(fixed >= t0[..., None], axis=-1)
        else:
            count = jnp.searchsorted(-fixed, -t0, side="right")
        i = jnp.clip(count - 1, 0, n - 2)
        dtau = self.dtau
        p0, p1 = self.phi[i], self.phi[i + 1]
        m0, m1 = self.slope[i] * dtau, self.slope[i + 1] * dtau

        def cubic_slope(t):  # d/dt of the interval's Hermite cubic
            t2 = t * t
            d = (6.0 * t2 - 6.0 * t) * (p0 - p1) + (3.0 * t2 - 4.0 * t + 1.0) * m0
            return d + (3.0 * t2 - 2.0 * t) * m1

        t = jax.lax.stop_gradient(jnp.clip((p0 - t0) / (p0 - p1), 0.0, 1.0))
        for _ in range(_NEWTON):
            t = t - (hermite(t, p0, p1, m0, m1) - target) / cubic_slope(t)
        tau = self.tau[0] + (i + t) * dtau
        # Beyond the first knot: the log law, linear in tau.
        beyond = t0 > fixed[0]
        tau = jnp.where(beyond, self.tau[0] + (target - self.phi[0]) / self.slope[0], tau)
        gap = jnp.exp(tau)
        alpha = self.alpha_sh + gap
        if not with_slope:
            return alpha
        slope = jnp.where(beyond, self.slope[0], cubic_slope(t) / dtau) / gap
        return alpha, slope

    def horizon_angle(self, alpha: ArrayLike) -> Float[Array, "..."]:
        """Interpolated azimuth (radians) at which a captured ray ($\\alpha < \\alpha_{sh}$)
        crosses the horizon; needs `build(..., captured=True)`."""
        if self.inner is None:
            raise ValueError("this RayMap was built without captured=True")
        alpha = jnp.asarray(angle(alpha, "alpha"), self.phi.dtype)
        return _look_up(alpha, self.alpha_sh, (self.inner,), sign=-1.0)[0]

    def __call__(self, alpha: ArrayLike):
        """Trace rays at local angles `alpha` (radians, or an astropy angle Quantity)
        through the table.

        **Returns:** a `TraceResult`; `r_min` is the closed-form periapsis.
        """
        alpha = jnp.asarray(angle(alpha, "alpha"), self.phi.dtype)
        gap = alpha - self.alpha_sh
        escaped = gap > 0
        # Both sides, and the periapsis of the escaping one, from one logarithm and one
        # knot index a ray (on CPU a pass of their own, then one pass an output).
        sides = (self._outer(),) + ((self.inner,) if self.inner is not None else ())
        phi, u = _look_up(alpha, self.alpha_sh, sides, self.periapsis)
        if self.inner is None:
            phi = jnp.where(escaped, phi, 0.0)
        cap = 2.0 * jnp.pi * self.max_windings
        phi = jnp.where((gap == 0) | ~(phi < cap), cap, phi)
        # The status from the finished phi (read back, not recomputed with it: XLA
        # fuses no value into two consumers on CPU, it writes it out between them).
        status = jnp.where(phi == cap, UNRESOLVED, jnp.where(escaped, ESCAPED, CAPTURED))
        turning = escaped & (alpha <= _inward_limit(alpha.dtype))
        if u is not None:
            r0 = 1.0 / jnp.where(turning, u, 1.0)
        else:
            b = _exact.impact_parameter(alpha, self.distance)
            r0 = _exact.periapsis(jnp.where(turning, b, 2.0 * _exact.B_CRIT))
        r_min = jnp.where(turning, r0, jnp.where(escaped, self.distance, 1.0))
        return TraceResult(phi, status.astype(jnp.int8), r_min.astype(phi.dtype))


@functools.cache
def _inward_limit(dtype) -> np.ndarray:
    """The largest angle of `dtype` below $\\pi/2$: a ray at $\\alpha$ heads inward
    ($\\cos\\alpha > 0$, it has a periapsis) exactly when $\\alpha$ is at most this."""
    half = np.asarray(math.pi / 2, dtype)
    return half if float(half) < math.pi / 2 else np.nextafter(half, np.asarray(0, dtype))


def tabulate(
    distance,
    *,
    accuracy: float = 1e-10,
    knots: int | None = None,
    max_windings: float = 10.0,
    captured: bool = False,
    alpha_max: float = math.pi,
    exact_slopes: bool = False,
    iterations: int = 8,
    cls=RayMap,
    radius=None,
) -> RayMap:
    """`RayMap.build` without its check of the distance: for callers that checked it
    already (`trace`, the renderer, the fit), so that their compiled programs hold no
    second error callback (a program with one is not kept by the persistent cache).
    `radius`: as `RayMap.build`'s (the caller has checked $R > D$)."""
    dtype = jnp.result_type(float, distance)
    concrete_d = is_concrete((distance, radius))
    # A concrete distance stays on the host (`jnp.asarray` would compile a program).
    d = np.asarray(distance, dtype) if concrete_d else jnp.asarray(distance, dtype)
    if d.ndim != 0:
        raise ValueError(f"RayMap.build needs a scalar distance, got shape {d.shape}")
    r = None
    if radius is not None:
        r = np.asarray(radius, dtype) if concrete_d else jnp.asarray(radius, dtype)
        if r.ndim != 0:
            raise ValueError(f"RayMap.build needs a scalar radius, got shape {r.shape}")
        if captured:
            raise ValueError("RayMap.build(radius=...) tabulates the escaping rays only: "
                             "captured=True is not supported with a radius")  # fmt: skip
    settings = _settings(accuracy, knots, max_windings, captured, alpha_max,
                         exact_slopes, iterations)  # fmt: skip
    if not concrete_d:  # part of the caller's program
        return _tabulated(cls, d, r, **settings)
    # A concrete distance: one compiled program a setting, reused for every distance
    # (not op by op), and the table of each of the last few distances kept for the next
    # build. Inside a caller's trace (a distance fixed in its program) the table is
    # built the same way, now, and is a constant of that program: not rebuilt on each
    # of its calls.
    with run_now():  # inside a caller's trace, not staged into it
        return _tabulated_recent(cls, d.dtype.name, d.item(), tuple(settings.items()),
                                 None if r is None else r.item())  # fmt: skip


def _tabulated(cls, d, r, *, knots, max_windings, captured, alpha_max, exact_slopes,
               iterations):  # fmt: skip
    """The body of `RayMap.build` for a float array `d` (and `r`, the sphere's radius,
    or `None`), the settings resolved."""
    alpha_sh = _exact.shadow_angle(d)
    # Both sides of the shadow edge in one evaluation of the closed form (one copy of
    # it in the program: compiling it dominates a first call).
    spans = [(alpha_max - alpha_sh, 1.0)] + ([(alpha_sh, -1.0)] if captured else [])
    sides = _tabulate(d, alpha_sh, spans, n=knots, exact_slopes=exact_slopes,
                      iterations=iterations, radius=r)  # fmt: skip
    outer = sides[0]
    inner = sides[1] if captured else None
    peri = None
    if captured:  # trace()'s full result: also 1/r_min of the escaping side
        gap = jnp.exp(outer[0])

        def u_min(a):  # periapsis u_2(b(alpha)), smooth through alpha = pi/2
            s = _exact.B_CRIT / _exact.impact_parameter(a, d)
            return _exact.real_roots(s, (1.0 - s) * (1.0 + s))[1]

        peri = jax.jvp(u_min, (alpha_sh + gap,), (gap,))
    # Materialise the knots: otherwise XLA recomputes the closed form for every ray.
    outer, inner, peri = fusion_barrier((outer, inner, peri), d)
    return cls(d, alpha_sh, *outer, inner, peri, max_windings)


def _settings(
    accuracy=1e-10,
    knots=None,
    max_windings=10.0,
    captured=False,
    alpha_max=math.pi,
    exact_slopes=False,
    iterations=8,
) -> dict:
    """`RayMap.build`'s keyword arguments checked, the number of knots resolved."""
    if knots is None:
        knots = default_knots(accuracy, exact_slopes)
    if not 0.0 < alpha_max <= math.pi:
        raise ValueError(f"alpha_max={alpha_max!r} must be in (0, pi] radians")
    return dict(knots=int(knots), max_windings=float(max_windings), captured=captured,
                alpha_max=float(alpha_max), exact_slopes=exact_slopes,
                iterations=int(iterations))  # fmt: skip


# The closed form on a few thousand knots, once a distance: compiled without LLVM's
# optimisations (the table's errors unchanged).
@program(profile="legacy_fusion_o0_side")
def _tabulated_compiled(cls, d, r, settings: dict):
    return _tabulated(cls, d, r, **settings)


@functools.lru_cache(maxsize=16)
def _tabulated_recent(cls, dtype: str, distance: float, settings: tuple, radius=None):
    """The tables of the last distances (and radii) built eagerly (a few thousand knots
    each): the next `trace` at the same camera distance reuses its table."""
    r = None if radius is None else np.asarray(radius, dtype)
    return _tabulated_compiled(cls, np.asarray(distance, dtype), r, dict(settings))


def _structure(cls, settings: dict):
    """The pytree structure of a built table, known without tracing it."""
    sides = {"inner": (0.0,) * 4, "periapsis": (0.0,) * 2} if settings["captured"] else {}
    return jax.tree.structure(cls(*(0.0,) * 6, **sides, max_windings=settings["max_windings"]))


def placeholder(dtype, lead: tuple = (), **options) -> "RayMap":
    """Zeros shaped as the table `RayMap.build(distance, **options)` makes in `dtype`,
    with leading axes `lead`: for compiling a program that reads a table before the
    table is built."""
    settings = _settings(**options)
    n = settings["knots"]
    shapes = [(), (), (n,), (), (n,), (n,)]
    if settings["captured"]:
        shapes += [(n,), (), (n,), (n,), (n,), (n,)]
    leaves = [np.zeros(lead + s, dtype) for s in shapes]
    return jax.tree.unflatten(_structure(RayMap, settings), leaves)


def _tabulate(d, alpha_sh, spans, *, n, exact_slopes, iterations, radius=None):
    """`(knots, dtau, phi, slope)` of each side `(span, sign)` of the shadow edge, the
    closed form evaluated once on all sides' knots together."""
    # Knots uniform in tau = ln|alpha - alpha_sh| from 1e-13 alpha_sh to `span` (the
    # last knot a hair short, where |sin(alpha)| has its kink at alpha = 0 or pi).
    floor = 1e-300 if d.dtype == jnp.float64 else 1e-37
    tau_lo = jnp.log(jnp.maximum(alpha_sh * _REL_START, floor))
    steps = jnp.arange(n, dtype=d.dtype)
    knots, dtaus, alphas, tangents = [], [], [], []
    for span, sign in spans:
        tau_hi = jnp.log(jnp.maximum(span, jnp.finfo(d.dtype).tiny)) - 1e-13
        dtau = (tau_hi - tau_lo) / (n - 1)
        # Counted down from the top: tau_lo + dtau * k loses ~ulp(|tau_lo|) ~ 2e-6 (float32)
        # to rounding near the top (tau ~ 0) unless the machine fuses it into one
        # multiply-add, and a knot position that is off by that moves the look-up.
        tau = tau_hi - dtau * steps[::-1]
        gap = jnp.exp(tau)
        knots.append(tau)
        dtaus.append(dtau)
        alphas.append(alpha_sh + sign * gap)
        tangents.append(sign * gap)
    alpha = jnp.concatenate(alphas)
    # Not folded at compile time where the distance is a constant of the caller's
    # program (a closure's, a static argument): JAX 0.8's XLA folded the closed form to
    # 1.8e-3 rad off at D = 5 (JAX 0.10's: 4e-13, as computed at run time).
    alpha, d = jax.lax.optimization_barrier((alpha, d))

    def phi_of_alpha(a):
        if radius is not None:  # the one crossing of a sphere beyond the camera
            return _exact.finite_crossings(a, d, radius, iterations=iterations,
                                           max_windings=1e6).first  # fmt: skip
        return _exact.escape_angle(a, d, iterations=iterations, max_windings=1e6)[0]

    if exact_slopes:
        # d phi / d tau = (d phi / d alpha) d alpha / d tau: one forward-mode pass.
        phi, slope = jax.jvp(phi_of_alpha, (alpha,), (jnp.concatenate(tangents),))
        phis, slopes = jnp.split(phi, len(spans)), jnp.split(slope, len(spans))
    else:
        # Materialised first (and its derivative, under a fit's Jacobian): the five
        # shifted reads of the differences would otherwise each recompute it.
        phis = jnp.split(fusion_barrier(phi_of_alpha(alpha), d), len(spans))
        slopes = [_difference_slopes(p, h) for p, h in zip(phis, dtaus, strict=True)]
    return list(zip(knots, dtaus, phis, slopes, strict=True))


def _difference_slopes(phi, dtau):
    """$d\\phi/d\\tau$ at uniform knots from their values: fourth-order differences,
    central inside and one-sided at the two knots of each end."""
    h12 = 12.0 * dtau
    inside = (phi[:-4] - 8.0 * phi[1:-3] + 8.0 * phi[3:-1] - phi[4:]) / h12
    p, q = phi[:5], phi[-5:][::-1]  # the ends, outward first
    first = (-25.0 * p[0] + 48.0 * p[1] - 36.0 * p[2] + 16.0 * p[3] - 3.0 * p[4]) / h12
    second = (-3.0 * p[0] - 10.0 * p[1] + 18.0 * p[2] - 6.0 * p[3] + p[4]) / h12
    last = -(-25.0 * q[0] + 48.0 * q[1] - 36.0 * q[2] + 16.0 * q[3] - 3.0 * q[4]) / h12
    before = -(-3.0 * q[0] - 10.0 * q[1] + 18.0 * q[2] - 6.0 * q[3] + q[4]) / h12
    return jnp.concatenate([jnp.stack([first, second]), inside, jnp.stack([before, last])])


def hermite(t, p0, p1, m0, m1):
    """Cubic Hermite interpolant on [0, 1] of values `p0`, `p1` and slopes `m0`, `m1`
    (per unit of `t`), at `t`."""
    t2 = t * t
    t3 = t2 * t
    return (
        (2.0 * t3 - 3.0 * t2 + 1.0) * p0
        + (t3 - 2.0 * t2 + t) * m0
        + (3.0 * t2 - 2.0 * t3) * p1
        + (t3 - t2) * m1
    )


def _cubic(dtau, phi, slope):
    """Each knot interval's cubic in $t \\in [0, 1]$, $c_0 + t (c_1 + t (c_2 + t c_3))$:
    the Hermite interpolant of the values `phi` and slopes `slope` (per unit of
    $\\tau$) at its two ends."""
    p0, p1 = phi[:-1], phi[1:]
    m0, m1 = slope[:-1] * dtau, slope[1:] * dtau
    d = p1 - p0
    return p0, m0, 3.0 * d - 2.0 * m0 - m1, m0 + m1 - 2.0 * d


def _coefficients(sides, extra):
    """The interval cubics of `_look_up`'s tables, the sides stacked, and (below
    float64) each interval's first knot: computed once a call and written out (fused into the rays'
    pass, XLA would recompute them from eight reads a ray), or, for a table known when
    the program is traced, computed here once, a constant of the program."""
    tables = (sides, extra)
    xp = np if is_concrete(tables) else jnp
    if xp is np:
        sides, extra = jax.tree.map(np.asarray, tables)
    stacked = [xp.concatenate(c) for c in zip(*(_cubic(*s[1:]) for s in sides), strict=True)]
    float64 = sides[0][0].dtype == np.float64  # reads no knot (see `_look_up`)
    knots = None if float64 else xp.concatenate([s[0][:-1] for s in sides])
    extra = None if extra is None else _cubic(sides[0][1], *extra)
    out = (stacked, knots, extra)
    if xp is np:
        return jax.tree.map(jnp.asarray, out)
    if len(sides) == 1 and extra is None:
        # One table (the renderer's escape angle): left to XLA, which reads the knot
        # values in the rays' pass; a render was slower with them written out apart
        # (benchmarks/bench_render.py).
        return out
    return fusion_barrier(out, sides[0][1])


def _look_up(alpha, origin, sides, extra=None, sign=1.0):
    """Interpolate tables uniform in $\\tau = \\ln|{\\rm gap}|$ at
    ${\\rm gap} = $ `sign` (`alpha` - `origin`).

    `sides`: one table `(knots, dtau, values, slopes)`, read at `gap` (> 0), or two
    with the same number of knots, the first read where `gap > 0` and the second where
    `gap < 0`. `extra`: `(values, slopes)` on the first table's knots, or `None`.

    One logarithm a ray, vectorised (`_fastmath.log`), gives the knot index and the
    fraction $t$ in it; each interval's cubic is read as four coefficients (the sides
    stacked, so a ray reads one row whichever its side). Below the first knot the
    logarithmic law is extrapolated, linear in $\\tau$; `gap == 0` reads the first knot.

    **Returns:** `(value, extra value or None)`, each of the shape of `alpha`.
    """
    knots, dtau = sides[0][0], sides[0][1]
    n = knots.shape[0]
    two = len(sides) == 2
    gap = sign * (alpha - origin)
    inner = (gap < 0) if two else None

    def per_side(first, second, inner=inner):
        return jnp.where(inner, second, first) if two else first

    stacked, starts, extra = _coefficients(sides, extra)
    tau0 = per_side(knots[0], sides[-1][0][0])
    inv = per_side(1.0 / dtau, 1.0 / sides[-1][1])
    first = (jnp.exp(knots[0]), jnp.exp(sides[-1][0][0]))

    def log_size(a):  # ln|gap|: the first knot's where gap <= 0 (one table), NaN kept
        g = sign * (a - origin)
        size = jnp.abs(g) if two else g
        keep = (size > 0) | jnp.isnan(size)
        return _fastmath.log(jnp.where(keep, size, per_side(*first, inner=g < 0)))

    if alpha.size and jax.default_backend() == "cpu":
        # tau computed in a pass of its own and written out. The logarithm is plain
        # multiply-adds, cheap in XLA's eyes, and XLA's CPU backend (without the
        # multi-output fusion GPUs have) copies cheap code into every consumer: into
        # the Phi and periapsis look-ups of a whole `TraceResult`, into each use of a
        # render's escape angle (benchmarks/bench_render.py). The pass is
        # the branch of a `lax.cond` on a predicate XLA cannot fold (a ray, never
        # NaN), a fusion boundary. benchmarks/floor.py measures it.
        ok = ~jnp.isnan(jnp.nan_to_num(jnp.ravel(alpha)[0]))
        tau = jax.lax.cond(ok, log_size, jnp.negative, alpha)
    else:
        tau = log_size(alpha)
    x = (tau - tau0) * inv
    i = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, n - 2)
    row = i + per_side(0, n - 1)
    if knots.dtype == jnp.float64:
        # The fraction by arithmetic: exact to round-off, and no read of the knot.
        t = x - i
    else:
        # In lower precisions x - i loses ulp(n) ~ 5e-4 of an interval: the fraction
        # against the knot's own tau (no loss from |tau - tau0| ~ 30).
        t = (tau - starts[row]) * inv
    below = t < 0  # before the first knot: the linear law

    def evaluate(coefficients, at):
        c0, c1, c2, c3 = (c[at] for c in coefficients)
        return c0 + t * (c1 + t * jnp.where(below, 0.0, c2 + t * c3))

    value = evaluate(stacked, row)
    return value, None if extra is None else evaluate(extra, i)
