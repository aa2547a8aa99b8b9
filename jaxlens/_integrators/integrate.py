"""The one integration loop of the orbit equation, driven by a `ButcherTableau`."""

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp

from .._orbit import _finish, acceleration
from ._tableau import ButcherTableau, rk_step

_RUNNING = 2  # outcome while a ray runs, and after the loop if it ran out of steps


def integrate(u0, v0, tableau: ButcherTableau, *, dphi, tol=None, max_steps: int):
    """Integrate rays from $(u_0, u'_0)$ until each reaches $u = 0$ or $u = 1$.

    Steps in azimuth with `tableau` until a step would cross $u = 0$ (the asymptote)
    or $u = 1$ (the horizon); the crossing is then reached from the last state before
    it by a quadrature in $u$ (`_orbit._finish`), once, after the loop. Runs under
    `vmap` (rays that are done are frozen) and is reverse-mode differentiable (a
    checkpointed, bounded while loop).

    **Arguments:**
    - `u0, v0`: initial $u = 1/r$ (units of $1/R_S$) and $du/d\\phi$, arrays of one
      shape.
    - `tableau`: the method. Fixed step `dphi` (radians) if it has no error estimate;
      otherwise adaptive, first step `dphi`, tolerance `tol` per step on the error
      relative to $|u| + |u'|$.
    - `tol`: the per-step tolerance of an adaptive tableau; `None` for a fixed step.
    - `max_steps`: step budget; rays still running after it are unresolved.

    **Returns:** `(phi, outcome, r_min, steps)`: azimuth swept (radians), outcome
    (0 reached $u = 0$, 1 reached $u = 1$, 2 out of budget), the smallest radius
    reached (units of R_S) and the number of steps taken (rejected ones included).
    """
    if tableau.adaptive != (tol is not None):
        raise ValueError(
            f"tol={tol!r}: an adaptive tableau (one with b_error) needs a tolerance, a "
            "fixed-step one takes none"
        )
    dtype = jnp.result_type(u0, v0)
    u0 = jnp.asarray(u0, dtype)
    v0 = jnp.asarray(v0, dtype)

    def one(u0, v0):
        init = (
            jnp.zeros((), dtype),  # phi
            u0,
            v0,
            jnp.asarray(dphi, dtype),  # h
            jnp.asarray(_RUNNING, jnp.int8),  # outcome
            jnp.zeros((), jnp.int32),  # steps
            u0,  # u_max
        )

        def cond(state):
            return state[4] == _RUNNING

        def body(state):
            phi, u, v, h, outcome, n, umax = state
            u1, v1, error = rk_step(tableau, acceleration, u, v, h)
            if tableau.adaptive:
                # Relative to the state's size: for u << 1 the orbit equation is nearly
                # linear (u'' = -u), so a far camera's ray (u ~ 1/D) needs the steps of a
                # near one; an absolute error let D = 1e8 take 8 steps and err by 3 rad
                # at tol 1e-6.
                size = jnp.maximum(jnp.abs(u) + jnp.abs(v), jnp.finfo(dtype).tiny)
                err = jnp.maximum(jnp.abs(error[0]), jnp.abs(error[1])) / size
                accept = err <= tol
                factor = 0.9 * (tol / jnp.maximum(err, 1e-300)) ** (1.0 / tableau.order)
                h_next = h * jnp.clip(factor, 0.2, 5.0)
            else:
                accept = jnp.asarray(True)
                h_next = h
            out = (u1 <= 0) | (u1 >= 1)
            move = accept & ~out
            # A step that would cross stops the ray where it is; the crossing itself
            # is integrated after the loop.
            outcome = jnp.where(accept & out, (u1 > 0).astype(jnp.int8), outcome)
            phi = jnp.where(move, phi + h, phi)
            umax = jnp.maximum(umax, jnp.where(move, u1, u))
            u = jnp.where(move, u1, u)
            v = jnp.where(move, v1, v)
            return phi, u, v, h_next, outcome, n + 1, umax

        phi, u, v, _, outcome, n, umax = eqxi.while_loop(
            cond, body, init, max_steps=max_steps, kind="checkpointed"
        )
        crossed = outcome != _RUNNING
        target = jnp.where(outcome == 1, 1.0, 0.0).astype(dtype)
        phi = jnp.where(crossed, phi + _finish(u, v, target), phi)
        umax = jnp.where(crossed, jnp.maximum(umax, target), umax)
        return phi, outcome, 1.0 / umax, n

    shape = u0.shape
    flat = jax.vmap(one)(u0.reshape(-1), v0.reshape(-1))
    return jax.tree.map(lambda x: x.reshape(shape), flat)


integrate = eqx.filter_jit(integrate)
