"""Fitting the black hole to an Einstein ring: the forward model, its
gradients, recovery on rendered rings, uncertainties, degenerate and bad inputs, CLI.

Most fits share one image size (96 x 72) and the Gauss-Legendre order 3, so that the
compiled fit programs are reused across tests.
"""

import functools
import json
import math
import re
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio
import pytest

import jaxlens as jl
from jaxlens import (
    RS_SUN_M,
    Camera,
    GaussianStar,
    Uniform,
    clipped_mean,
    distance_in_metres,
    einstein_ring_angle,
    fit_ring,
    mass_from_distance,
    read_observation,
    render_array,
    ring_image,
    shadow_angle,
    trace,
)

W, H = 96, 72
K = 3  # the order the fit picks for rings >= 0.75 px wide


def rendered(d, fov_deg, sigma_deg, floor, *, a=0.8, w=W, h=H, k=8):
    """The library's renderer (midpoint k x k samples, linear-ramp edge coverage)."""
    cam = Camera(d, math.radians(fov_deg), w, h, supersample=k)
    sky = GaussianStar(math.radians(sigma_deg), a) + Uniform(floor)
    return np.asarray(jax.jit(render_array)(cam, sky))[..., 0]


def modelled(d, fov_deg, sigma_deg, floor, *, a=0.8, ring_flux=1.0, w=W, h=H, k=8):
    """The fit's forward model: the primary image and the relativistic rings (their flux
    times `ring_flux`) of a star of peak `a`, over the floor."""
    return np.asarray(
        jax.jit(ring_image, static_argnums=(2, 3), static_argnames="supersample")(
            d, math.radians(fov_deg), w, h, sigma=math.radians(sigma_deg), brightness=a,
            floor=floor, ring_flux=ring_flux, supersample=k,
        )
    )  # fmt: skip


def noisy(img, noise, seed):
    return img + noise * np.random.default_rng(seed).standard_normal(img.shape)


def write_png(path, img, bits, *, rgba=False):
    """Linear values straight into an 8/16-bit PNG tagged linear (gAMA 1.0, no sRGB
    transfer), clipped to [0, 1]; `rgba`: as grey RGB with an opaque alpha channel.
    Returns the stored values."""
    top = 255 if bits == 8 else 65535
    q = np.clip(np.round(np.asarray(img) * top), 0, top)[..., None]
    if rgba:
        q = np.concatenate([q, q, q, np.full_like(q, top)], axis=-1)
    q = np.ascontiguousarray(q.astype(np.uint8 if bits == 8 else np.uint16))
    out = oiio.ImageOutput.create(str(path))
    fmt = oiio.UINT8 if bits == 8 else oiio.UINT16
    spec = oiio.ImageSpec(q.shape[1], q.shape[0], q.shape[2], fmt)
    spec.attribute("oiio:ColorSpace", "linear")  # else PNG means sRGB
    if rgba:
        spec.alpha_channel = 3
    assert out.open(str(path), spec)
    assert out.write_image(q) and out.close()
    return q[..., 0] / top


# ----------------------------------------------------------------- exact relations


def test_units():
    # R_S of one solar mass 2953.25 m (2 GM_sun / c^2: IAU nominal GM_sun, exact c).
    assert RS_SUN_M == pytest.approx(2953.25, abs=0.01)
    d_m = distance_in_metres(20.0, 4.0e6)
    assert d_m == pytest.approx(20.0 * 4.0e6 * 2953.25, rel=1e-6)
    assert mass_from_distance(20.0, d_m) == pytest.approx(4.0e6, rel=1e-12)


def test_einstein_ring_angle_reference_values():
    # Reference Einstein ring angles of the exact deflection (quoted to 1e-4 deg).
    got = np.degrees(np.asarray(einstein_ring_angle(jnp.asarray([10.0, 20.0, 50.0]))))
    np.testing.assert_allclose(got, [29.8283, 20.2039, 12.2928], atol=6e-5)
    # Phi(alpha_E) = pi on the exact trace, to the table's 1e-9 rad.
    a = einstein_ring_angle(20.0)
    assert abs(float(trace(a, 20.0, accuracy=1e-12).phi) - math.pi) < 1e-9
    # Weak field sqrt(2/D) to its O(1/D) correction, and invisible rings are refused.
    assert float(einstein_ring_angle(1e5)) == pytest.approx(math.sqrt(2e-5), rel=2e-3)
    with pytest.raises(ValueError, match="distance=1.7 is below 1.76030898"):
        einstein_ring_angle(1.7)


def test_stored_ring_table_is_the_computed_one():
    # The fit's starting values read a stored table of the ring relation; recomputed
    # from the escape tables it agrees to round-off (a changed closed form or table
    # setting must regenerate it). Round-off differs between XLA versions: 2.6e-12
    # relative with jax 0.8.0 against a table made with 0.10.2; a changed setting moves
    # the values by far more.
    from jaxlens._fit import starts

    stored, computed = starts.ring_table(), starts.compute_ring_table()
    for s, c in zip(stored, computed, strict=True):
        np.testing.assert_allclose(s, c, rtol=2e-11, atol=0.0)


