"""trace(): accuracy against an independent reference, API, transforms and errors."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as ref

import jaxlens as jl

EPS = np.finfo(np.float64).eps


def _hard_rays(n, seed):
    # D log-uniform in [1.2, 1e5]; alpha radial, generic, or grazing the critical
    # angle at relative 1e-10 .. 1e-2, on both sides; inward and outward rays.
    rng = np.random.default_rng(seed)
    d = 10 ** rng.uniform(math.log10(1.2), 5, n)
    ash = np.array([ref.shadow_angle(x) for x in d])
    kind = rng.integers(0, 3, n)
    rel = 10 ** rng.uniform(-10, -2, n) * rng.choice([-1, 1], n)
    alpha = np.where(kind == 0, ash * (1 + rel), rng.uniform(0, math.pi, n))
    alpha = np.where(
        kind == 2, rng.choice([0.0, math.pi / 2, math.pi, 1e-9, math.pi - 1e-9], n), alpha
    )
    return np.clip(alpha, 0.0, math.pi), d, ash


def test_accuracy_1e10_against_quadrature():
    alpha, d, ash = _hard_rays(150, seed=1)
    res = jl.trace(alpha, d, accuracy=1e-10)
    for i in range(alpha.size):
        phi_ref, outcome = ref.escape_angle(alpha[i], d[i])
        # Conditioning: rounding alpha moves phi by ~ eps * alpha / |alpha - alpha_c|.
        cond = EPS * alpha[i] / max(abs(alpha[i] - ash[i]), 1e-300)
        if cond > 1e-10:
            continue
        assert int(res.status[i]) == (jl.ESCAPED if outcome == "escaped" else jl.CAPTURED), i
        if outcome == "escaped":
            assert abs(float(res.phi[i]) - phi_ref) < 1e-9, (alpha[i], d[i])


def test_accuracy_option_selects_setting():
    alpha = jnp.linspace(0.001, 0.5, 300)
    ref12 = jl.trace(alpha, 20.0, method=jl.Exact(iterations=12)).phi
    for acc in (1e-3, 1e-6, 1e-9, 1e-12):
        err = float(jnp.max(jnp.abs(jl.trace(alpha, 20.0, accuracy=acc).phi - ref12)))
        assert err < acc


def test_result_fields_and_broadcasting():
    alpha = jnp.linspace(0.0, math.pi, 4)[None, :]
    d = jnp.array([3.0, 20.0, 1e4])[:, None]
    r = jl.trace(alpha, d)
    assert r.phi.shape == r.status.shape == r.r_min.shape == (3, 4)
    alpha = jnp.broadcast_to(alpha, (3, 4))
    assert r.captured.dtype == jnp.bool_
    assert bool(jnp.all(r.captured[:, 0]))  # alpha = 0 goes straight in
    assert np.all(np.asarray(r.phi[:, -1]) < 1e-14)  # alpha = pi goes straight out
    assert np.all(np.asarray(r.half_turns) >= 0)
    esc_in = r.escaped & (jnp.cos(alpha) > 0)
    assert bool(jnp.all(jnp.where(esc_in, r.r_min > 1.5, True)))  # periapsis outside r = 1.5


@pytest.mark.parametrize("bad", [1.0, 0.5, -3.0, float("nan"), float("inf")])
def test_bad_distance_raises_eagerly(bad):
    with pytest.raises(ValueError, match="distance"):
        jl.trace(0.3, bad)


def test_bad_distance_errors_under_jit():
    f = jax.jit(lambda d: jl.trace(0.3, d).phi)
    assert np.isfinite(float(f(20.0)))
    with pytest.raises(Exception, match="distance must be finite and > 1"):
        jax.block_until_ready(f(0.9))


@pytest.mark.parametrize(
    "alpha, distance",
    [(np.array([0.3 + 0.1j]), 10.0), (np.array([True]), 10.0), (np.array(["0.3"]), 10.0),
     (0.3, np.array([10.0 + 0j])), (np.array([0.3], object), 10.0)],
)  # fmt: skip
def test_non_real_inputs_are_refused(alpha, distance):
    with pytest.raises(TypeError, match="must be real numbers"):
        jl.trace(alpha, distance)


def test_integer_inputs_are_converted():
    got = jl.trace(np.array([0, 1, 3]), 10)
    want = jl.trace(np.array([0.0, 1.0, 3.0]), 10.0)
    assert jnp.issubdtype(got.phi.dtype, jnp.floating)
    np.testing.assert_array_equal(got.phi, want.phi)


def test_bad_options():
    with pytest.raises(ValueError, match="accuracy"):
        jl.trace(0.3, 10.0, accuracy=0.0)
    with pytest.raises(ValueError, match="method"):
        jl.trace(0.3, 10.0, method="leapfrog")


def test_jit_vmap_and_both_gradient_modes():
    alpha = jnp.array([0.2, 0.9, 1.7, 2.8])
    d = jnp.array([4.0, 10.0, 30.0, 1e3])
    f = lambda a, x: jl.trace(a, x, accuracy=1e-12).phi  # noqa: E731
    direct = f(alpha, d)
    # XLA fuses differently under jit: a few ulp apart
    np.testing.assert_allclose(jax.jit(f)(alpha, d), direct, rtol=0, atol=4 * EPS * 8)
    np.testing.assert_allclose(jax.vmap(f)(alpha, d), direct, rtol=0, atol=1e-14)
    grad_a = jax.vmap(jax.grad(f, argnums=(0, 1)))(alpha, d)
    fwd_a = jax.vmap(jax.jacfwd(f, argnums=(0, 1)))(alpha, d)
    for h, (ga, gd), (fa, fd) in zip([1e-6], [grad_a], [fwd_a]):
        np.testing.assert_allclose(ga, fa, rtol=1e-12)
        # d phi / dD is a difference of terms ~ phi / D: round-off ~ eps phi / D
        np.testing.assert_allclose(gd, fd, rtol=1e-12, atol=4 * EPS * np.pi / float(d.max()))
        # central differences: error ~ h^2 phi''' + eps/h ~ 1e-10 relative
        fd_a = (f(alpha + h, d) - f(alpha - h, d)) / (2 * h)
        fd_d = (f(alpha, d * (1 + h)) - f(alpha, d * (1 - h))) / (2 * h * d)
        np.testing.assert_allclose(ga, fd_a, rtol=2e-7)
        # FD round-off: ~ eps |phi| / (h D), large where dphi/dD is tiny (D = 1e3)
        np.testing.assert_allclose(
            gd, fd_d, rtol=2e-6, atol=float(jnp.max(10 * EPS * direct / (h * d)))
        )


@pytest.mark.parametrize("n", [10, 60_000])  # the exact method; the table
def test_host_rays_held_by_a_jitted_function_are_part_of_its_program(n):
    # Rays and a distance the function holds (NumPy, Python numbers) are concrete
    # inside its trace: traced with it, not run as trace's own compiled programs (a
    # nested jit with XLA options, which JAX refuses).
    alpha = np.linspace(0.1, 3.0, n)
    inside = jax.jit(lambda: jl.trace(alpha, 10.0).phi)()
    np.testing.assert_allclose(inside, jl.trace(alpha, 10.0).phi, rtol=1e-12, atol=1e-12)
    table = eqx.filter_jit(jl.RayMap.build)(5.0, accuracy=1e-8)  # a static distance
    np.testing.assert_allclose(table.phi, jl.RayMap.build(5.0, accuracy=1e-8).phi, rtol=1e-12)


def test_float64_needed_for_accuracy_is_the_inputs_dtype():
    r = jl.trace(jnp.float32(0.3), jnp.float32(20.0))
    assert r.phi.dtype == jnp.float32
    r = jl.trace(0.3, 20.0)
    assert r.phi.dtype == jnp.float64


@pytest.mark.parametrize(
    "method, tol",
    [
        (jl.Euler(), 0.3),  # the original program: first order, dphi = 0.003
        (jl.RK4(dphi=0.02), 2.0 * 0.02**4 * 5),
        (jl.DormandPrince(tol=1e-10), 1e-6),
        ("rk4", 1e-6),
        ("dopri5", 1e-6),
    ],
)
def test_integrators_agree_with_exact(method, tol):
    alpha = jnp.concatenate([jnp.linspace(0.001, 0.5, 40), jnp.linspace(1.0, 3.1, 20)])
    exact = jl.trace(alpha, 20.0, method="exact", accuracy=1e-12)
    r = jl.trace(alpha, 20.0, method=method, accuracy=1e-6)
    np.testing.assert_array_equal(np.asarray(r.status), np.asarray(exact.status))
    err = jnp.abs(r.phi - exact.phi)
    assert float(jnp.max(jnp.where(exact.escaped, err, 0.0))) < tol


def test_step_budget_is_reported_not_painted():
    r = jl.trace(jnp.array([0.3, 2.0]), 20.0, method=jl.RK4(dphi=0.01, max_steps=50))
    assert bool(jnp.all(r.unresolved))
    assert bool(jnp.all(jnp.isfinite(r.phi)))


def test_winding_budget():
    ash = float(jl.shadow_angle(20.0))
    r = jl.trace(jnp.array([ash * (1 + 1e-12), 0.3]), 20.0, max_windings=2.0)
    assert bool(r.unresolved[0]) and bool(r.escaped[1])
    assert float(r.phi[0]) == pytest.approx(4 * math.pi)


def test_method_objects_are_pytrees():
    m = jl.RK4(dphi=0.05)
    leaves, _ = jax.tree.flatten(m)
    assert leaves == []  # settings are static: they fix the compiled program
    assert eqx.tree_equal(m, jl.RK4(dphi=0.05))


def test_jitted_derivatives_match_eager_on_a_random_batch():
    # Regression: fused under jit, XLA:CPU once miscompiled the forward-mode derivative
    # of jnp.cbrt inside the closed form (errors of 30 % on a few lanes).
    rng = np.random.default_rng(0)
    a = jnp.asarray(rng.uniform(0, math.pi, 4000))
    d = jnp.asarray(10 ** rng.uniform(0.0001, 4, 4000))

    def tangents(a, d):
        f = lambda a, d: jl.trace(a, d).phi  # noqa: E731
        return jax.jvp(f, (a, d), (jnp.ones_like(a), jnp.zeros_like(d)))[1]

    eager, jitted = np.asarray(tangents(a, d)), np.asarray(jax.jit(tangents)(a, d))
    rel = np.abs(eager - jitted) / np.maximum(np.abs(eager), 1e-300)
    assert np.max(rel) < 1e-7  # rounding differences of fusion only, amplified near alpha_c


def test_ray_status_messages():
    # One item per outcome, each with its own message; the unresolved one names both
    # budgets, so a user who sees it knows which option to raise.
    items = [jl.RayStatus.escaped, jl.RayStatus.captured, jl.RayStatus.unresolved]
    assert len(jl.RayStatus) == 3
    messages = [jl.RayStatus[item] for item in items]
    assert len(set(messages)) == 3
    assert "escaped" in messages[0] and "horizon" in messages[1]
    assert "winding budget" in messages[2] and "step budget" in messages[2]
    assert bool(jl.RayStatus.unresolved == jl.RayStatus.unresolved)
    assert not bool(jl.RayStatus.unresolved == jl.RayStatus.captured)


def test_throw_raises_the_unresolved_message():
    # Out of budget is data by default; throw=True turns it into RayStatus.unresolved's
    # message, eagerly and under jit; captured and escaped rays are not failures.
    message = "beyond the winding budget"
    a = jnp.array([0.3, 2.0])
    r = jl.trace(a, 20.0, method=jl.RK4(dphi=0.01, max_steps=50))
    assert bool(jnp.all(r.status == jl.UNRESOLVED))
    with pytest.raises(Exception, match=message):
        jl.trace(a, 20.0, method=jl.RK4(dphi=0.01, max_steps=50), throw=True)
    f = jax.jit(lambda d: jl.trace(jnp.array([0.0, 0.3]), d, max_windings=0.2, throw=True).phi)
    with pytest.raises(Exception, match=message):
        jax.block_until_ready(f(20.0))
    ok = jl.trace(jnp.array([0.0, 0.3]), 20.0, throw=True)  # one captured, one escaped
    assert [int(s) for s in ok.status] == [jl.CAPTURED, jl.ESCAPED]
