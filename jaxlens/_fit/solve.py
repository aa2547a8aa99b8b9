"""The optimistix Levenberg-Marquardt solve with a dense Jacobian."""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jax.flatten_util import ravel_pytree

from .spd import solve_spd

# The Gauss-Newton step left at a point, as the chi^2 it would still gain (its Newton
# decrement), below which a fit has settled: the solve then takes that step without
# evaluating the model again and stops. 3e-2 is a step of 0.17 standard errors
# (whitened), and the step's own error is far smaller: on the benchmark ring the
# solver's decrements were 3668, 68, 1.0e-2 and 3.6e-7, each step leaving at most 2e-2
# of the decrement before it (1.5e-4 near the optimum), so a settling step lands within
# 0.025 standard errors of the optimum (within 1e-3 there). Optimistix's own test
# (every residual and every parameter changed by less than rtol/atol between accepted
# steps) also stops it.
SETTLED_CHI2 = 3e-2


def gauss_newton(r, jac):
    """The Gauss-Newton step `(J^T J)^-1 J^T (-r)` from residuals `r (N,)` with
    Jacobian `jac (N, p)`, and its Newton decrement `r^T J (J^T J)^-1 J^T r`: the
    decrease of `sum(r^2)` it would bring. Columns scaled to unit norm, and a ridge of
    1e-14 of the trace on `J^T J`, so that directions the data do not fix, such as a
    held parameter's zero column, neither move nor add. Solved by `solve_spd`, not
    LAPACK (why: see there)."""
    jn, a, scale = _scaled_normal(jac)
    g = jn.T @ r
    z = solve_spd(a, g)
    return -z / scale, g @ z


def _scaled_normal(a):
    """`(an, m, scale)` of a tall `a (N, p)`: its columns scaled to unit norm (`an = a /
    scale`; a zero column kept) and their normal matrix `an^T an` with a ridge of 1e-14
    of its trace, for `solve_spd`."""
    scale = jnp.sqrt(jnp.sum(a * a, axis=0))
    scale = jnp.where(scale > 0, scale, 1.0)
    an = a / scale
    m = an.T @ an
    m = m + 1e-14 * jnp.maximum(jnp.trace(m), 1.0) * jnp.eye(m.shape[0], dtype=m.dtype)
    return an, m, scale


class ScaledNormalEquations(lx.AbstractLinearSolver):
    """Least squares `min |A x - b|` for a tall `A` of a few columns (the damped
    Gauss-Newton system `[J; sqrt(lambda) I]` that optimistix's Levenberg-Marquardt
    poses) by its normal equations, the columns scaled to unit norm and solved by
    `solve_spd`: no LAPACK call (lineax's default, QR, makes one), so the fit's solver
    runs without setting up JAX's LAPACK kernels (importing scipy.linalg). The normal
    equations square the scaled columns' condition number (about 100 for the fit
    benchmark's first ring), which float64 absorbs: on the fit benchmark every fitted
    value and step count is QR's, the two degenerate rings included."""

    def init(self, operator, options):
        del options
        a = operator.as_matrix()
        # Columns scaled by their largest entry first: a damping row of sqrt(lambda) up
        # to 1e154 (optimistix's largest) would overflow when squared.
        big = jnp.max(jnp.abs(a), axis=0)
        big = jnp.where(big > 0, big, 1.0)
        an, m, norm = _scaled_normal(a / big)
        return an, m, big * norm, operator.in_structure()

    def compute(self, state, vector, options):
        del options
        an, m, scale, in_structure = state
        b = ravel_pytree(vector)[0]
        x = solve_spd(m, an.T @ b) / scale
        unravel = ravel_pytree(jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype),
                                            in_structure))[1]  # fmt: skip
        return unravel(x.astype(b.dtype)), lx.RESULTS.successful, {}

    def transpose(self, state, options):
        raise NotImplementedError("ScaledNormalEquations solves least squares only")

    def conj(self, state, options):
        raise NotImplementedError("ScaledNormalEquations solves real systems only")

    def assume_full_rank(self):
        return True


def newton_decrement(r, jac):
    """The decrease of `sum(r^2)` the full Gauss-Newton step from `r`, `jac` would bring
    (`gauss_newton`)."""
    return gauss_newton(r, jac)[1]


class _SettledState(eqx.Module):
    inner: object
    settled: jax.Array
    step: jax.Array  # the Gauss-Newton step taken where it settled (else zeros)


