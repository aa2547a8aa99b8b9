"""Point sources: image positions from the lens equation on the ray map, magnification
from the autodiff Jacobian, against the weak-field point lens and the exact closed form."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as ref

import jaxlens as jl

ACC = 1e-10  # ray-map accuracy (radians)
_build = eqx.filter_jit(jl.RayMap.build)  # one compiled builder for every distance


def ray_map(d):
    return _build(jnp.asarray(d, jnp.float64), accuracy=ACC)


def _sources(theta):
    theta = jnp.atleast_1d(jnp.asarray(theta, jnp.float64))
    return jnp.stack([jnp.sin(theta), jnp.zeros_like(theta), jnp.cos(theta)], -1)


def _exact_phi(alpha, d):
    """Escape angle by mpmath quadrature (tests/reference.py), elementwise."""
    a = np.asarray(alpha, np.float64)
    return np.vectorize(lambda x: ref.escape_angle(float(x), float(d), dps=25)[0])(a)


def _point_lens(u, d):
    te = math.sqrt(2 / d)
    th = u * te
    return (th + np.sqrt(th**2 + 4 * te**2)) / 2, (np.sqrt(th**2 + 4 * te**2) - th) / 2


U = np.array([0.2, 0.5, 1.0, 2.0, 4.0])


def test_images_solve_the_lens_equation_exactly():
    for d in [4.0, 20.0, 1e3]:
        theta = np.array([0.01, 0.3, 1.0, 2.5, 3.0])
        im = jl.point_source_images(_sources(theta), ray_map(d))
        alpha = np.asarray(im.alpha)
        exact = _exact_phi(alpha, d)
        # primary: Phi = pi - theta; secondary: Phi = pi + theta, to the table's accuracy
        np.testing.assert_allclose(exact[0], math.pi - theta, atol=10 * ACC)
        np.testing.assert_allclose(exact[1], math.pi + theta, atol=10 * ACC)
        assert np.all(alpha > float(jl.shadow_angle(d)))
        np.testing.assert_allclose(np.asarray(im.beta[1] - im.beta[0]), math.pi, atol=1e-15)


def test_relativistic_images():
    d = 20.0
    theta = np.array([0.2, 0.6, 1.0, 2.0, 3.0])
    im = jl.point_source_images(_sources(theta), ray_map(d), order=1)
    exact = _exact_phi(im.alpha, d)
    np.testing.assert_allclose(exact[0], 3 * math.pi - theta, atol=1e-8)
    np.testing.assert_allclose(exact[1], 3 * math.pi + theta, atol=1e-8)
    # they hug the shadow edge and are strongly demagnified
    ash = float(jl.shadow_angle(d))
    assert np.all(np.asarray(im.alpha) < ash * 1.03)
    assert np.all(np.abs(np.asarray(im.magnification)) < 1e-2)


@pytest.mark.parametrize("d", [1e4, 1e6])
def test_weak_field_point_lens(d):
    te = math.sqrt(2 / d)
    im = jl.point_source_images(_sources(U * te), ray_map(d))
    ap, am = _point_lens(U, d)
    mp, mm = (np.asarray(x) for x in jl.point_lens_magnification(U))
    # Corrections to the point lens are O(theta_E): the next deflection term,
    # (15 pi / 16) / b^2 against 2 / b, is (15 pi / 32) / b of it, b = D alpha.
    b = d * np.minimum(ap, am)
    rel = 3 * (15 * math.pi / 32) / b
    np.testing.assert_allclose(np.asarray(im.alpha[0]), ap, rtol=rel.max())
    np.testing.assert_allclose(np.asarray(im.alpha[1]), am, rtol=rel.max())
    mu = np.asarray(im.magnification)
    assert np.all(np.abs(mu[0] / mp - 1) < rel)
    assert np.all(np.abs(mu[1] / mm - 1) < rel)
    assert np.all(mu[1] < 0)  # the secondary image is mirrored
    total = np.abs(mu).sum(axis=0)
    want = (U**2 + 2) / (U * np.sqrt(U**2 + 4))
    assert np.all(np.abs(total / want - 1) < rel)


def test_point_lens_limit_converges():
    # The error against the point lens falls like theta_E ~ D^-1/2 (x10 per 100 in D).
    errs = []
    for d in [1e4, 1e6]:
        te = math.sqrt(2 / d)
        mu = np.asarray(jl.point_source_images(_sources(U * te), ray_map(d)).magnification)
        mp, mm = (np.asarray(x) for x in jl.point_lens_magnification(U))
        errs.append(np.max(np.abs(mu[1] / mm - 1)))
    assert errs[1] < errs[0] / 5


@pytest.mark.parametrize("d", [3.0, 10.0, 100.0])
def test_magnification_against_finite_differences_of_the_exact_map(d):
    # Axisymmetric lens: mu = (sin alpha / sin theta) / (d theta / d alpha), theta(alpha) =
    # |pi - Phi(alpha)| for the primary image; central difference of the exact Phi.
    theta = np.array([0.05, 0.4, 1.2, 2.0, 2.8])
    im = jl.point_source_images(_sources(theta), ray_map(d))
    a = np.asarray(im.alpha[0])
    h = 1e-6 * a
    phi = lambda x: _exact_phi(x, d)  # noqa: E731
    dtheta = -(phi(a + h) - phi(a - h)) / (2 * h)
    th = math.pi - phi(a)
    mu = np.sin(a) / np.sin(th) / dtheta
    # FD truncation h^2 |Phi'''| / 6 and rounding eps / h: ~1e-8 relative
    np.testing.assert_allclose(np.asarray(im.magnification[0]), mu, rtol=1e-6)


def test_image_position_gradient():
    # d alpha / d theta through the lens equation (one Newton step carries the implicit
    # derivative), in both modes, against a central difference.
    rm = ray_map(30.0)

    def alpha_of(theta):
        return rm.solve(jnp.stack([math.pi - theta, math.pi + theta]))

    theta = 0.3
    jac = np.asarray(jax.jit(jax.jacfwd(alpha_of))(theta))
    grad = float(jax.jit(jax.grad(lambda t: alpha_of(t)[1]))(theta))
    h = 1e-6
    fd = (np.asarray(alpha_of(theta + h)) - np.asarray(alpha_of(theta - h))) / (2 * h)
    # truncation h^2 and rounding eps / h: ~1e-9 relative
    np.testing.assert_allclose(jac, fd, rtol=1e-6)
    assert grad == pytest.approx(fd[1], rel=1e-6)
    assert jac[0] > 0 and jac[1] < 0  # the primary moves out with the source, the secondary in


def test_brightest_pixel_is_the_predicted_image():
    # Render a small star and find it where the lens equation puts its primary image.
    d = 15.0
    cam = jl.Camera(d, math.radians(90), 101, 101)
    lon, lat = 0.35, 0.1
    n = jl.direction_from_angles(lon, lat)
    star = jl.GaussianStar(0.004, 1.0, n)
    scene = jl.Scene(cam, star, redshift=jl.Redshift("bolometric"), accuracy=ACC)
    img = jl.render(scene)[..., 0]
    im = jl.point_source_images(n, ray_map(d))
    col, row = (np.asarray(x) for x in im.pixels(cam))
    for k in range(2):
        r0, c0 = int(row[k]), int(col[k])
        patch = img[r0 - 6 : r0 + 7, c0 - 6 : c0 + 7]
        pr, pc = np.unravel_index(np.argmax(patch), patch.shape)
        # the peak pixel contains (or touches) the predicted position
        assert abs(r0 - 6 + pr + 0.5 - row[k]) <= 1.0 and abs(c0 - 6 + pc + 0.5 - col[k]) <= 1.0
    with pytest.raises(ValueError, match="centred"):
        im.pixels(jl.Camera(d, 1.0, 8, 8, yaw=0.1))
