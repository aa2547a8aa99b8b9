"""The ray-map table: interpolation error against the exact closed form, and gradients."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl

EPS = np.finfo(np.float64).eps


@functools.cache
def _build(accuracy):
    return jax.jit(lambda d: jl.RayMap.build(d, accuracy=accuracy))


_exact = jax.jit(lambda a, d: jl.trace(a, d, method=jl.Exact(iterations=10)))


@pytest.mark.parametrize("d", [1.0001, 1.2, 1.5, 3.0, 20.0, 1e3, 1e5, 1e8, 1e12])
@pytest.mark.parametrize("accuracy", [1e-6, 1e-10])
def test_table_matches_exact(d, accuracy):
    rm = _build(accuracy)(d)
    ash = float(rm.alpha_sh)
    rng = np.random.default_rng(0)
    alpha = np.concatenate(
        [
            ash + (math.pi - ash) * rng.uniform(0, 1, 3000),  # anywhere outside the shadow
            ash * (1 + 10 ** rng.uniform(-12, 0, 3000)),  # grazing the shadow edge
            ash * (1 - 10 ** rng.uniform(-12, -1, 500)),  # inside the shadow
            [math.pi, math.pi / 2, ash],
        ]
    )
    alpha = np.clip(alpha, 0.0, math.pi)
    exact = _exact(alpha, d)
    got = jax.jit(lambda r, a: r(a))(rm, alpha)
    # status: the table decides by alpha vs alpha_sh; only alpha == alpha_sh may differ
    same = np.asarray(got.status) == np.asarray(exact.status)
    assert np.all(same | (alpha == ash))
    esc = np.asarray(exact.escaped) & (alpha != ash)
    err = np.abs(np.asarray(got.phi - exact.phi))[esc]
    # Allowed: the requested accuracy plus the conditioning of phi near the edge.
    cond = 3 * EPS * alpha[esc] / np.maximum(np.abs(alpha[esc] - ash), 1e-300)
    assert np.all(err <= accuracy + cond)


def test_table_gradient_wrt_distance():
    # d phi / dD through the table (knots move with D) matches the exact closed form.
    alpha = jnp.array([0.15, 0.3, 0.6, 1.2])

    def table(d):
        return jl.RayMap.build(d, accuracy=1e-10).escape_angle(alpha)

    def exact(d):
        return jl.trace(alpha, d, accuracy=1e-12).phi

    # Jitted, each one program (eager, the build's operations compile one by one: 24 s
    # for the three, 16 s jitted).
    want = jax.jit(jax.jacfwd(exact))(20.0)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(table))(20.0), want, rtol=1e-6)
    np.testing.assert_allclose(jax.jit(jax.jacrev(table))(20.0), want, rtol=1e-6)


def test_table_method_through_trace():
    alpha = jnp.linspace(0.13, 3.0, 500)
    a = jl.trace(alpha, 20.0, method="table", accuracy=1e-9)
    b = jl.trace(alpha, 20.0, method="exact", accuracy=1e-12)
    np.testing.assert_array_equal(np.asarray(a.status), np.asarray(b.status))
    assert float(jnp.max(jnp.abs(a.phi - b.phi))) < 1e-9


def test_eager_table_trace_keeps_the_table_of_its_distance():
    # Called eagerly, the table method builds the table of a distance once (its own
    # program), looks the rays up in another, and gives what the jitted call gives.
    from jaxlens import _raymap

    alpha = np.linspace(0.13, 3.0, 3000)
    _raymap._tabulated_recent.cache_clear()
    first = jl.trace(alpha, 17.0, method="table", accuracy=1e-9)
    again = jl.trace(alpha[:100], 17.0, method="table", accuracy=1e-9)
    other = jl.trace(alpha[:100], 18.0, method="table", accuracy=1e-9)
    info = _raymap._tabulated_recent.cache_info()
    assert (info.misses, info.hits) == (2, 1)
    jitted = jax.jit(lambda a: jl.trace(a, 17.0, method="table", accuracy=1e-9))(alpha)
    for got, want in zip(jax.tree.leaves(first), jax.tree.leaves(jitted), strict=True):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(np.asarray(again.phi), np.asarray(first.phi)[:100])
    assert not np.array_equal(np.asarray(other.phi), np.asarray(again.phi))


def _primitives(jaxpr) -> set:
    """The names of the primitives in `jaxpr` and in every jaxpr nested in it."""
    names = set()
    for eqn in jaxpr.eqns:
        names.add(eqn.primitive.name)
        for param in eqn.params.values():
            for sub in param if isinstance(param, list | tuple) else [param]:
                inner = sub if hasattr(sub, "eqns") else getattr(sub, "jaxpr", None)
                if inner is not None and hasattr(inner, "eqns"):
                    names |= _primitives(inner)
    return names


def test_a_distance_fixed_under_jit_has_its_table_built_once():
    # A distance known when a program is traced: its table is built then, kept with the
    # eager ones, and read as a constant; the program holds the look-up alone (no
    # closed form, whose roots take square roots). A traced distance builds it inside.
    from jaxlens import _raymap

    alpha = jnp.linspace(0.13, 3.0, 64)
    _raymap._tabulated_recent.cache_clear()
    fixed = jax.make_jaxpr(lambda a: jl.trace(a, 16.0, method="table", accuracy=1e-9))(alpha)
    assert _raymap._tabulated_recent.cache_info().misses == 1
    jax.make_jaxpr(lambda a: jl.trace(a, 16.0, method="table", accuracy=1e-9).phi)(alpha)
    assert _raymap._tabulated_recent.cache_info().hits == 1
    traced = jax.make_jaxpr(
        lambda a, d: jl.trace(a, d, method="table", accuracy=1e-9).phi
    )(alpha, 16.0)  # fmt: skip
    assert "sqrt" not in _primitives(fixed.jaxpr)
    assert "sqrt" in _primitives(traced.jaxpr)
    ours = jax.jit(lambda a: jl.trace(a, 16.0, method="table", accuracy=1e-9))(alpha)
    built = jax.jit(lambda a, d: jl.trace(a, d, method="table", accuracy=1e-9))(alpha, 16.0)
    for got, want in zip(jax.tree.leaves(ours), jax.tree.leaves(built), strict=True):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-13)


def test_a_nan_ray_is_unresolved_not_captured():
    # A NaN angle reads no knot: NaN escape angle, and an unresolved ray in the whole
    # result (not a captured one with the first knot's azimuth), eagerly and jitted.
    table = jl.RayMap.build(20.0, accuracy=1e-9, captured=True)
    alpha = jnp.array([np.nan, 0.3, 0.05])
    for call in (lambda m, a: m(a), jax.jit(lambda m, a: m(a))):
        r = call(table, alpha)
        assert bool(r.unresolved[0]) and not bool(r.unresolved[1])
        assert not bool(r.captured[0]) and bool(r.captured[2])
    phi = np.asarray(table.escape_angle(alpha))
    assert np.isnan(phi[0]) and np.all(np.isfinite(phi[1:]))


def test_the_look_up_compiled_ahead_is_the_one_the_table_trace_runs(jax_events):
    # An eager table trace compiles its look-up on a thread while the table's program
    # compiles: the trace must then find it compiled (one compile, not a second).
    with jax_events("/jax/core/compile/backend_compile_duration") as compiled:
        r = jl.trace(np.linspace(0.05, 3.0, 70_001), 19.0, accuracy=1e-7)  # a new bucket
    assert compiled.count("jit(_through_map)") == 1, compiled
    assert r.phi.shape == (70_001,) and not np.any(np.asarray(r.unresolved))


def test_table_needs_scalar_distance():
    with pytest.raises(ValueError, match="scalar distance"):
        jl.RayMap.build(jnp.array([10.0, 20.0]))


def test_auto_uses_the_table_for_many_rays_with_the_same_answers():
    # One distance and >= 50,000 rays: 'auto' tabulates both sides; the captured side
    # reports the horizon azimuth like the closed form does.
    alpha = jnp.linspace(0.0, math.pi, 60_001)
    auto = jax.jit(lambda a: jl.trace(a, 20.0, accuracy=1e-9))(alpha)
    exact = _exact(alpha, 20.0)
    ash = float(jl.shadow_angle(20.0))
    ok = np.abs(np.asarray(alpha) - ash) > 1e-6 * ash  # conditioning allows ~2e-10 there
    np.testing.assert_array_equal(np.asarray(auto.status)[ok], np.asarray(exact.status)[ok])
    assert float(jnp.max(jnp.abs(auto.phi - exact.phi)[ok])) < 1e-9


def test_table_periapsis_matches_closed_form():
    alpha = jnp.linspace(0.13, 3.0, 2000)
    t = jl.RayMap.build(20.0, accuracy=1e-10, captured=True)(alpha)
    e = _exact(alpha, 20.0)
    esc = np.asarray(e.escaped)
    np.testing.assert_allclose(np.asarray(t.r_min)[esc], np.asarray(e.r_min)[esc], rtol=1e-9)
