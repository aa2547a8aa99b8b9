"""The least-squares problem: its static setup, the parametrisation, the residuals
with a dense Jacobian, and the optimistix Levenberg-Marquardt solve."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .model import _pixel_basis
from .noise import clipped_mean
from .table import _D_MIN, escape_table


class _Setup(eqx.Module):
    """Static description of one least-squares problem: pixels of side `block` (full-
    image pixels) with a k x k rule, and optionally a second, coarser set of side
    `coarse` with `k_coarse` (`coarse` = 0: none)."""

    half_width: float = eqx.field(static=True)  # W/2 of the full image, pixels
    block: int = eqx.field(static=True)
    k: int = eqx.field(static=True)
    knots: int = eqx.field(static=True)
    fit_sigma: bool = eqx.field(static=True)
    coarse: int = eqx.field(static=True, default=0)
    k_coarse: int = eqx.field(static=True, default=2)

    @property
    def width(self) -> int:
        """Width of the full image (pixels)."""
        return round(2 * self.half_width)


# The flux of the relativistic rings (order 1 and 2, radially a few thousandths of a
# pixel wide) is a nuisance factor `ring_flux` (1: the exact area average), with a
# Gaussian prior of this standard deviation about 1. Renderers that point-sample pixels
# alias these rings (k = 12 samples a pixel gave 55 % of the exact flux at D = 17, in a
# moire pattern), and a fit that trusted their flux was pulled 5 % in D on such images
# when sigma was fitted and no floor was seen; their positions, which fix D
# against the primary ring's radius, are still used.
_RING_FLUX_PRIOR = 1.0


def _unpack(theta, fixed_sigma, scale, setup: _Setup):
    """Internal parameters -> (D, fov, sigma, A, floor, ring_flux)."""
    d = _D_MIN + jnp.exp(theta[0])
    fov = jnp.pi * jax.nn.sigmoid(theta[1])
    if setup.fit_sigma:
        sigma, rest = jnp.exp(theta[2]), theta[3:]
    else:
        sigma, rest = fixed_sigma, theta[2:]
    return d, fov, sigma, rest[0] * scale, rest[1] * scale, rest[2]


def _pack(d, fov, sigma, a, floor, scale, fit_sigma):
    """(D, fov, sigma, A, floor) -> internal parameters, ring_flux starting at 1."""
    v = [math.log(d - _D_MIN), math.log(fov / (math.pi - fov))]
    if fit_sigma:
        v.append(math.log(sigma))
    return np.asarray(v + [a / scale, floor / scale, 1.0])


def _model(theta, args, setup: _Setup):
    """Model pixel values / scale: the fine pixels, then the coarse ones (if any)."""
    (x0, y0), coarse, _, _, fixed_sigma, scale = args[:6]
    d, fov, sigma, a, floor, ring_flux = _unpack(theta, fixed_sigma, scale, setup)
    table = escape_table(d, knots=setup.knots)
    focal = setup.half_width / jnp.tan(0.5 * fov)
    width = setup.width
    g, t, c = _pixel_basis(table, focal, sigma, x0, y0, width=width, block=setup.block, k=setup.k)
    if setup.coarse:
        gc, tc, cc = _pixel_basis(
            table, focal, sigma, *coarse, width=width, block=setup.coarse, k=setup.k_coarse
        )
        g, t, c = (jnp.concatenate(v) for v in ((g, gc), (t, tc), (c, cc)))
    return (a * (g + ring_flux * t) + floor * c) / scale


def _residuals(theta, args, setup: _Setup):
    """weight x (expected observation - data) / scale.

    `args` = (fine edges, coarse edges, data, weights, fixed sigma, scale, clip): the
    weight of a pixel averaging b x b original ones is b, so every weighted residual
    has the noise of one original pixel; `clip` = (lo, hi, noise) / scale of the
    clipping of the stored values (infinite bounds: none)."""
    data, weight, scale, clip = args[2], args[3], args[5], args[6]
    m = clipped_mean(_model(theta, args, setup), clip[0], clip[1], clip[2])
    # The prior on ring_flux, in units of one pixel's noise.
    prior = clip[2] * (theta[-1:] - 1.0) / _RING_FLUX_PRIOR
    return jnp.concatenate([weight * (m - data / scale), prior])


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


@eqx.filter_jit
def _solve(theta0, args, setup: _Setup, rtol, atol, max_steps):
    theta, r, jac, _, result, steps = dense_least_squares(
        lambda th: (_residuals(th, args, setup), None), theta0, rtol, atol, max_steps
    )
    return theta, r, jac, result, steps
