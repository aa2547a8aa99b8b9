"""The photon orbit equation $u'' = 1.5 u^2 - u$: pure functions on arrays.

$u = 1/r$ (units of $1/R_S$) as a function of the azimuth $\\phi$ (radians). The
integrators that march it are tableaux in `_integrators`; their loop ends a ray with
`_finish`, the last, partial step taken in $u$ instead of $\\phi$ (Henon's trick, here
as a Gauss-Legendre quadrature of $d\\phi/du = 1/u'$ with $u'$ from the first
integral), so the crossing itself is located to round-off and the error is the
integrator's own.
"""

import jax.numpy as jnp

# Gauss-Legendre nodes and weights on [0, 1], five points (exact to degree 9).
_GL_X = (
    0.046910077030668,
    0.230765344947158,
    0.5,
    0.769234655052842,
    0.953089922969332,
)
_GL_W = (
    0.118463442528095,
    0.239314335249683,
    0.284444444444444,
    0.239314335249683,
    0.118463442528095,
)


def acceleration(u):
    """$u'' = 1.5 u^2 - u$ as a function of $u$ alone (the integrators' $f$)."""
    return 1.5 * u * u - u


def rhs(u, v):
    """Right-hand side of the orbit equation: $(u, u')' = (u', 1.5 u^2 - u)$."""
    return v, acceleration(u)


def first_integral(u, v):
    """The first integral $u'^2 + u^2 - u^3$ of the orbit equation.

    Conserved along an orbit, where it equals $1/b^2$ ($b$ the impact parameter in
    units of R_S).

    **Arguments:**
    - `u, v`: $u = 1/r$ (units of $1/R_S$) and $u' = du/d\\phi$, broadcastable arrays.

    **Returns:** $u'^2 + u^2 - u^3$, in units of $R_S^{-2}$.
    """
    return v * v + u * u - u * u * u


def _finish(u, v, target):
    # Azimuth from state (u, v) to u = target, integrating dphi/du = 1/v(u) with
    # v(u)^2 = v^2 + (u_k^2 - u^2) - (u_k^3 - u^3) (the first integral).
    du = target - u
    sgn = jnp.where(v < 0, -1.0, 1.0)
    total = jnp.zeros_like(u)
    for x, w in zip(_GL_X, _GL_W):
        uu = u + x * du
        # v(uu)^2 / v^2, no v^2 (it underflows for a far camera in float32, v ~ 1/D)
        g = 1.0 + ((u - uu) / v) * (((u + uu) - (u * u + u * uu + uu * uu)) / v)
        total = total + w / jnp.sqrt(jnp.maximum(g, 1e-6))
    return total * du / (sgn * jnp.abs(v))
