"""Hard rays of issue 6: grazing the photon sphere, radial, cameras at the edges."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as ref

import jaxlens as jl

EPS = np.finfo(np.float64).eps


@pytest.mark.parametrize("d", [1.2, 3.0, 20.0, 1e4])
@pytest.mark.parametrize("side", [-1, 1])
def test_rays_within_1e12_of_critical(d, side):
    ash = ref.shadow_angle(d)
    alpha = ash * (1 + side * 1e-12)
    r = jl.trace(alpha, d, accuracy=1e-10)
    phi_ref, outcome = ref.escape_angle(alpha, d)
    assert int(r.status) == (jl.ESCAPED if outcome == "escaped" else jl.CAPTURED)
    # conditioning: eps * alpha / |alpha - alpha_c| = eps / 1e-12 ~ 2e-4 rad
    assert abs(float(r.phi) - phi_ref) < 3 * EPS / 1e-12
    assert float(r.phi) > 4 * math.pi  # several windings, not painted black


def test_radial_and_tangential_rays():
    d = 20.0
    r = jl.trace(jnp.array([0.0, math.pi, math.pi / 2]), d, accuracy=1e-12)
    assert bool(r.captured[0]) and float(r.phi[0]) == 0.0  # straight in
    assert bool(r.escaped[1]) and abs(float(r.phi[1])) < 1e-15  # straight out
    phi_ref, _ = ref.escape_angle(math.pi / 2, d)  # starts at periapsis
    assert abs(float(r.phi[2]) - phi_ref) < 1e-13
    assert abs(float(r.r_min[2]) - d) < 1e-12 * d


@pytest.mark.parametrize("d", [1 + 1e-9, 1.0001, 1.2, 1.5, 1.5 - 1e-9, 1.5 + 1e-9, 1e8, 1e12])
def test_extreme_cameras_against_reference(d):
    ash = ref.shadow_angle(d)
    alphas = [math.pi, 0.5 * (ash + math.pi), ash * (1 + 1e-6), ash * (1 - 1e-6), 1e-3 * ash]
    if d > 2:
        alphas += [min(3 * ash, 3.0), 1.2 * ash]
    r = jl.trace(jnp.array(alphas), d, accuracy=1e-10)
    for i, a in enumerate(alphas):
        phi_ref, outcome = ref.escape_angle(a, d)
        assert int(r.status[i]) == (jl.ESCAPED if outcome == "escaped" else jl.CAPTURED), a
        cond = EPS * a / abs(a - ash)
        assert abs(float(r.phi[i]) - phi_ref) < 1e-8 + 3 * cond, (a, float(r.phi[i]), phi_ref)


def test_photon_sphere_camera_tangential_ray():
    # At D = 1.5 the float alpha = pi/2 lies 6e-17 inside the critical angle: b/b_c - 1
    # is -2e-33 (computed exactly from cos^2 alpha), so the ray winds 6 times and falls in.
    r = jl.trace(math.pi / 2, 1.5)
    phi_ref, outcome = ref.escape_angle(math.pi / 2, 1.5, dps=60)
    assert outcome == "captured" and bool(r.captured)
    assert abs(float(r.phi) - phi_ref) < 1e-5  # a double root of P 1e-33 away
    # With a smaller winding budget it is flagged, never painted as captured.
    r = jl.trace(math.pi / 2, 1.5, max_windings=2.0)
    assert bool(r.unresolved) and float(r.phi) == 4 * math.pi


@pytest.mark.parametrize("d", [1e8, 1e12])
def test_weak_field_limit_far_camera(d):
    # The microarcsecond ring regime: bending Phi - (pi - alpha) to relative 1e-9 of the
    # quadrature value, at the Einstein ring and 10x outside it (no cancellation in
    # 1 - 1/D, sqrt(G) or pi - alpha).
    for a in (math.sqrt(2 / d), 10 * math.sqrt(2 / d)):
        bend = float(jl.trace(a, d, accuracy=1e-12).phi) - (math.pi - a)
        bend_ref = ref.deflection_mp(a, d)
        # float64 phi ~ pi carries 4.4e-16 absolute: relative 1e-9 needs bend > 4e-7
        assert abs(bend - bend_ref) < 1e-9 * abs(bend_ref) + 2 * EPS * math.pi
        b = float(jl.impact_parameter(a, d))
        # first order: (1 + sqrt(1 - b^2/D^2)) / b, corrections O(1/b^2)
        weak = (1 + math.sqrt(1 - (b / d) ** 2)) / b
        assert abs(bend - weak) < 3.0 / b**2


def test_gradients_finite_everywhere():
    alpha = jnp.concatenate(
        [
            jnp.array([0.0, 1e-300, math.pi / 2, math.pi]),
            jnp.linspace(0.0, math.pi, 301),
        ]
    )

    # One program for every distance (an argument): 6 s, where eager, op by op, the
    # twelve gradients took 26 s.
    @jax.jit
    def grads(d):
        ga = jax.vmap(jax.grad(lambda a: jl.trace(a, d).phi))(alpha)
        gd = jax.vmap(jax.grad(lambda x, a: jl.trace(a, x).phi), (None, 0))(d, alpha)
        return ga, gd

    for d in (1 + 1e-9, 1.2, 1.5, 3.0, 20.0, 1e12):
        ga, gd = grads(d)
        assert bool(jnp.all(jnp.isfinite(ga))) and bool(jnp.all(jnp.isfinite(gd))), d


@pytest.mark.parametrize("fov_deg, d", [(1.0 / 3600.0, 1e12), (179.0, 3.0)])
def test_tiny_and_huge_fields_of_view(fov_deg, d):
    # 1 arcsecond at D = 1e12 (the ring is 0.29 arcsec) and 179 degrees at D = 3: the
    # ring of a star behind the hole sits where the exact Einstein angle says.
    w = h = 96
    fov = math.radians(fov_deg)
    cam = jl.Camera(d, fov, w, h, supersample=2)
    lo, hi = float(jl.shadow_angle(d)) * (1 + 1e-9), math.pi / 2
    for _ in range(80):  # Einstein angle: phi(alpha) = pi
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if float(jl.trace(mid, d).phi) > math.pi else (lo, mid)
    ring = 0.5 * (lo + hi)
    sigma = 0.02 * ring if fov_deg < 1 else math.radians(1.0)
    img = np.asarray(jl.render_array(cam, jl.GaussianStar(sigma)))[..., 0]
    assert np.all(np.isfinite(img))
    f = (w / 2) / math.tan(fov / 2)
    y, x = np.mgrid[0:h, 0:w]
    r = np.hypot(x + 0.5 - w / 2, y + 0.5 - h / 2)
    r_ring = float(np.sum(img * r) / np.sum(img))  # intensity-weighted radius, px
    # the ring's width and pixelisation bias the mean radius by < ~1 px here
    assert abs(r_ring - f * math.tan(ring)) < 1.5


def test_pixel_gradient_wrt_distance_matches_finite_differences():
    # Rendered pixels against a non-zero floor (so the shadow edge contributes through
    # its coverage) differentiated w.r.t. the camera distance through the ray map's
    # knots: forward mode against central differences (h = 1e-4: error ~ h^2 g''' and
    # eps / h, both < 1e-9 here), finite everywhere.
    sky = jl.GaussianStar(math.radians(2.0)) + jl.Uniform(0.1)

    def image(d):
        cam = jl.Camera(d, math.radians(60.0), 24, 16, supersample=2)
        return jl.render_array(cam, sky, accuracy=1e-6)[..., 0]

    # One compiled program gives the pixels and their forward-mode derivative (a jvp
    # along d: the one column jacfwd builds, without its vmap over a basis); the
    # differences use its pixels at d +- h, so nothing else is compiled or run eagerly.
    pixels_and_slope = jax.jit(lambda d: jax.jvp(image, (d,), (jnp.ones_like(d),)))
    g = pixels_and_slope(20.0)[1]
    h = 1e-4
    fd = (pixels_and_slope(20.0 + h)[0] - pixels_and_slope(20.0 - h)[0]) / (2 * h)
    assert bool(jnp.all(jnp.isfinite(g)))
    assert float(jnp.max(jnp.abs(g))) > 0.1  # the ring and the edge do move with D
    np.testing.assert_allclose(np.asarray(g), np.asarray(fd), rtol=0, atol=1e-8)
