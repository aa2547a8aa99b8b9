"""Area-exact sampling (`Camera(..., sampling="gauss")`): exact shadow-edge areas, the
thin relativistic rings' flux, agreement with dense point sampling, gradients, and
the plan's and the scene file's handling of the mode."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl

W = H = 48


def _gauss(distance, fov, *, k=3, w=W, h=H, **kw):
    return jl.Camera(distance, fov, w, h, supersample=k, sampling="gauss", **kw)


def _render(cam, sky, **kw):
    return np.asarray(jl.render_array(jl.Scene(cam, sky, **kw)))


def test_shadow_area_is_exact():
    # A unit sky: each pixel is the fraction of its area outside the shadow, so the
    # image sums to W H - pi rho_sh^2 (rho_sh = f tan alpha_sh, the shadow fully in
    # view). The rule takes the edge as straight across each sub-cell (side s ~ 1/k
    # px): the circle's sagitta leaves ~ s^3 / (12 rho) a crossing, ~ 2 pi rho / s
    # crossings, a total ~ (pi / 6) s^2 = 0.06 px^2 at k = 3 (measured 0.033, a radius
    # bias of 3e-4 px), falling as 1 / k^2. Point samples put the edge on a ramp.
    d, fov = 6.0, math.radians(60.0)
    errors = {}
    for k in (3, 6):
        cam = _gauss(d, fov, k=k)
        img = _render(cam, jl.Uniform(1.0))[..., 0]
        assert np.all((img >= 0.0) & (img <= 1.0 + 1e-12))
        rho = float(cam.focal) * math.tan(float(jl.shadow_angle(d)))
        assert 8.0 < rho < 0.5 * W
        errors[k] = abs(img.sum() - (W * H - math.pi * rho**2))
    assert errors[3] < 0.06, errors
    assert errors[6] < errors[3] / 2.5, errors  # second order in the sub-cell side


def test_thin_ring_flux():
    # An annulus of +-2 px about the shadow edge holds the images of order >= 1 only
    # (the primary ring lies at Phi = pi, the star's Gaussian of sigma 0.6 deg is e^-50
    # below its peak there). Its sum is the rings' total flux,
    # 2 pi rho_m F_m with F_m = A sqrt(2 pi) sigma f / (cos^2 alpha_m |Phi'(alpha_m)|)
    # (m = 1, 2), from the ray map's solve: the cells' shares of a thin ring sum to its
    # length in view, to the curvature error of a straight ring across a sub-cell
    # (relative ~ s^2 / rho^2 ~ 1e-3); 3e-3 relative bounds it.
    d, fov, sigma, amp = 8.0, math.radians(50.0), math.radians(0.6), 2.0
    cam = _gauss(d, fov, k=3, w=64, h=64)
    img = _render(cam, jl.GaussianStar(sigma, amp))[..., 0]
    f = float(cam.focal)
    rmap = jl.RayMap.build(d)
    expect = 0.0
    for m in (1, 2):
        a, slope = (float(v) for v in rmap.solve((2 * m + 1) * math.pi, with_slope=True))
        flux = amp * math.sqrt(2 * math.pi) * sigma * f / (math.cos(a) ** 2 * abs(slope))
        expect += 2 * math.pi * f * math.tan(a) * flux
    yy, xx = np.mgrid[0:64, 0:64]
    rho_px = np.hypot(xx + 0.5 - 32, 32 - yy - 0.5)
    rho_sh = f * math.tan(float(jl.shadow_angle(d)))
    band = np.abs(rho_px - rho_sh) < 2.0
    got = img[band].sum()
    assert abs(got / expect - 1.0) < 3e-3, (got, expect)


@pytest.mark.parametrize("lon_deg, lat_deg", [(0.0, 0.0), (2.5, -1.0)])
def test_agrees_with_dense_point_sampling(lon_deg, lat_deg):
    # Away from the shadow edge (where point samples alias the thin rings and put the
    # edge on a ramp) both are area averages of a smooth image: k = 4 Gauss-Legendre
    # is exact to ~1e-6 of the peak for a ring 2 px wide, 16 x 16 point samples to
    # ~1/(12 k^2) of its curvature, ~3e-4 of the peak; 2e-3 of the peak bounds both.
    d, fov = 12.0, math.radians(70.0)
    sky = jl.GaussianStar(math.radians(1.5), 1.0, lon=math.radians(lon_deg),
                          lat=math.radians(lat_deg)) + jl.Uniform(0.05)  # fmt: skip
    g = _render(_gauss(d, fov, k=4), sky)
    u = _render(jl.Camera(d, fov, W, H, supersample=16), sky)
    cam = _gauss(d, fov)
    rho_sh = float(cam.focal) * math.tan(float(jl.shadow_angle(d)))
    yy, xx = np.mgrid[0:H, 0:W]
    far = np.abs(np.hypot(xx + 0.5 - W / 2, H / 2 - yy - 0.5) - rho_sh) > 2.0
    peak = g.max()
    assert peak > 0.5
    assert np.abs(g - u)[far].max() < 2e-3 * peak


def test_moving_camera_agrees_with_point_sampling():
    # The same check through the aberration (an orbiting camera) and the redshift, the
    # general path of the kernel (gradient of the static-frame alpha by forward mode).
    d, fov = 12.0, math.radians(70.0)
    sky = jl.GaussianStar(math.radians(1.5), 1.0, lon=math.radians(1.0)) + jl.Uniform(0.05)
    kw = dict(motion=jl.CircularOrbit(), redshift=jl.Redshift("bolometric"))
    g = _render(_gauss(d, fov, k=4), sky, **kw)
    u = _render(jl.Camera(d, fov, W, H, supersample=16), sky, **kw)
    assert np.all(np.isfinite(g))
    # Far from the edge (off-centre and oval here): pixels that are wholly outside the
    # shadow, with their neighbours (the images of order >= 1 hug the edge).
    cover = _render(_gauss(d, fov, k=4), jl.Uniform(1.0), motion=jl.CircularOrbit())[..., 0]
    out = cover > 1.0 - 1e-12
    far = out.copy()
    for ax in (0, 1):
        for step in (1, -1):
            far &= np.roll(out, step, axis=ax)
    assert 0.3 < far.mean() < 0.99
    peak = g.max()
    assert np.abs(g - u)[far].max() < 2e-3 * peak


def test_gradients_are_finite_and_match_differences():
    # Area-exact pixels are continuous in D, the FOV and the star's position: central
    # differences with step 1e-5 (relative) agree with autodiff to ~h^2 |f'''| and the
    # 1e-10 rad table noise / h: 1e-5 relative.
    def loss(params):
        d, fov, lon = params
        sky = jl.GaussianStar(0.02, 1.0, lon=lon) + jl.Uniform(0.1)
        # Values-only knots (as a fit builds them): the derivative of the map with
        # respect to D needs only first derivatives of the closed form.
        rmap = jl.RayMap.build(d, knots=2048, alpha_max=0.5 * math.pi, exact_slopes=False)
        img = jl.render_array(jl.Scene(_gauss(d, fov, w=32, h=24), sky), ray_map=rmap)
        return jnp.sum(img[..., 0] ** 2)

    p = jnp.asarray([9.0, math.radians(55.0), 0.03])
    # Forward mode, as a fit differentiates (reverse mode through the ray map's build
    # compiles several times longer; tests/test_render.py checks it on bare scenes).
    grad = np.asarray(jax.jit(jax.jacfwd(loss))(p))
    assert np.all(np.isfinite(grad)) and np.all(grad != 0.0)
    f = jax.jit(loss)
    for i in range(3):
        h = 1e-5 * float(abs(p[i]))
        e = jnp.zeros(3).at[i].set(h)
        fd = (float(f(p + e)) - float(f(p - e))) / (2 * h)
        assert abs(fd - grad[i]) < 1e-5 * abs(grad[i]) + 1e-7, (i, fd, grad[i])


def test_plan_and_refusals():
    cam = _gauss(10.0, 1.0)
    plan = jl.plan(jl.Scene(cam, jl.Uniform(1.0)))
    assert plan.geometry == "table" and not plan.symmetric
    assert any("area-exact" in r for r in plan.reasons)
    with pytest.raises(ValueError, match="Disk"):
        jl.plan(jl.Scene(cam, jl.Uniform(1.0), disk=jl.Disk(3.0, 10.0)))
    with pytest.raises(ValueError, match="table"):
        jl.plan(jl.Scene(cam, jl.Uniform(1.0), method="trace"))
    with pytest.raises(ValueError, match="sampling"):
        jl.Camera(10.0, 1.0, 8, 8, sampling="box")


def test_traced_bad_distance_raises():
    sky = jl.Uniform(1.0)

    @jax.jit
    def f(d):
        return jl.render_array(jl.Scene(_gauss(d, 1.0, w=8, h=8), sky))

    assert np.all(np.isfinite(np.asarray(f(5.0))))
    with pytest.raises(Exception, match="camera distance must be finite and > 1"):
        jax.block_until_ready(f(0.5))


def test_scene_file_and_cli(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text('[camera]\nwidth = 16\nheight = 12\nsampling = "gauss"\n')
    scene = jl.load_scene(path)
    assert scene.camera.sampling == "gauss"
    bad = tmp_path / "b.toml"
    bad.write_text('[camera]\nsampling = "box"\n')
    with pytest.raises(ValueError, match="sampling"):
        jl.load_scene(bad)
    from jaxlens.cli import main

    out = tmp_path / "o.exr"
    assert main(["render", str(path), "-o", str(out), "--sky", "star"]) == 0
    img = jl.read_image(out)
    assert img.shape == (12, 16, 3) and np.all(np.isfinite(img))
