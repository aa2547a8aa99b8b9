"""Closed forms of PHYSICS.md against jaxlens' exact escape angle and its helpers."""

import math

import jax.numpy as jnp
import numpy as np
import pytest
import reference as ref

import jaxlens as jl

# PHYSICS.md reference deflections (10 decimals: tolerance 1e-10 plus rounding).
DARWIN = {
    2.6: 6.8103719567,
    3.0: 1.7193883102,
    5.0: 0.5903957876,
    10.0: 0.2361359954,
    100.0: 0.0202999662,
}


def test_carlson_rf_special_values():
    # R_F(0, 1, 2) = K(1/2)/sqrt(2)... use the lemniscate and R_C identities:
    # R_F(x, y, y) = R_C(x, y) = acos(sqrt(x/y)) / sqrt(y - x) for x < y.
    x, y = 0.3, 1.7
    expected = math.acos(math.sqrt(x / y)) / math.sqrt(y - x)
    assert abs(float(jl.carlson_rf(x, y, y)) - expected) < 1e-15
    # R_F(0, 1, 2) = 1.3110287771460599 (DLMF 19.20.1: K(1/sqrt 2) / sqrt 1 ... value tabled)
    from scipy.special import elliprf

    rng = np.random.default_rng(0)
    args = 10.0 ** rng.uniform(-12, 3, (3, 500))
    args[0, :50] = 0.0
    got = np.asarray(jl.carlson_rf(*args))
    want = elliprf(*args)
    np.testing.assert_allclose(got, want, rtol=4e-15)  # a few ulp


@pytest.mark.parametrize("b", sorted(DARWIN))
def test_darwin_reference_values(b):
    got = float(jl.darwin_deflection(b))
    assert abs(got - DARWIN[b]) < 1.5e-10  # table rounded to 1e-10
    assert abs(got - ref.darwin_deflection(b)) < 1e-12 * max(1.0, got)


def test_far_camera_sees_darwin_deflection():
    # A camera at D = 1e12 is at infinity for rays with b ~ 3..100 to ~b/D.
    d = 1e12
    for b in (3.0, 5.0, 10.0):
        alpha = math.asin(b * math.sqrt(1 - 1 / d) / d)
        phi = float(jl.trace(alpha, d, accuracy=1e-12).phi)
        assert abs(phi - (math.pi + DARWIN[b] - alpha)) < 1.5e-10 + 2 * b / d


@pytest.mark.parametrize("d", [1.05, 1.2, 1.4999, 1.5, 1.5001, 3.0, 10.0, 1e3, 1e6])
def test_synge_shadow_separates_capture_from_escape(d):
    ash = float(jl.shadow_angle(d))
    assert abs(ash - ref.shadow_angle(d)) < 1e-14
    r = jl.trace(jnp.array([ash * (1 - 1e-9), ash * (1 + 1e-9)]), d)
    assert bool(r.captured[0]) and bool(r.escaped[1])


def test_shadow_at_three_is_45_degrees():
    assert abs(float(jl.shadow_angle(3.0)) - math.pi / 4) < 1e-15


def test_shadow_of_d10_is_not_the_coordinate_angle():
    # PHYSICS.md: the correct static-observer shadow at D = 10 is 14.27 deg, not 15.01.
    assert abs(math.degrees(float(jl.shadow_angle(10.0))) - 14.27) < 0.005


def test_weak_field_series():
    # deflection - series = O(1/b^4): the next term is ~ (3465 pi / 1024) / b^4 ~ 10.6 / b^4.
    for b in (50.0, 200.0, 1000.0):
        diff = abs(float(jl.darwin_deflection(b)) - float(jl.weak_field_deflection(b)))
        assert diff < 12.0 / b**4


def test_strong_field_limit():
    # Bozza: deflection = -ln(b/b_c - 1) + const - pi + O(b - b_c).
    for eps in (1e-4, 1e-6, 1e-8):
        b = jl.B_CRIT * (1 + eps)
        diff = abs(float(jl.darwin_deflection(b)) - float(jl.strong_field_deflection(b)))
        assert diff < 5.0 * eps * jl.B_CRIT


@pytest.mark.parametrize("b", [2.7, 3.0, 10.0, 1e4])
def test_periapsis_relation(b):
    r0 = float(jl.periapsis(b))
    assert abs(b * b - r0**3 / (r0 - 1)) < 1e-13 * b * b


def _ring_angle(d):
    # Primary Einstein ring: Phi(alpha) = pi on the escaping branch; bisection.
    lo, hi = float(jl.shadow_angle(d)) * (1 + 1e-9), math.pi / 2
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if float(jl.trace(mid, d).phi) > math.pi:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@pytest.mark.parametrize("d, deg", [(10.0, 29.8283), (20.0, 20.2039), (50.0, 12.2928)])
def test_einstein_ring_angles(d, deg):
    assert abs(math.degrees(_ring_angle(d)) - deg) < 6e-5  # table rounded to 1e-4 deg


def test_einstein_ring_weak_field_limit():
    # alpha_E -> sqrt(2/D) (1 + O(D^-1/2)) as D grows.
    for d in (1e4, 1e6):
        rel = _ring_angle(d) / math.sqrt(2 / d) - 1
        assert abs(rel) < 2.0 / math.sqrt(d)