class _Settled(optx.AbstractLeastSquaresSolver):
    """A least-squares solver (`inner`, whose `fn` returns `(r, (r, jac, ...))`) that
    also stops once the last accepted point's Newton decrement is below
    `SETTLED_CHI2`, with that point's Gauss-Newton step taken: a fit of a model whose
    residuals never reach round-off (noise) would otherwise take rejected steps of 1e-6
    standard errors until optimistix's test passes (11 steps from an optimum, each with
    its full Jacobian), and a step it can compute from the Jacobian it has would cost
    an evaluation of the model."""

    inner: optx.AbstractLeastSquaresSolver

    @property
    def rtol(self):
        return self.inner.rtol

    @property
    def atol(self):
        return self.inner.atol

    @property
    def norm(self):
        return self.inner.norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        state = self.inner.init(fn, y, args, options, f_struct, aux_struct, tags)
        return _SettledState(state, jnp.array(False), jnp.zeros_like(y))

    def step(self, fn, y, args, options, state, tags):
        y, inner, aux = self.inner.step(fn, y, args, options, state.inner, tags)
        # The accepted point's own residuals and Jacobian, kept in the inner state
        # (optimistix 0.1 returns those of the point before it, 0.0.10 its own): a point
        # that has settled stops the solve without a further evaluation of the model.
        aux = getattr(inner, "aux", aux)
        step, decrement = gauss_newton(aux[0], aux[1])
        settled = decrement < SETTLED_CHI2
        step = jnp.where(settled, step, 0.0)
        return y + step, _SettledState(inner, settled, step), aux

    def terminate(self, fn, y, args, options, state, tags):
        done, result = self.inner.terminate(fn, y, args, options, state.inner, tags)
        return done | state.settled, result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state.inner, tags, result)


def dense_least_squares(both, theta0, rtol, atol, max_steps):
    """Levenberg-Marquardt (optimistix) on `both(theta) -> (r, aux)`, with a dense
    Jacobian.

    The Jacobian `J` comes from one forward-mode pass over the few parameters, and the
    residual function's JVP is `J @ dtheta`: optimistix applies the linearised
    residuals several times a step (the damped QR, the trust region's predicted
    reduction) and each application would otherwise be a further copy of the model's
    tangent program; as matrix products the solver's program compiles ~3x faster.

    **Returns:** `(theta, r, J, aux, result, steps, moved)`; `r`, `J`, `aux` are those
    of the last accepted point, evaluated in the solve (no further copy of the model's
    Jacobian is compiled): `theta - moved`, where `moved` is the Gauss-Newton step
    (of a decrement below `SETTLED_CHI2`) the solve took when it settled, else zero.
    To first order the residuals at `theta` are `r + J @ moved`.
    """

    traced = {}

    def with_jacobian(theta):
        jac, (r, aux) = jax.jacfwd(lambda t: (lambda r, a: (r, (r, a)))(*both(t)),
                                   has_aux=True)(theta)  # fmt: skip
        return r, jac, aux

    @jax.custom_jvp
    def fn(theta):
        # Traced once: optimistix traces the function twice (for its output's shape,
        # then in the step), each a trace of the model and its Jacobian; the jaxpr of
        # the first trace is replayed in the second.
        if not traced:
            traced["jaxpr"], shape = jax.make_jaxpr(with_jacobian, return_shape=True)(theta)
            traced["tree"] = jax.tree.structure(shape)
        jaxpr = traced["jaxpr"]
        return jax.tree.unflatten(
            traced["tree"], jax.core.eval_jaxpr(jaxpr.jaxpr, jaxpr.consts, theta)
        )

    @fn.defjvp
    def _jvp(primals, tangents):
        (theta,), (dtheta,) = primals, tangents
        r, jac, aux = fn(theta)
        zero = jax.tree.map(jnp.zeros_like, aux)
        return (r, jac, aux), (jac @ dtheta, jnp.zeros_like(jac), zero)

    sol = optx.least_squares(
        lambda th, _: (lambda r, jac, aux: (r, (r, jac, aux)))(*fn(th)),
        _Settled(
            optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=ScaledNormalEquations())
        ),  # fmt: skip
        theta0,
        has_aux=True,
        max_steps=max_steps,
        throw=False,
    )
    r, jac, aux = sol.aux
    return sol.value, r, jac, aux, sol.result, sol.stats["num_steps"], sol.state.step
