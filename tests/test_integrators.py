"""The integrators of u'' = 1.5 u^2 - u: their tableaux (order conditions), convergence
order, the first integral, and the abstract bases."""

import itertools
import math
from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl

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


def _first_integral(u, v):
    # G = u'^2 + u^2 - u^3, conserved by the orbit equation u'' = 1.5 u^2 - u.
    return v * v + u * u - u * u * u


def _orbit_states(cls, h, n):
    # March one orbit with the method's own step and record (u, v).
    u0 = 1.0 / D
    alpha = 0.3
    v0 = u0 * math.sqrt(1 - u0) / math.tan(alpha)
    method = cls(dphi=h)

    def body(carry, _):
        u, v = method.step(*carry)
        return (u, v), (u, v)

    _, (u, v) = jax.lax.scan(body, (jnp.float64(u0), jnp.float64(v0)), None, length=n)
    return u, v, u0 * u0 * (1 - u0) / math.sin(alpha) ** 2  # G = 1/b^2 at the camera


@pytest.mark.parametrize("cls, order", [(jl.RK4, 4), (jl.Euler, 1)])
def test_first_integral_conserved(cls, order):
    drifts = []
    for h in (0.02, 0.01):
        u, v, g0 = _orbit_states(cls, h, int(2.0 / h))  # 2 radians of the orbit
        drifts.append(float(jnp.max(jnp.abs(_first_integral(u, v) - g0))) / g0)
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


# ---------------------------------------------------------------------------
# The tableaux: Butcher's order conditions, exactly in rational arithmetic.


def _trees(order):
    """Rooted trees with `order` nodes, each a sorted tuple of its children's trees."""
    if order == 1:
        return [()]
    found = set()
    # The children of the root: a multiset of trees whose sizes sum to order - 1.
    for sizes in _partitions(order - 1):
        for kids in itertools.product(*(_trees(k) for k in sizes)):
            found.add(tuple(sorted(kids)))
    return sorted(found)


def _partitions(n, largest=None):
    largest = n if largest is None else largest
    if n == 0:
        yield ()
        return
    for k in range(min(n, largest), 0, -1):
        for rest in _partitions(n - k, k):
            yield (k, *rest)


def _size(tree):
    return 1 + sum(_size(t) for t in tree)


def _density(tree):  # gamma(t): the tree's size times its subtrees' densities
    return _size(tree) * math.prod(_density(t) for t in tree)


def _weights(a, tree):
    # Phi_i(t) = prod over children t' of sum_j a_ij Phi_j(t'), per stage i.
    stages = len(a)
    w = [Fraction(1)] * stages
    for child in tree:
        inner = _weights(a, child)
        w = [w[i] * sum(a[i][j] * inner[j] for j in range(i)) for i in range(stages)]
    return w


def _as_fractions(rows):
    return [[Fraction(x).limit_denominator(10**7) for x in row] for row in rows]


TABLEAUX = [(jl.Euler, 1), (jl.RK4, 4), (jl.DormandPrince, 5)]


@pytest.mark.parametrize("cls, order", TABLEAUX)
def test_tableau_rows_sum_to_nodes(cls, order):
    t = cls.tableau
    assert t.order == order
    for row, c in zip(t.a, t.c):
        assert abs(sum(row) - c) < 1e-15  # the coefficients are exact to 1 ulp of 1


@pytest.mark.parametrize("cls, order", TABLEAUX)
def test_tableau_meets_order_conditions(cls, order):
    # b . Phi(t) = 1 / gamma(t) for every rooted tree t with at most `order` nodes
    # (1, 1, 2, 4, 9 trees of orders 1..5: sum b = 1, sum b c = 1/2, ...), and fails
    # for at least one tree of the next order (the order is not understated). The
    # floats are read back as the fractions they were written as (denominators < 1e7).
    t = cls.tableau
    a, (b,) = _as_fractions(t.a), _as_fractions([t.b])
    a = [row + [Fraction(0)] * (len(b) - len(row)) for row in a]

    def residuals(weights_b, k):
        return [
            sum(bi * w for bi, w in zip(weights_b, _weights(a, tree))) - Fraction(1, _density(tree))
            for tree in _trees(k)
        ]

    for k in range(1, order + 1):
        assert all(r == 0 for r in residuals(b, k)), (k, residuals(b, k))
    if t.a_velocity is None:  # a partitioned method has its own conditions above 1
        assert any(r != 0 for r in residuals(b, order + 1))
    if t.b_error is not None:
        # The embedded solution b* = b - b_error is one order lower.
        (e,) = _as_fractions([t.b_error])
        b_star = [bi - ei for bi, ei in zip(b, e)]
        for k in range(1, order):
            assert all(r == 0 for r in residuals(b_star, k)), k
        assert any(r != 0 for r in residuals(b_star, order))


