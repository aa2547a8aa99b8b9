"""The one-dimensional ray map of a static camera: Phi(alpha) tabulated once per distance.

For a static camera the escape angle depends on the local angle alpha alone, so an
image needs Phi on the alphas it contains, not one orbit per pixel. The table is
uniform in $\\tau = \\ln(\\alpha - \\alpha_{sh})$: near the shadow edge Phi grows like
$-\\tau$ (the strong-deflection logarithm), so it is smooth and nearly linear in
$\\tau$, and cubic Hermite interpolation with exact slopes (forward-mode autodiff of
the closed form) reaches $10^{-10}$ rad with a few thousand knots. Below the first
knot the logarithmic law is extrapolated linearly in $\\tau$.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from . import _exact
from ._exact import CAPTURED, ESCAPED, UNRESOLVED

# Interpolation error of a cubic Hermite spline: h^4 / 384 max|phi''''(tau)|, and
# |phi''''| <= ~pi on the escaping branch (measured by tests/test_raymap.py).
_HERMITE_C = math.pi / 384.0
_REL_START = 1e-13  # first knot at alpha_sh * (1 + 1e-13): beyond float64 conditioning


def knots_for(accuracy: float, span: float) -> int:
    """Number of knots for a target interpolation error `accuracy` (radians) over a
    $\\tau$-span `span`, with a safety factor of 10 on the error model."""
    h = (accuracy / (10.0 * _HERMITE_C)) ** 0.25
    return int(min(max(math.ceil(span / h) + 1, 64), 200_000))


class RayMap(eqx.Module):
    """Escape angle as a function of alpha for one static camera distance.

    Build it with `RayMap.build(distance)`; call it on any array of alphas. It is a
    pytree of arrays, so it can be built inside `jit` and differentiated with respect
    to the distance (gradients flow through the knots and the shadow angle).

    **Fields:** `distance` (units of R_S), `alpha_sh` (shadow angle, radians), the
    knot grid `tau0`, `dtau` and the knot values `phi`, `slope` ($d\\phi/d\\tau$).
    """

    distance: Float[Array, ""]
    alpha_sh: Float[Array, ""]
    tau0: Float[Array, ""]
    dtau: Float[Array, ""]
    phi: Float[Array, " n"]
    slope: Float[Array, " n"]
    max_windings: float = eqx.field(static=True, default=10.0)

    @classmethod
    def build(
        cls,
        distance: ArrayLike,
        *,
        accuracy: float = 1e-10,
        knots: int | None = None,
        max_windings: float = 10.0,
    ) -> "RayMap":
        """Tabulate Phi(alpha) for a camera at `distance` (units of R_S, scalar).

        **Arguments:**
        - `distance`: camera radius $D > 1$ (units of R_S).
        - `accuracy`: target interpolation error of phi (radians); sets the number
          of knots unless `knots` is given.
        - `max_windings`: rays sweeping more than $2\\pi\\times$ this are unresolved.
        """
        d = jnp.asarray(distance, jnp.result_type(float, distance))
        if d.ndim != 0:
            raise ValueError(f"RayMap.build needs a scalar distance, got shape {d.shape}")
        alpha_sh = _exact.shadow_angle(d)
        # tau range: from just outside the critical angle to alpha = pi.
        tiny = jnp.finfo(d.dtype).tiny
        # The last knot sits a hair short of alpha = pi, where |sin(alpha)| has its kink.
        tau_hi = jnp.log(jnp.maximum(jnp.pi - alpha_sh, tiny)) - 1e-13
        tau_lo = jnp.log(
            jnp.maximum(alpha_sh * _REL_START, 1e-300 if d.dtype == jnp.float64 else 1e-37)
        )
        if knots is None:
            # The span is at most ~ln(pi / (alpha_sh 1e-13)); alpha_sh >= b_c/D.
            span_bound = 30.0 + 2.0 * math.log(10.0) + 25.0
            knots = knots_for(accuracy, span_bound)
        n = knots
        dtau = (tau_hi - tau_lo) / (n - 1)
        tau = tau_lo + dtau * jnp.arange(n, dtype=d.dtype)

        gap = jnp.exp(tau)

        def phi_of_alpha(a):
            return _exact.escape_angle(a, d, iterations=8, max_windings=1e6)[0]

        # d phi / d tau = (d phi / d alpha) (alpha - alpha_sh): one forward-mode pass.
        phi, slope = jax.jvp(phi_of_alpha, (alpha_sh + gap,), (gap,))
        return cls(d, alpha_sh, tau_lo, dtau, phi, slope, max_windings)

    def escape_angle(self, alpha: ArrayLike) -> Float[Array, "..."]:
        """Interpolated escape angle (radians) at `alpha`; meaningful where
        `alpha > alpha_sh` (escaping rays), finite everywhere."""
        alpha = jnp.asarray(alpha, self.phi.dtype)
        n = self.phi.shape[0]
        gap = alpha - self.alpha_sh
        floor_gap = jnp.exp(self.tau0)
        tau = jnp.log(jnp.maximum(gap, floor_gap))
        s = (tau - self.tau0) / self.dtau
        i = jnp.clip(jnp.floor(s).astype(jnp.int32), 0, n - 2)
        t = jnp.maximum(s - i, 0.0)  # may pass 1 by ~1e-13 / dtau at alpha = pi
        p0, p1 = self.phi[i], self.phi[i + 1]
        m0, m1 = self.slope[i] * self.dtau, self.slope[i + 1] * self.dtau
        t2 = t * t
        t3 = t2 * t
        h00 = 2.0 * t3 - 3.0 * t2 + 1.0
        h10 = t3 - 2.0 * t2 + t
        h01 = 3.0 * t2 - 2.0 * t3
        h11 = t3 - t2
        inside = h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1
        # Below the first knot: the logarithmic law, linear in tau.
        gap_safe = jnp.where(gap > 0, gap, floor_gap)
        below = self.phi[0] + self.slope[0] * (jnp.log(gap_safe) - self.tau0)
        return jnp.where(gap < floor_gap, below, inside)

    def __call__(self, alpha: ArrayLike):
        """Trace rays at local angles `alpha` (radians) through the table.

        **Returns:** a `TraceResult`; `r_min` is the closed-form periapsis.
        """
        from ._trace import TraceResult

        alpha = jnp.asarray(alpha, self.phi.dtype)
        phi = self.escape_angle(alpha)
        escaped = alpha > self.alpha_sh
        cap = 2.0 * jnp.pi * self.max_windings
        unresolved = (alpha == self.alpha_sh) | (escaped & ~(phi <= cap))
        status = jnp.where(unresolved, UNRESOLVED, jnp.where(escaped, ESCAPED, CAPTURED))
        phi = jnp.where(escaped & ~unresolved, phi, jnp.where(unresolved, cap, 0.0))
        b = _exact.impact_parameter(alpha, self.distance)
        turning = escaped & (jnp.cos(alpha) > 0) & (b > _exact.B_CRIT)
        r0 = _exact.periapsis(jnp.where(turning, b, 2.0 * _exact.B_CRIT))
        r_min = jnp.where(turning, r0, jnp.where(escaped, self.distance, 1.0))
        return TraceResult(phi, status.astype(jnp.int8), r_min.astype(phi.dtype))
