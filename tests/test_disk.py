"""The thin accretion disk: crossings of the disk plane against the exact orbit, the
redshift of Keplerian emitters against closed forms, and the disk in an image."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as ref

import jaxlens as jl

D = 30.0
_trace = jax.jit(jl.trace_disk)


def _azimuth_at_radius(alpha, d, r):
    """Exact azimuths (both branches: before and after periapsis) at which the ray
    from a static camera at `d` with local angle `alpha` is at radius `r`:
    Phi(alpha, d) - Phi(alpha_r, r), with alpha_r the local angle at r of the same
    impact parameter (inward or outward), from the mpmath reference."""
    b = d * math.sin(alpha) / math.sqrt(1 - 1 / d)
    total = ref.escape_angle(alpha, d, dps=25)[0]
    s = b * math.sqrt(1 - 1 / r) / r
    if s > 1:
        return []
    a_in = math.asin(s)
    return [total - ref.escape_angle(a, r, dps=25)[0] for a in (a_in, math.pi - a_in)]


def _hits(alpha, beta, disk, d=D):
    alpha = jnp.asarray(alpha, jnp.float64)
    beta = jnp.broadcast_to(jnp.asarray(beta, jnp.float64), alpha.shape)
    return _trace(alpha, jnp.cos(beta), jnp.sin(beta), d, disk)


def test_face_on_ring_against_the_exact_orbit():
    # Face-on, every ray meets the plane at azimuth pi/2 from the camera: r = 1/u(pi/2)
    # on the exact orbit, and the same for every beta (the images are exact rings).
    disk = jl.Disk(3.0, 40.0, 0.0, steps=48)
    alpha = np.array([0.15, 0.2, 0.3, 0.45, 0.6])
    h = _hits(alpha, 0.0, disk)
    assert np.all(np.asarray(h.hit)) and np.all(np.asarray(h.crossing) == 0)
    for a, r in zip(alpha, np.asarray(h.radius)):
        phis = _azimuth_at_radius(float(a), D, float(r))
        # RK4, 48 steps a half turn: measured error ~1e-7 rad in azimuth
        assert min(abs(p - math.pi / 2) for p in phis) < 1e-6
    for beta in [0.7, 2.0, -1.3]:
        other = _hits(alpha, beta, disk)
        np.testing.assert_allclose(other.radius, h.radius, rtol=1e-12)
    # Keplerian emitters seen face-on: no line-of-sight motion, L_z = 0, so
    # g = sqrt(1 - 3/(2r)) (gravitational plus transverse Doppler), exactly
    np.testing.assert_allclose(h.g, np.sqrt(1 - 1.5 / np.asarray(h.radius)), rtol=1e-12)


def test_edge_on_far_side_against_the_exact_orbit():
    # Edge-on (camera in the disk plane), every ray out of the plane meets it behind the
    # hole, at azimuth pi: the far side's image, a ring independent of beta.
    disk = jl.Disk(3.0, 40.0, math.pi / 2, steps=48)
    alpha = np.array([0.13, 0.16, 0.2])  # rays bent by more than pi - alpha, outside r_in
    h = _hits(alpha, 0.9, disk)
    assert np.all(np.asarray(h.hit)) and np.all(np.asarray(h.crossing) == 0)
    for a, r in zip(alpha, np.asarray(h.radius)):
        phis = _azimuth_at_radius(float(a), D, float(r))
        assert min(abs(p - math.pi) for p in phis) < 1e-6
    for beta in [0.3, 2.5, -0.8, -2.0]:
        np.testing.assert_allclose(_hits(alpha, beta, disk).radius, h.radius, rtol=1e-9)


@pytest.mark.parametrize("inclination", [0.0, 90.0])
def test_inner_edge_image(inclination):
    # The inner edge r_in = 3 is seen where the exact orbit reaches r = 3 at the crossing
    # azimuth (pi/2 face-on, on the way in; pi edge-on, behind the hole on the way out),
    # found by bisection on the mpmath reference; just outside that angle the disk is
    # hit, just inside it is not.
    target, branch = (math.pi / 2, 0) if inclination == 0.0 else (math.pi, 1)

    def inside(a):
        # True: at the crossing azimuth the ray is already within r = 3
        phis = _azimuth_at_radius(a, D, 3.0)
        if not phis:  # the periapsis is beyond r = 3
            return False
        return phis[branch] < target if branch == 0 else phis[branch] > target

    lo, hi = 0.09, 0.25
    assert inside(lo) and not inside(hi)
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if inside(mid) else (lo, mid)
    edge = 0.5 * (lo + hi)
    disk = jl.Disk(3.0, 40.0, math.radians(inclination))
    # 1e-4 relative in angle is ~1e-3 in radius, far above the RK4 error (~1e-7)
    h = _hits([edge * (1 - 1e-4), edge * (1 + 1e-4)], 1.0, disk)
    assert list(np.asarray(h.hit)) == [False, True]


def test_redshift_of_a_tangential_photon():
    # A photon leaving an emitter along its motion (L_z = +- b at the turning point, b =
    # r / sqrt(1 - 1/r)): in the static frame, Doppler 1/(gamma (1 -+ v)) with the
    # orbital speed v = 1/sqrt(2(r - 1)), then sqrt(1 - 1/r) climbing out.
    for r in [2.0, 3.0, 6.0, 50.0]:
        b = r / math.sqrt(1 - 1 / r)
        v = float(jl.orbital_speed(r))
        gam = float(jl.lorentz_factor(v))
        for sign in (1, -1):
            want = math.sqrt(1 - 1 / r) / (gam * (1 - sign * v))
            assert float(jl.disk_redshift(r, sign * b)) == pytest.approx(want, rel=1e-13)


def test_inclined_disk_images():
    # 80 degrees: the approaching side (+x, the disk turns counter-clockwise about a
    # normal tipped toward the camera and up) is blueshifted; the far side appears above
    # the shadow; rays grazing the shadow meet the disk again (the secondary image).
    disk = jl.Disk(3.0, 20.0, math.radians(80.0), crossings=2)
    rng = np.random.default_rng(0)
    ash = float(jl.shadow_angle(D))
    alpha = ash + rng.uniform(0.0, 0.5, 20000) ** 2
    beta = rng.uniform(-math.pi, math.pi, alpha.size)
    h = _hits(alpha, beta, disk)
    hit, g, k = (np.asarray(x) for x in (h.hit, h.g, h.crossing))
    right, left = hit & (np.cos(beta) > 0.9), hit & (np.cos(beta) < -0.9)
    assert g[right].mean() > 1.0 > g[left].mean()
    # the direct image above the hole comes from behind it (the far side), below from in front
    up = hit & (k == 0) & (np.sin(beta) > 0.9)
    down = hit & (k == 0) & (np.sin(beta) < -0.9)
    assert up.any() and down.any()
    phi = np.asarray(h.azimuth)
    assert np.all(phi[up] > math.pi / 2) and np.all(phi[down] < math.pi / 2)
    second = hit & (k == 1)
    assert second.sum() > 50
    # secondary hits lie close to the shadow edge
    assert np.all(alpha[second] < 1.6 * ash)
    # and vanish when only one crossing is followed
    one = _hits(alpha, beta, dataclasses.replace(disk, crossings=1))
    np.testing.assert_array_equal(np.asarray(one.hit), hit & (k == 0))
    # |L_z| <= b, with the photon's angular momentum about the disk axis
    b = D * np.sin(alpha) / math.sqrt(1 - 1 / D)
    assert np.all(np.abs(np.asarray(h.lz)) <= b * (1 + 1e-12))


def test_only_reachable_rays_hit():
    disk = jl.Disk(3.0, 10.0, math.radians(60.0), crossings=3)
    rng = np.random.default_rng(1)
    alpha = rng.uniform(0.0, 1.0, 20000)
    beta = rng.uniform(-math.pi, math.pi, alpha.size)
    h = _hits(alpha, beta, disk)
    reach = np.asarray(jl.can_reach(jnp.asarray(alpha), D, 10.0))
    assert not np.any(np.asarray(h.hit) & ~reach)
    assert np.any(np.asarray(h.hit))
    bound = jl.disk_angle_bound(D, 10.0)
    assert np.all(alpha[reach] <= bound + 1e-12)


def test_temperature_profile():
    disk = jl.Disk(3.0, 30.0, 0.0, temperature=1e4)
    r = jnp.array([3.0, 3.0 * 49 / 36, 30.0])
    t = np.asarray(disk.temperature_at(r))
    assert t[0] == 0.0
    assert t[1] == pytest.approx(1e4, rel=1e-12)  # the peak, at (7/6)^2 r_in

    def profile(x):  # T / T_peak up to a constant, x = r / r_in
        return x**-0.75 * (1 - x**-0.5) ** 0.25

    peak = profile((7.0 / 6.0) ** 2)
    assert t[2] == pytest.approx(1e4 * profile(10.0) / peak, rel=1e-12)
    with pytest.raises(ValueError, match="r_in"):
        jl.Disk(1.2, 10.0, 0.0)


def test_disk_in_an_image():
    # The compact gather of reachable rays gives the same image as masking all rays, and
    # the disk image is differentiable in the disk's temperature.
    cam = jl.Camera(60.0, math.radians(40), 64, 40)
    disk = jl.Disk(3.0, 12.0, math.radians(80.0))
    scene = jl.Scene(cam, jl.Uniform(0.01), redshift=jl.Redshift("spectral"), disk=disk)
    plan = jl.plan(scene)
    assert plan.disk and plan.disk_rays < 64 * 40 / 2
    img = jl.render(scene)
    rm = eqx.filter_jit(jl.RayMap.build)(cam.distance, accuracy=scene.accuracy)
    masked_plan = dataclasses.replace(plan, disk_rays=None)

    # One compiled program: the masked image (all rays through the disk stage) at a
    # disk temperature, its pixel sum and the sum's reverse-mode derivative in it.
    @jax.jit
    def masked_image_and_grad(t):
        def total(t):
            s = scene.replace(disk=eqx.tree_at(lambda k: k.temperature, disk, t))
            image = jl.render_array(s, plan=masked_plan, ray_map=rm)
            return jnp.sum(image), image

        return jax.value_and_grad(total, has_aux=True)(t)

    assert float(disk.temperature) == 8000.0  # the image below is the scene's own disk
    (_, masked), g = masked_image_and_grad(8000.0)
    np.testing.assert_allclose(img, np.asarray(masked), rtol=1e-6, atol=1e-9)  # f32 output
    assert (img.sum(-1) > 0.05).sum() > 100  # the disk is there

    def loss(t):
        return float(masked_image_and_grad(t)[0][0])

    fd = (loss(8000.0 * (1 + 1e-5)) - loss(8000.0 * (1 - 1e-5))) / (0.16)
    assert float(g) == pytest.approx(fd, rel=1e-4)  # piecewise-linear colour table, tiny step