def test_area_of_a_rectangle_within_a_disc():
    # Closed forms (inside, around, a quadrant, a half) and a fine point count.
    from jaxlens._area import rect_in_disc

    assert rect_in_disc(-1.0, 2.0, -2.0, 1.0, 10.0) == pytest.approx(9.0, rel=1e-14)
    assert rect_in_disc(-5.0, 5.0, -5.0, 5.0, 3.0) == pytest.approx(9 * math.pi, rel=1e-14)
    assert rect_in_disc(0.0, 4.0, 0.0, 4.0, 4.0) == pytest.approx(4 * math.pi, rel=1e-14)
    assert rect_in_disc(-9.0, 9.0, 0.0, 9.0, 2.0) == pytest.approx(2 * math.pi, rel=1e-14)
    assert rect_in_disc(3.0, 4.0, 3.0, 4.0, 4.0) == 0.0
    rng = np.random.default_rng(5)
    u = (np.arange(1500) + 0.5) / 1500
    for _ in range(5):
        x1, y1 = rng.uniform(-8.0, 4.0, 2)
        x2, y2 = x1 + rng.uniform(0.5, 8.0), y1 + rng.uniform(0.5, 8.0)
        r = rng.uniform(1.0, 10.0)
        xx, yy = np.meshgrid(x1 + (x2 - x1) * u, y1 + (y2 - y1) * u)
        count = np.mean(np.hypot(xx, yy) < r) * (x2 - x1) * (y2 - y1)
        assert rect_in_disc(x1, x2, y1, y2, r) == pytest.approx(count, abs=2e-3 * (x2 - x1))


@pytest.mark.parametrize("d, focal, sigma", [(12.0, 250.0, 0.026), (3.0, 120.0, 0.01)])
def test_start_search_model_is_the_area_exact_model(d, focal, sigma):
    # The start search's radial model against the renderer's area-exact pixels (8 x 8
    # rule, within 4e-5 of the peak on these bins; the radial grid's error is ~7e-5)
    # and the exact shadow shares.
    from jaxlens._area import rect_in_disc
    from jaxlens._fit import starts
    from jaxlens._fit.model import _pixel_basis
    from jaxlens._fit.pixels import pixel_edges
    from jaxlens._fit.table import escape_table

    with jax.enable_x64(True):
        x0, y0 = pixel_edges(400, 300, 8, np.float64)
        table = escape_table(d, knots=1024)
        radial, group, count = starts._radial_weights(400, 300, 8, 2.7)
        assert len(count) == 475 and count.sum() == 1850  # one bin of each mirrored set
        kept = starts._radial_basis(table, focal, sigma, radial)
        g, cov = (np.asarray(v)[group] for v in kept)
        ref, _, _ = _pixel_basis(table, focal, sigma, jnp.asarray(x0), jnp.asarray(y0),
                                 width=400, block=8, k=8, rings=False)  # fmt: skip
        r_sh = focal * math.tan(float(table.alpha_sh))
    ref = np.asarray(ref).ravel()
    assert ref.max() > 0.5
    np.testing.assert_allclose(g, ref, rtol=0, atol=1e-4 * ref.max())
    x1, y2 = x0.ravel(), y0.ravel()
    exact = 1.0 - rect_in_disc(x1, x1 + 8.0, y2 - 8.0, y2, r_sh) / 64.0
    assert exact.min() == 0.0 and np.any((exact > 0.01) & (exact < 0.99))  # shadow edge
    # Linear in radius between the exact shares: 2e-5, but 1e-3 where the edge is
    # tangent to a bin's side (the share grows as (r - r_t)^1.5 there).
    err = np.abs(cov - exact)
    assert np.mean(err > 2e-5) < 0.02 and err.max() < 1e-3


def test_gauss_legendre_order_meets_its_bound():
    # The order the model takes for a ring of a given width (pixels) averages a Gaussian
    # of that width over a pixel within 4e-5 of its peak (against the exact erf
    # average, every offset of the ring from the pixel); the next lower order does not.
    from jaxlens._area import rule
    from jaxlens._fit.model import samples_for

    erf = np.vectorize(math.erf)

    def worst(k, s):
        node, weight, _ = rule(k)
        c = np.linspace(-4.0 * s - 1.0, 4.0 * s + 1.0, 4001)[:, None]
        exact = math.sqrt(0.5 * math.pi) * s * (erf((1.0 - c) / (math.sqrt(2.0) * s))
                                                - erf(-c / (math.sqrt(2.0) * s)))  # fmt: skip
        quad = np.sum(weight * np.exp(-0.5 * ((node - c) / s) ** 2), axis=1, keepdims=True)
        return np.max(np.abs(quad - exact))

    orders = [2, 3, 4, 6, 8]
    for width in (2.1, 0.75, 0.5, 0.25):
        k = samples_for(width, 1)
        assert worst(k, width) < 4e-5
        if k > 2:
            assert worst(orders[orders.index(k) - 1], width) > 4e-5
        assert samples_for(0.99 * width, 1) > k  # the smallest order that meets it
    assert samples_for(3.0, 1, lowest=3) == 3 and samples_for(3.0, 2) == 3  # side 2 px


def test_einstein_ring_angle_gradient():
    # Implicit-function derivative against central differences (step 1e-4 D: the
    # truncation error ~1e-8 relative, the table's value noise ~1e-12 / 2e-3).
    g = float(jax.grad(einstein_ring_angle)(20.0))
    fd = float(einstein_ring_angle(20.002) - einstein_ring_angle(19.998)) / 0.004
    assert g == pytest.approx(fd, rel=1e-6)


@pytest.mark.parametrize("d", [5.0, 1000.0])
def test_the_fits_ray_map_matches_trace(d):
    # The fit's table: a RayMap of 4096 knots out to pi/2 with values-only knots (slopes
    # by fourth-order differences).
    build = eqx.filter_jit(jl.RayMap.build)
    table = build(d, knots=4096, alpha_max=0.5 * math.pi, exact_slopes=False)
    a_sh = float(shadow_angle(d))
    gap = np.geomspace(1e-7 * a_sh, 0.5 * np.pi - a_sh, 3000)
    alpha = a_sh + gap
    err = np.abs(np.asarray(table.escape_angle(alpha)) - trace(alpha, d, accuracy=1e-13).phi)
    # The interpolation: 1.1e-11 measured from 1e-4 of the shadow angle out, as with
    # slopes by autodiff (the difference slopes are fourth order, like the Hermite).
    assert err[gap > 1e-4 * a_sh].max() < 5e-11
    exact = build(d, knots=4096, alpha_max=0.5 * math.pi)
    err_exact = np.abs(np.asarray(exact.escape_angle(alpha)) - trace(alpha, d, accuracy=1e-13).phi)
    assert err[gap > 1e-4 * a_sh].max() < 2 * err_exact[gap > 1e-4 * a_sh].max() + 1e-12
    # Nearer the edge the closed form itself is conditioned to ~1e-16 / relative gap.
    assert err.max() < 1e-8