def test_tree_counts():
    # The numbers of rooted trees (OEIS A000081), so the conditions above are complete.
    assert [len(_trees(k)) for k in range(1, 6)] == [1, 1, 2, 4, 9]


def test_euler_tableau_is_symplectic_euler():
    # The partitioned pair (a, a_velocity) is symplectic:
    # b_i ahat_ij + b_j a_ji - b_i b_j = 0 for all i, j (Hairer, Lubich & Wanner, VI.4).
    t = jl.Euler.tableau
    n = len(t.b)
    a = [list(row) + [0.0] * (n - len(row)) for row in t.a]
    ahat = [list(row) + [0.0] * (n - len(row)) for row in t.a_velocity]
    for i in range(n):
        for j in range(n):
            assert t.b[i] * ahat[i][j] + t.b[j] * a[j][i] - t.b[i] * t.b[j] == 0.0
    # and one step is v += h f(u); u += h v, the original C++ scheme, to the last bit.
    u, v, h = 0.05, -0.01, 0.003
    v1 = v + h * (1.5 * u * u - u)
    got = jl.Euler(dphi=h).step(jnp.float64(u), jnp.float64(v))
    assert (float(got[0]), float(got[1])) == (u + h * v1, v1)


def test_user_tableau_converges_at_its_order():
    # A scheme is data: Kutta's third-order method, defined with the public API, traces
    # through the same loop and converges at order 3.
    class Kutta3(jl.AbstractIntegrator):
        tableau = jl.ButcherTableau(
            a=((), (0.5,), (-1.0, 2.0)), b=(1 / 6, 2 / 3, 1 / 6), c=(0.0, 0.5, 1.0), order=3
        )
        tol = None
        dphi: float = 0.01
        max_steps: int = 40_000

    errs = [_err(Kutta3(dphi=h)) for h in (0.04, 0.02, 0.01)]
    rates = [math.log2(errs[i] / errs[i + 1]) for i in range(2)]
    for r in rates:  # as in test_convergence_order
        assert abs(r - 3) < 0.3, (errs, rates)


def test_tableau_shape_is_checked():
    with pytest.raises(ValueError, match="strictly lower triangular"):
        jl.ButcherTableau(a=((), (0.5, 0.5)), b=(0.5, 0.5), c=(0.0, 1.0), order=1)
    with pytest.raises(ValueError, match="b_error"):
        jl.ButcherTableau(a=((), (1.0,)), b=(0.5, 0.5), c=(0.0, 1.0), order=2, b_error=(1.0,))


# ---------------------------------------------------------------------------
# The abstract bases.


@pytest.mark.parametrize("cls", [jl.AbstractMethod, jl.AbstractIntegrator])
def test_abstract_methods_cannot_be_built(cls):
    with pytest.raises(TypeError):
        cls()


@pytest.mark.parametrize("cls", [jl.Exact, jl.Table, jl.Euler, jl.RK4, jl.DormandPrince])
def test_methods_are_final_and_override_nothing(cls):
    assert getattr(cls, "__final__", False)
    # No concrete method of a base is overridden (equinox's abstract/final pattern).
    for base in cls.__mro__[1:]:
        for name, value in vars(base).items():
            if callable(value) and not getattr(value, "__isabstractmethod__", False):
                if not name.startswith("__") or name == "__call__":
                    assert name not in vars(cls), (cls, base, name)
