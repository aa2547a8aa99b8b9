"""The integrators of u'' = 1.5 u^2 - u: convergence order and the first integral."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl
from jaxlens import _orbit

ALPHA = jnp.linspace(0.05, 0.5, 24)  # escaping rays of a camera at D = 20
D = 20.0


def _err(method):
    exact = jl.trace(ALPHA, D, method=jl.Exact(iterations=12)).phi
    return float(jnp.max(jnp.abs(jl.trace(ALPHA, D, method=method).phi - exact)))


@pytest.mark.parametrize(
    "cls, steps, order",
    [(jl.Euler, (0.004, 0.002, 0.001), 1), (jl.RK4, (0.08, 0.04, 0.02), 4)],
)
def test_convergence_order(cls, steps, order):
    errs = [_err(cls(dphi=h, max_steps=40_000)) for h in steps]
    rates = [math.log2(errs[i] / errs[i + 1]) for i in range(len(errs) - 1)]
    # Halving the step divides the error by 2^order; +-0.3 allows the asymptotic
    # regime to be approached, not yet reached, at the coarsest step.
    for r in rates:
        assert abs(r - order) < 0.3, (errs, rates)


def test_adaptive_error_follows_tolerance():
    e1, e2 = _err(jl.DormandPrince(tol=1e-8)), _err(jl.DormandPrince(tol=1e-11))
    assert e2 < e1 / 100  # tolerance 1000x tighter: error at least 100x smaller
    assert e2 < 1e-7


@pytest.mark.parametrize("distance", [1e4, 1e6, 1e8])
def test_adaptive_error_is_scale_free_for_far_cameras(distance):
    """Far cameras' rays have u ~ 1/D; the step error is measured relative to |u| + |u'|,
    so tol 1e-6 gives a small error there too (an absolute error norm took 8 steps at
    D = 1e8 and erred by 3 rad)."""
    alpha = jnp.sqrt(2.0 / distance) * jnp.geomspace(0.3, 3.0, 16)  # about the ring
    exact = jl.trace(alpha, distance, method=jl.Exact(iterations=12)).phi
    got = jl.trace(alpha, distance, method=jl.DormandPrince(tol=1e-6)).phi
    assert float(jnp.max(jnp.abs(got - exact))) < 1e-5  # 4.4e-7 measured on 1,500 rays


def _orbit_states(step, h, n):
    # March one orbit and record (u, v) for the first-integral check.
    u0 = 1.0 / D
    alpha = 0.3
    v0 = u0 * math.sqrt(1 - u0) / math.tan(alpha)

    def body(carry, _):
        u, v = step(*carry, h)
        return (u, v), (u, v)

    _, (u, v) = jax.lax.scan(body, (jnp.float64(u0), jnp.float64(v0)), None, length=n)
    return u, v, u0 * u0 * (1 - u0) / math.sin(alpha) ** 2  # G = 1/b^2 at the camera


@pytest.mark.parametrize("step, order", [(_orbit.rk4_step, 4), (_orbit.euler_step, 1)])
def test_first_integral_conserved(step, order):
    drifts = []
    for h in (0.02, 0.01):
        u, v, g0 = _orbit_states(step, h, int(2.0 / h))  # 2 radians of the orbit
        drifts.append(float(jnp.max(jnp.abs(_orbit.first_integral(u, v) - g0))) / g0)
    # Semi-implicit Euler is symplectic: its energy error stays bounded at O(h) and
    # does not grow; RK4 drifts at O(h^4). Both shrink with h at their order.
    rate = math.log2(drifts[0] / drifts[1])
    assert rate > order - 0.5, drifts
    assert drifts[1] < (1e-7 if order == 4 else 0.05)


def test_integrator_outcomes_match_capture():
    a = jnp.array([0.0, 0.05, 0.2, math.pi / 2, 3.0, math.pi])
    exact = jl.trace(a, 5.0)
    for m in (jl.RK4(dphi=0.01), jl.DormandPrince(tol=1e-10), jl.Euler()):
        r = jl.trace(a, 5.0, method=m)
        np.testing.assert_array_equal(np.asarray(r.status), np.asarray(exact.status))


def test_integrator_reverse_mode_gradient():
    f = lambda a: jl.trace(a, 20.0, method=jl.RK4(dphi=0.01)).phi  # noqa: E731
    g = jax.grad(f)(0.3)
    ge = jax.grad(lambda a: jl.trace(a, 20.0).phi)(0.3)
    assert abs(float(g) - float(ge)) < 1e-6 * abs(float(ge))