def test_clipped_mean():
    # E[max(0, n)] for n ~ N(0, s^2) is s / sqrt(2 pi); far from the bounds, the mean.
    s = 0.01
    assert float(clipped_mean(0.0, 0.0, 1.0, s)) == pytest.approx(s / math.sqrt(2 * math.pi))
    assert float(clipped_mean(0.5, 0.0, 1.0, s)) == pytest.approx(0.5, abs=1e-12)
    assert float(clipped_mean(0.3, -np.inf, np.inf, s)) == 0.3
    x = 0.004 + s * np.random.default_rng(1).standard_normal(400_000)
    assert float(clipped_mean(0.004, 0.0, 1.0, s)) == pytest.approx(
        np.clip(x, 0, 1).mean(), abs=4 * s / math.sqrt(x.size)
    )


def test_solve_spd_matches_numpy():
    """The written-out solve of the fit's small positive definite systems (the start
    search's 2 x 2 and 4 x 4, the decrement's 7 x 7) against numpy's, in float64 and
    float32."""
    from jaxlens._fit.spd import solve_spd

    rng = np.random.default_rng(7)
    for p, dtype, rtol in ((2, np.float64, 1e-12), (4, np.float64, 1e-10), (7, np.float32, 1e-3)):
        m = rng.standard_normal((50, p)) * rng.uniform(0.1, 10.0, p)
        a, b = m.T @ m, rng.standard_normal(p)
        with jax.enable_x64(dtype == np.float64):
            x = np.asarray(solve_spd(jnp.asarray(a, dtype), jnp.asarray(b, dtype)))
        assert x.dtype == dtype
        np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=rtol, atol=rtol * np.abs(x).max())


