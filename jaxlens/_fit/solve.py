"""The starting search's static setup and the optimistix Levenberg-Marquardt solve with
a dense Jacobian."""

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx


class _Setup(eqx.Module):
    """Static description of the starting search's model (`starts`): pixels of side
    `block` (full-image pixels) with a k x k rule."""

    half_width: float = eqx.field(static=True)  # W/2 of the full image, pixels
    block: int = eqx.field(static=True)
    k: int = eqx.field(static=True)
    knots: int = eqx.field(static=True)

    @property
    def width(self) -> int:
        """Width of the full image (pixels)."""
        return round(2 * self.half_width)


def dense_least_squares(both, theta0, rtol, atol, max_steps):
    """Levenberg-Marquardt (optimistix) on `both(theta) -> (r, aux)`, with a dense
    Jacobian.

    The Jacobian `J` comes from one forward-mode pass over the few parameters, and the
    residual function's JVP is `J @ dtheta`: optimistix applies the linearised
    residuals several times a step (the damped QR, the trust region's predicted
    reduction) and each application would otherwise be a further copy of the model's
    tangent program; as matrix products the solver's program compiles ~3x faster.

    **Returns:** `(theta, r, J, aux, result, steps)`; `r`, `J`, `aux` are those of the
    last accepted point but one: at termination that step is below the tolerances, so
    they are the optimum's to that accuracy, and no further copy of the model's
    Jacobian is compiled.
    """

    @jax.custom_jvp
    def fn(theta):
        jac, (r, aux) = jax.jacfwd(lambda t: (lambda r, a: (r, (r, a)))(*both(t)),
                                   has_aux=True)(theta)  # fmt: skip
        return r, jac, aux

    @fn.defjvp
    def _jvp(primals, tangents):
        (theta,), (dtheta,) = primals, tangents
        r, jac, aux = fn(theta)
        zero = jax.tree.map(jnp.zeros_like, aux)
        return (r, jac, aux), (jac @ dtheta, jnp.zeros_like(jac), zero)

    sol = optx.least_squares(
        lambda th, _: (lambda r, jac, aux: (r, (r, jac, aux)))(*fn(th)),
        optx.LevenbergMarquardt(rtol=rtol, atol=atol),
        theta0,
        has_aux=True,
        max_steps=max_steps,
        throw=False,
    )
    r, jac, aux = sol.aux
    return sol.value, r, jac, aux, sol.result, sol.stats["num_steps"]