def test_the_solvers_damped_steps_match_lstsq():
    """The Levenberg-Marquardt step's least squares ([J; sqrt(lambda) I], columns of
    scales 1e-3 to 1e3, as the fit's parameters have) by the scaled normal equations
    against numpy's lstsq; and optimistix's largest damping, sqrt(lambda) ~ 1e154,
    gives a step of zero, not NaN."""
    import lineax as lx

    from jaxlens._fit.solve import ScaledNormalEquations

    rng = np.random.default_rng(11)
    jac = rng.standard_normal((4000, 7)) * np.geomspace(1e-3, 1e3, 7)
    r = rng.standard_normal(4000)
    with jax.enable_x64(True):
        for root_lambda in (0.0, 0.3, 1e154):
            a = np.concatenate([jac, root_lambda * np.eye(7)])
            b = np.concatenate([r, np.zeros(7)])
            op = lx.MatrixLinearOperator(jnp.asarray(a))
            x = np.asarray(lx.linear_solve(op, jnp.asarray(b), ScaledNormalEquations()).value)
            assert np.all(np.isfinite(x))
            if root_lambda < 1e100:
                want = np.linalg.lstsq(a, b, rcond=None)[0]
                np.testing.assert_allclose(x, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
            else:
                assert np.abs(x).max() < 1e-140


@pytest.mark.parametrize("case", ["plain", "held", "collinear"])
def test_newton_decrement_is_the_gauss_newton_gain(case):
    """`newton_decrement` (elimination written out) against the chi^2 gain of the
    Gauss-Newton step from numpy's least squares, with a held parameter's zero column
    and with two nearly collinear columns (an eigenvalue of 8e-10 of the scaled
    normal matrix: the ridge of 7e-14 lowers the gain by 1.3e-5)."""
    from jaxlens._fit.solve import newton_decrement

    rng = np.random.default_rng(5)
    jac = rng.standard_normal((500, 7)) * rng.uniform(0.01, 100.0, 7)
    if case == "held":
        jac[:, 3] = 0.0
    if case == "collinear":
        jac[:, 4] = 3.0 * jac[:, 2] + 1e-3 * rng.standard_normal(500)
    r = rng.standard_normal(500)
    step = np.linalg.lstsq(jac, r, rcond=None)[0]
    gain = r @ r - np.sum((r - jac @ step) ** 2)
    with jax.enable_x64(True):
        dec = float(newton_decrement(jnp.asarray(r), jnp.asarray(jac)))
    assert dec == pytest.approx(gain, rel=1e-4 if case == "collinear" else 1e-9)


def test_second_pass_check_rescales_residuals_and_jacobian():
    """A clipped image's re-estimated noise: `renoised` gives the residuals and the
    Jacobian of the new noise from the old ones (the model's derivatives through the
    old clipped slope) and their Newton decrement, as computed directly."""
    from jaxlens._fit.noise import Gaussian, clipped_slope
    from jaxlens._fit.objective import Data, renoised
    from jaxlens._fit.solve import newton_decrement

    with jax.enable_x64(True):
        rng = np.random.default_rng(3)
        n = 400
        model = np.linspace(-0.02, 0.3, n)  # into the clipping at 0
        dmodel = rng.standard_normal((n, 3))  # d model / d theta
        weight = rng.uniform(0.5, 2.0, n)
        data = np.clip(model + 0.01 * rng.standard_normal(n), 0.0, 1.0)

        def rows(clip):
            lo, hi, s, scale = clip
            r = weight * (np.asarray(clipped_mean(model, lo, hi, s)) - data) / scale
            slope = np.asarray(clipped_slope(model, lo, hi, s))
            return r, (weight * slope / scale)[:, None] * dmodel

        old, new = (0.0, 1.0, 0.01, 0.01), (0.0, 1.0, 0.013, 0.013)
        prior_r, prior_j = 0.3, np.asarray([[0.0, 0.0, 0.5]])
        r_old, j_old = rows(old)
        r_new, j_new = rows(new)

        def noise(clip):
            lo, hi, s, scale = (np.float64(v) for v in clip)
            return Gaussian(s, lo, hi, scale, rel=np.float64(0.01))

        d = Data(None, (), None, jnp.asarray(data), jnp.asarray(weight), noise(old), None)
        r2, j2, dec = renoised(model, d, noise(new), np.append(r_old, prior_r),
                               np.vstack([j_old, prior_j]), np.zeros(3))  # fmt: skip
        np.testing.assert_allclose(np.asarray(r2), np.append(r_new, prior_r), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(j2), np.vstack([j_new, prior_j]), rtol=1e-10)
        assert float(dec) == pytest.approx(float(newton_decrement(r2, j2)), rel=1e-12)
        assert float(dec) > 0.0
        # Where the solve settled with a last step, the decrement is that of the moved
        # point (its residuals to first order); the step to the optimum leaves none.
        moved = np.asarray([0.01, -0.02, 0.005])
        *_, dec_moved = renoised(model, d, noise(new), np.append(r_old, prior_r),
                                 np.vstack([j_old, prior_j]), moved)  # fmt: skip
        expect = newton_decrement(r2 + j2 @ moved, j2)
        assert float(dec_moved) == pytest.approx(float(expect), rel=1e-12)
        step = np.linalg.lstsq(np.asarray(j2), -np.asarray(r2), rcond=None)[0]
        *_, dec_opt = renoised(model, d, noise(new), np.append(r_old, prior_r),
                               np.vstack([j_old, prior_j]), step)  # fmt: skip
        assert float(dec_opt) < 1e-12 * float(dec)


# ------------------------------------------------------------------ forward model


def test_ring_image_matches_the_renderer():
    """The fit's model against the library's renderer (k = 12 point samples), D = 20."""
    d, fov, sig, floor = 20.0, 60.0, 1.5, 0.1
    ours = modelled(d, fov, sig, floor, k=6)
    theirs = rendered(d, fov, sig, floor, k=12)
    yy, xx = np.mgrid[0:H, 0:W]
    rho = np.hypot(xx + 0.5 - W / 2, H / 2 - yy - 0.5)
    rho_sh = (W / 2) / math.tan(math.radians(fov) / 2) * math.tan(float(shadow_angle(d)))
    edge = np.abs(rho - rho_sh) < 1.5
    # Away from the edge: the midpoint rule's error for a ring ~1 px wide (k = 12:
    # ~3e-4 of the peak, measured in 1-D against the exact erf average).
    assert np.abs(ours - theirs)[~edge].max() < 1e-3
    # The edge band: both conserve the floor's area (straight-edge coverage per cell
    # against the renderer's ramp, photon rings sampled vs integrated): 0.5 %.
    assert ours[edge].sum() == pytest.approx(theirs[edge].sum(), rel=5e-3)


@pytest.mark.parametrize(
    "kwargs, match",
    [({"distance": 1.2}, "distance=1.2 must be finite and > 1.5"),
     ({"fov": 0.0}, "fov=0.0 must be in"), ({"fov": math.pi}, "fov="),
     ({"sigma": -0.01}, "sigma=-0.01 must be"), ({"floor": math.nan}, "floor=nan"),
     ({"brightness": 1j}, "brightness must be real"),
     ({"width": 0}, "width=0 must be a whole number"), ({"height": 2.5}, "height=2.5"),
     ({"supersample": True}, "supersample=True")],
)  # fmt: skip
def test_ring_image_refuses_bad_values(kwargs, match):
    args = {"distance": 20.0, "fov": 1.0, "width": 8, "height": 6, "sigma": 0.02} | kwargs
    w, h = args.pop("width"), args.pop("height")
    with pytest.raises(ValueError, match=re.escape(match)):
        ring_image(args.pop("distance"), args.pop("fov"), w, h, **args)


def test_ring_image_checks_traced_values_at_run_time():
    # `modelled`'s program (every value traced), which the ring tests compile anyway.
    assert np.all(np.isfinite(modelled(20.0, 60.0, 1.5, 0.1)))
    with pytest.raises(Exception, match="distance must be finite and > 1.5"):
        modelled(1.2, 60.0, 1.5, 0.1)


@functools.partial(jax.jit, static_argnums=(2, 3))
def _image_and_jacobian(p, q, w, h):
    """The model image (order 4) at D, FOV = `p` and its Jacobian in `p` (forward mode),
    `q` the star's width, its brightness and the floor: one program for the gradient
    tests, the image the differences' values."""

    def img(p):
        out = ring_image(p[0], p[1], w, h, sigma=q[0], brightness=q[1], floor=q[2],
                         supersample=4)  # fmt: skip
        return out, out

    return jax.jacfwd(img, has_aux=True)(p)


def test_model_gradient_matches_finite_differences():
    """d(image)/dD and d(image)/dFOV by forward-mode autodiff against central
    differences of the same area-sampled image."""
    d, fov, sig, floor = 20.0, math.radians(60.0), math.radians(1.5), 0.1
    p, q = jnp.asarray([d, fov]), jnp.asarray([sig, 0.8, floor])
    jac = np.asarray(_image_and_jacobian(p, q, 64, 48)[0])
    for i, h in enumerate((1e-4 * d, 1e-5)):
        e = np.zeros(2)
        e[i] = h
        fd = (np.asarray(_image_and_jacobian(p + e, q, 64, 48)[1])
              - np.asarray(_image_and_jacobian(p - e, q, 64, 48)[1])) / (2 * h)  # fmt: skip
        # Central differences: truncation ~h^2 |f'''|, well below 1e-4 of the scale.
        np.testing.assert_allclose(jac[..., i], fd, atol=2e-4 * np.abs(fd).max())


def test_shadow_edge_contributes_gradient():
    """Against a floor, the pixels on the shadow edge carry d/dD of the floor's area
    outside the shadow: -floor 2 pi rho_sh d(rho_sh)/dD, exactly what the coverage
    of the edge gives (the renderer's ramp agrees within its sampling)."""
    d, fov, sig, floor = 10.0, math.radians(60.0), math.radians(0.5), 0.2
    w, h = 64, 48  # the gradient test's size, so its program (the edge lies 14 px out)
    focal = (w / 2) / math.tan(fov / 2)
    yy, xx = np.mgrid[0:h, 0:w]
    rho = np.hypot(xx + 0.5 - w / 2, h / 2 - yy - 0.5)

    def rho_sh(dd):
        return focal * jnp.tan(shadow_angle(dd))

    band = np.abs(rho - float(rho_sh(d))) < 2.0
    assert not (band[0].any() or band[-1].any())  # the whole edge in the frame

    # d/dD of the band's sum: the D column of the model's Jacobian summed over the band.
    jac = _image_and_jacobian(jnp.asarray([d, fov]), jnp.asarray([sig, 0.8, floor]), w, h)[0]
    got = float(np.asarray(jac)[..., 0][band].sum())
    expect = -floor * 2 * math.pi * float(rho_sh(d)) * float(jax.grad(rho_sh)(d))
    # The images of order >= 1 on the edge move with it too (flux ~1e-3 of the floor's).
    assert got == pytest.approx(expect, rel=1e-2)
    assert abs(got) > 1.0  # not a point-sampled step: a real contribution
    band = jnp.asarray(band)

    def render_sum(dd):
        cam = Camera(dd, fov, w, h, supersample=16)
        img = render_array(cam, GaussianStar(sig, 0.8) + Uniform(floor))[..., 0]
        return jnp.sum(jnp.where(band, img, 0.0))

    fd = float(jax.jit(render_sum)(d + 0.02) - jax.jit(render_sum)(d - 0.02)) / 0.04
    assert fd == pytest.approx(expect, rel=5e-2)


# ------------------------------------------------------------------------ recovery

# (D, FOV deg, sigma deg, floor, sigma given, noise): D from 5 to 1000, FOV 10 to 120,
# with and without floor, sigma given or fitted; the ring is resolved in 96 x 72.
# The two slowest (~40 s each on 2 cores) are also what the fit benchmark's rings cover:
# marked `benchmark`, run by `make test-slow`, not by `make test`.
_SLOW = pytest.mark.benchmark
RECOVERY = [
    pytest.param(5.0, 120.0, 2.0, 0.1, False, 0.02, marks=_SLOW),
    (20.0, 60.0, 1.5, 0.1, False, 0.02),
    pytest.param(40.0, 40.0, 1.0, 0.0, True, 0.01, marks=_SLOW),
    (200.0, 20.0, 0.5, 0.05, True, 0.01),
    (1000.0, 10.0, 0.3, 0.1, True, 0.01),
]


@pytest.mark.parametrize("d, fov, sig, floor, given, noise", RECOVERY)
def test_recovery_on_rendered_rings(d, fov, sig, floor, given, noise):
    img = noisy(rendered(d, fov, sig, floor), noise, seed=int(d))
    fit = fit_ring(img, star_sigma=math.radians(sig) if given else None, supersample=K)
    assert fit.converged and not fit.degenerate, fit.message
    # Within 1 % (the fit's goal), and within 4 reported standard errors (the data
    # come from another renderer: midpoint samples, ramp coverage, aliased photon rings).
    for got, err, true in (
        (fit.distance, fit.distance_err, d),
        (fit.fov_deg, fit.fov_deg_err, fov),
    ):
        assert abs(got / true - 1) < 0.01
        assert abs(got - true) < 4 * err
    assert fit.residual_noise == pytest.approx(noise, rel=0.1)
    assert "no pixel noise" not in fit.message and fit.valid


def test_white_noise_is_told_from_structure():
    from jaxlens._fit.noise import white_noise_found

    clean = np.asarray(modelled(20.0, 60.0, 1.5, 0.1))  # the ring tests' program
    assert not white_noise_found(clean)[0]  # smooth structure only
    assert not white_noise_found(np.round(clean * 255) / 255)[0]  # and quantised
    assert not white_noise_found(np.full((40, 50), 0.3))[0]  # flat
    rng = np.random.default_rng(5)
    for level in (1e-5, 1e-3, 1e-1):
        found, ratio = white_noise_found(clean + level * rng.standard_normal(clean.shape))
        assert found and 0.7 < ratio < 1.3, (level, ratio)


def test_noiseless_image_is_flagged():
    # A noiseless image: the estimated "noise" is structure, its errors no measurement's.
    fit = fit_ring(rendered(20.0, 60.0, 1.5, 0.1), supersample=K)
    assert "no pixel noise found" in fit.message
    assert not fit.valid and "FLAGGED" in fit.summary() and fit.to_dict()["valid"] is False


def test_a_nuisance_out_of_its_physical_range_is_flagged():
    # Relativistic rings of negative flux (dark rings inside the bright one): no star
    # and hole make them, and a fit that needs them is no measurement.
    img = noisy(modelled(20.0, 60.0, 1.5, 0.1, ring_flux=-4.0), 0.002, seed=7)
    fit = fit_ring(img, star_sigma=math.radians(1.5), supersample=K)
    assert fit.ring_flux < 0 and not fit.valid, fit.summary()
    assert "ring_flux" in fit.message and "is negative" in fit.message


@pytest.mark.parametrize("bits", [8, 16])
def test_png_round_trip(tmp_path, bits):
    """Linear values stored in integer PNGs tagged linear, noise clipped at 0 in the
    shadow: read as stored and fitted with the clipped-noise model."""
    d, fov, sig = 20.0, 60.0, 1.5
    path = tmp_path / f"ring{bits}.png"
    stored = write_png(path, noisy(modelled(d, fov, sig, 0.1), 0.01, seed=bits), bits)
    np.testing.assert_allclose(read_observation(path), stored, atol=1e-6)
    fit = fit_ring(path, star_sigma=math.radians(sig))
    assert isinstance(fit, jl.Fit)  # the general fit's result, not a copy of it
    assert fit.converged and not fit.degenerate and fit.transfer == "linear"
    # sigma given, so held: its error is 0 (exactly, not a tiny number), as in to_dict.
    assert fit.sigma_err == fit.sigma_deg_err == fit.to_dict()["sigma_err"] == 0.0
    # The given width as the star holds it (float32 outside the fit: 6e-8 relative).
    assert fit.sigma_deg == pytest.approx(sig, rel=1e-7) and "sigma" not in fit.names
    assert abs(fit.distance / d - 1) < 0.01 and abs(fit.fov_deg / fov - 1) < 0.01
    assert abs(fit.distance - d) < 4 * fit.distance_err
    assert fit.supersample == K
    # An RGBA file: the colour channels averaged, the (opaque) alpha left out.
    rgba = tmp_path / "rgba.png"
    stored = write_png(rgba, modelled(d, fov, sig, 0.1), bits, rgba=True)
    np.testing.assert_allclose(read_observation(rgba), stored, atol=1e-6)


def test_the_librarys_own_png_is_decoded_and_fits(tmp_path):
    """`write_image` stores a PNG in sRGB (8 bits); the fit's reader decodes it to
    linear, as `read_image` does (read as stored, the same ring gave D = 20.17 +- 0.015
    for 20, FOV 59.74 deg and a floor of 0.32 for 0.1)."""
    d, fov, sig = 20.0, 60.0, 1.5
    linear = np.clip(noisy(modelled(d, fov, sig, 0.1), 0.01, seed=5), 0.0, 1.0)
    path = tmp_path / "ring.png"
    jl.write_image(path, np.repeat(linear[..., None], 3, axis=-1).astype(np.float32))
    obs = jl.observe(path)
    got, transfer = obs.data, obs.transfer
    assert transfer == "srgb" and obs.transfer_tagged
    # 8-bit sRGB steps: at most 0.5 / 255 of the encoded value, 0.0045 in linear at 1.
    np.testing.assert_allclose(got, linear, atol=5e-3)
    np.testing.assert_allclose(got, jl.read_image(path)[..., :3].mean(-1), atol=1e-6)
    fit = fit_ring(path, star_sigma=math.radians(sig))
    assert fit.converged and not fit.degenerate and fit.transfer == "srgb"
    assert re.search(r"^transfer\s+= srgb \(decoded from sRGB to linear", fit.summary(), re.M)
    assert abs(fit.distance - d) < 4 * fit.distance_err and abs(fit.fov_deg / fov - 1) < 0.01
    assert abs(fit.floor - 0.1) < 0.01


@pytest.mark.parametrize("scale", [1.3, 0.7])
def test_start_30_percent_off(scale):
    d, fov, sig = 20.0, 60.0, 1.5
    img = noisy(modelled(d, fov, sig, 0.1), 0.02, seed=7)
    init = {"distance": d * scale, "fov_deg": fov / scale}
    fit = fit_ring(img, star_sigma=math.radians(sig), init=init, supersample=K)
    assert fit.converged
    assert abs(fit.distance / d - 1) < 0.01 and abs(fit.fov_deg / fov - 1) < 0.01


@pytest.mark.benchmark  # ~45 s: 24 fits; the fit benchmark reports the pulls of its cases
def test_uncertainties_cover_the_truth():
    """Pulls (fit - truth) / reported error over noise realisations: mean ~0, std ~1,
    ~68 % inside one standard error."""
    d, fov, sig, noise, n = 20.0, 60.0, 1.5, 0.03, 24
    clean = modelled(d, fov, sig, 0.1)
    pulls = []
    for i in range(n):
        fit = fit_ring(noisy(clean, noise, seed=100 + i), star_sigma=math.radians(sig),
                       init={"distance": d, "fov_deg": fov}, supersample=K)  # fmt: skip
        assert fit.converged
        pulls.append([(fit.distance - d) / fit.distance_err, (fit.fov_deg - fov) / fit.fov_deg_err])
    pulls = np.asarray(pulls)
    for p in pulls.T:
        # Sample std of n = 24 unit normals: sd 1/sqrt(2n) = 0.14, so 0.6-1.5 is beyond
        # 2.9 sd each way; the mean has sd 1/sqrt(n) = 0.2 (bound: 3 sd).
        assert 0.6 < p.std(ddof=1) < 1.5
        assert abs(p.mean()) < 3 / math.sqrt(n)
        # Binomial: 68.3 % +- 3 sqrt(0.683 * 0.317 / n) = +- 28 %.
        assert 0.40 < np.mean(np.abs(p) < 1) < 0.97


# ------------------------------------------------------------- degenerate and bad


def test_degenerate_without_sigma_or_shadow_edge():
    """sigma unknown and no floor: only the ring's radius and width (and a faint profile
    asymmetry) are seen, so D, FOV and sigma trade off: flagged, finite, explained."""
    # Started at the truth (the recovery tests cover the start search): 9 steps to the
    # flagged optimum, not 56 along the degenerate valley from the search's start
    # (D 25 +- 5 there, 44 +- 18 here: flagged both).
    img = noisy(modelled(50.0, 30.0, 1.0, 0.0), 0.03, seed=3)
    init = {"distance": 50.0, "fov_deg": 30.0, "sigma": math.radians(1.0)}
    fit = fit_ring(img, init=init, supersample=K)
    assert fit.degenerate
    assert "star_sigma" in fit.message and "shadow edge" in fit.message
    values = [fit.distance, fit.fov, fit.sigma, fit.distance_err, fit.fov_err]
    assert all(np.isfinite(values))


def test_ring_flux_is_a_nuisance():
    """The relativistic rings (a few thousandths of a pixel wide) have their flux fitted
    as a nuisance: halving or doubling it in the data, as the aliasing of a renderer that
    point-samples pixels does, moves `ring_flux`, not D."""
    d, fov, sig = 10.0, 60.0, 2.0
    noise = 0.002 * np.random.default_rng(1).standard_normal((H, W))
    lo, hi = (
        fit_ring(modelled(d, fov, sig, 0.1, ring_flux=f, k=6) + noise,
                 star_sigma=math.radians(sig), supersample=K)
        for f in (0.5, 2.0)
    )  # fmt: skip
    # Measured: ring_flux 0.34 and 1.74 +- 0.2; D 10.0023 and 10.0038 +- 0.0039.
    err = math.hypot(lo.ring_flux_err, hi.ring_flux_err)
    assert hi.ring_flux - lo.ring_flux == pytest.approx(1.5, abs=3 * err)
    assert hi.ring_flux - lo.ring_flux > 0.8
    assert abs(hi.distance - lo.distance) < 0.5 * lo.distance_err
    assert abs(lo.distance - d) < 3 * lo.distance_err


def test_degenerate_when_only_a_faint_relativistic_ring_separates_d():
    """sigma fitted, no floor: the primary ring leaves D, FOV and sigma trading off and
    only the relativistic ring separates them. Seen at ~3 standard errors, that is not
    enough (D off by 0.6-6 % over seeds at these settings): flagged, although D's
    relative error (2.5 %) is below the 10 % rule."""
    # Started at the truth (the recovery tests cover the start search): the optimum is the
    # one the search's own start reaches (D 17.102 +- 0.43 both), in 3 steps, not 68 along
    # the degenerate valley (7 s).
    img = noisy(modelled(17.0, 80.0, 1.2, 0.0, k=6), 0.001, seed=2)
    init = {"distance": 17.0, "fov_deg": 80.0, "sigma": math.radians(1.2)}
    fit = fit_ring(img, init=init, supersample=K)
    assert fit.degenerate and "relativistic ring" in fit.message, fit.message
    assert fit.distance_err / fit.distance < 0.10
    assert np.isfinite([fit.distance, fit.fov, fit.sigma, fit.ring_flux]).all()


@pytest.mark.benchmark  # ~50 s: a 192 x 144 fit; the benchmark's floor-free rings cover it
def test_relativistic_ring_fixes_d_without_sigma_or_floor():
    """The same scene at 192 x 144 and noise 5e-4: the relativistic ring is seen at >10
    standard errors and fixes D (measured 17.046 +- 0.046)."""
    img = modelled(17.0, 80.0, 1.2, 0.0, w=192, h=144, k=6)
    fit = fit_ring(noisy(img, 5e-4, seed=2), supersample=K)
    assert fit.converged and not fit.degenerate, fit.message
    assert abs(fit.distance / 17.0 - 1) < 0.01 and abs(fit.distance - 17.0) < 3 * fit.distance_err
    assert abs(fit.fov_deg / 80.0 - 1) < 0.01
    assert fit.ring_flux > 10 * fit.ring_flux_err


def test_a_stretched_ring_is_flagged_not_a_traceback():
    # A ring stretched 2x sideways: its shadow had no measured extent, and the start
    # from the ring and shadow radii divided by it (ZeroDivisionError). Now the start
    # skips it, and the fit says the model does not describe the image.
    from jaxlens._fit.starts import distance_from_radii

    assert distance_from_radii(10.0, 0.0, W) is None
    img = np.repeat(noisy(modelled(20.0, 60.0, 1.5, 0.1), 0.01, seed=9), 2, axis=1)
    # The order given (the ring's width would choose 2): the ring fits' compiled programs.
    fit = fit_ring(img[:, W // 2 : W // 2 + W], star_sigma=math.radians(1.5), supersample=K)
    assert not fit.valid and "does not describe the image" in fit.message, fit.summary()


def test_bad_images(tmp_path):
    with pytest.raises(ValueError, match="blank"):
        fit_ring(np.full((H, W), 0.3))
    with pytest.raises(ValueError, match="too small"):
        fit_ring(np.random.default_rng(0).random((4, 4)))
    with pytest.raises(ValueError, match="no ring"):
        fit_ring(np.random.default_rng(0).random((H, W)))
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")
    with pytest.raises(ValueError, match="not a readable image"):
        fit_ring(bad)
    with pytest.raises(ValueError, match="does not exist"):
        fit_ring(tmp_path / "missing.png")
    with pytest.raises(ValueError, match=r"transfer='gamma' is not valid: expected one of 'auto'"):
        fit_ring(modelled(20.0, 60.0, 1.5, 0.1), transfer="gamma")


# ----------------------------------------------------------------------------- CLI


def test_cli(tmp_path, capsys, monkeypatch):
    from jaxlens import _compile, cli

    monkeypatch.setenv("JAXLENS_CACHE_DIR", "")  # no persistent cache from a test
    # ... but the fit's programs run as the CLI keeps them (their executables).
    kept = tmp_path / "programs"
    monkeypatch.setattr(_compile, "_FOLDER", kept)
    path = tmp_path / "ring.png"
    write_png(path, noisy(modelled(20.0, 60.0, 1.5, 0.1), 0.01, seed=16), 16)
    assert cli.main(["fit", str(path), "--star-sigma-deg", "1.5", "--mass", "10", "--json"]) == 0
    # The solve, the starting values' search, the check of the re-estimated noise, the
    # blur test's residual slopes and `find_arcs`' three (its solve on bins and on
    # pixels, its model on the pixels): all kept (a ring's source starts behind the hole:
    # no scan of the loss, no arcs' rays; those are kept in test_fit_general's CLI fit
    # of arcs).
    assert len(list(kept.glob("*.executable"))) == 7 and not list(kept.glob("*.refused"))
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["converged"] is True and out["transfer"] == "linear"
    assert isinstance(out["transfer_reason"], str)
    assert out["distance"] == pytest.approx(20.0, rel=0.01)
    assert out["fov_deg"] == pytest.approx(60.0, rel=0.01)
    assert out["distance_m"] == pytest.approx(out["distance"] * 10 * 2953.25, rel=1e-6)
    assert out["distance_m_err"] == pytest.approx(out["distance_err"] * 10 * 2953.25, rel=1e-6)
    assert 0 < out["distance_err"] < 0.2 and 0 < out["fov_deg_err"] < 0.5

    # Several images, one JSON line each; a bad one says so on its line, the others go
    # on, and the exit code is 2.
    blank = tmp_path / "blank.png"
    write_png(blank, np.full((H, W), 0.25), 8)
    argv = ["fit", str(path), str(blank), str(path), "--star-sigma-deg", "1.5", "--json"]
    assert cli.main(argv) == 2
    captured = capsys.readouterr()
    lines = [json.loads(line) for line in captured.out.strip().splitlines()]
    assert [line["image"] for line in lines] == [str(path), str(blank), str(path)]
    assert "blank" in lines[1]["error"] and "distance" not in lines[1]
    assert lines[0]["distance"] == lines[2]["distance"] == out["distance"]
    assert "1 of 3 images could not be fitted" in captured.err

    # The text report, with the mass from a known distance (6 significant digits).
    argv = ["fit", str(path), "--star-sigma-deg", "1.5", "--distance-m", "6e5", "--transfer",
            "linear"]  # fmt: skip
    assert cli.main(argv) == 0
    text = capsys.readouterr().out
    assert "source_lon" in text
    d = float(re.search(r"^distance\s+= (\S+) \+- \S+ R_S", text, re.M).group(1))
    m = float(re.search(r"^mass\s+= (\S+) \+- \S+ M_sun \(distance 600000 m\)", text,
                        re.M).group(1))  # fmt: skip
    assert m == pytest.approx(6e5 / (d * 2953.25), rel=2e-5)
    # The text report is Fit.summary()'s: the file's decoding on a line of its own, here
    # as --transfer chose it.
    assert re.search(r"^transfer\s+= linear \(as stored.*transfer='linear' given", text, re.M)

    # --transfer takes the three decodings only (argparse: its usage line, exit 2).
    with pytest.raises(SystemExit) as e:
        cli.main(["fit", str(path), "--transfer", "gamma"])
    assert e.value.code == 2 and "--transfer: invalid choice: 'gamma'" in capsys.readouterr().err

    for argv in (["fit", str(blank)], ["fit", str(tmp_path / "none.png")],
                 ["fit", str(path), "--star-sigma-deg", "-1"],
                 ["fit", str(path), "--mass-msun", "0"]):  # fmt: skip
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("jaxlens fit: error:") and "\n" not in err


@pytest.mark.parametrize("call", ["fit_ring", "fit", "find_arcs"])
def test_host_drivers_under_a_trace_say_what_to_call(call):
    # They run on the host (numpy, a solver of their own): traced, each says so and
    # names what to differentiate (a TracerArrayConversionError from deep inside before).
    img = modelled(20.0, 60.0, 1.5, 0.05)
    scene = jl.Scene(Camera(20.0, 1.0, W, H), GaussianStar(0.02) + Uniform(0.0))
    f = {"fit_ring": lambda im: jl.fit_ring(im, star_sigma=0.02).distance,
         "fit": lambda im: jl.fit(scene, im).values["distance"],
         "find_arcs": lambda im: jl.find_arcs(im).x_c}[call]  # fmt: skip
    with pytest.raises(TypeError, match=f"jaxlens.{call} runs on the host"):
        jax.jit(f)(img)


@pytest.mark.parametrize("call", ["fit_ring", "fit", "find_arcs"])
@pytest.mark.parametrize("kind", ["complex", "bool", "object"])
def test_images_of_values_that_are_not_real_numbers_are_refused(call, kind):
    # A complex image was cast to its real part with a ComplexWarning: fit_ring then
    # said "blank (every pixel is 1)". Refused by its dtype, before any fitting.
    img = np.random.default_rng(0).random((H, W))
    img = {"complex": img * (1.0 + 1.0j), "bool": img > 0.1,
           "object": img.astype(object)}[kind]  # fmt: skip
    scene = jl.Scene(Camera(20.0, 1.0, W, H), GaussianStar(0.02) + Uniform(0.0))
    f = {"fit_ring": lambda: jl.fit_ring(img, star_sigma=0.02),
         "fit": lambda: jl.fit(scene, img),
         "find_arcs": lambda: jl.find_arcs(img)}[call]  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ComplexWarning on the way
        with pytest.raises(TypeError, match=rf"of dtype {img.dtype} is not valid: expected real"):
            f()
