"""Values checked where they are used: a bad traced value is an error under `jit`, never
a NaN or black image; the same values are a `ValueError` eagerly."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl

SKY = jl.GaussianStar(math.radians(2.0), 1.0) + jl.Uniform(0.1)


def _image(distance=20.0, fov=1.0, *, r_in=3.0, r_out=12.0, motion=None):
    cam = jl.Camera(distance, fov, 6, 4)
    disk = None if r_in is None else jl.Disk(r_in, r_out, 1.2)
    return jl.render_array(jl.Scene(cam, SKY, motion=motion, disk=disk))


_jitted = eqx.filter_jit(_image)
# One program for every case of a test (a lambda made inside the test compiled anew for
# each parametrisation: 6 s each).
_disk_radii = eqx.filter_jit(lambda a, b: _image(r_in=a, r_out=b))


def test_good_values_render_under_jit():
    img = np.asarray(_jitted(jnp.asarray(20.0), jnp.asarray(1.0), r_in=jnp.asarray(3.0)))
    assert img.shape == (4, 6, 3) and np.all(np.isfinite(img)) and img.max() > 0


@pytest.mark.parametrize("distance", [0.5, 1.0, -3.0, math.nan, math.inf])
def test_bad_distance_raises_under_jit(distance):
    with pytest.raises(Exception, match="camera distance must be finite and > 1"):
        jax.block_until_ready(_jitted(jnp.asarray(distance), jnp.asarray(1.0), r_in=None))


@pytest.mark.parametrize("fov", [0.0, -0.2, math.pi, 4.0, math.nan])
def test_bad_field_of_view_raises_under_jit(fov):
    with pytest.raises(Exception, match=r"field of view must be in \(0, pi\)"):
        jax.block_until_ready(_jitted(jnp.asarray(20.0), jnp.asarray(fov), r_in=None))


@pytest.mark.parametrize(
    "r_in,r_out", [(1.2, 12.0), (1.5, 12.0), (12.0, 12.0), (14.0, 12.0), (3.0, math.inf)]
)
def test_bad_disk_radii_raise_under_jit(r_in, r_out):
    # The disk is built from traced radii (its eager check cannot see them).
    with pytest.raises(Exception, match="disk radii must satisfy 1.5 < r_in < r_out"):
        jax.block_until_ready(_disk_radii(jnp.asarray(r_in), jnp.asarray(r_out)))


def test_orbit_inside_the_photon_sphere_raises_under_jit():
    f = eqx.filter_jit(lambda d: _image(d, r_in=None, motion=jl.CircularOrbit(0.0)))
    assert np.all(np.isfinite(np.asarray(f(jnp.asarray(5.0)))))
    with pytest.raises(Exception, match="circular orbit needs distance > 1.5"):
        jax.block_until_ready(f(jnp.asarray(1.4)))


def test_field_of_view_below_the_dtype_resolution():
    # Samples closer than 4 ulps of the dtype: 6 px across, float32 -> 1.6e-4 degrees.
    small = jl.Camera(20.0, math.radians(1e-4), 6, 4, dtype=np.float32)
    with pytest.raises(ValueError, match=r"at least 0.00016\d* degrees .*float64 reaches"):
        jl.render(small, SKY)
    f = jax.jit(lambda fov: jl.render_array(jl.Camera(20.0, fov, 6, 4), SKY))
    with pytest.raises(Exception, match="narrower fields are below the resolution"):
        jax.block_until_ready(f(np.float32(math.radians(1e-4))))
    # The same field in float64, and float32 just above its limit, render.
    ok = jl.Camera(20.0, math.radians(1e-4), 6, 4, dtype=np.float64)
    assert np.all(np.isfinite(jl.render(ok, SKY)))
    assert np.all(np.isfinite(np.asarray(f(np.float32(math.radians(2e-4))))))


def test_the_same_values_are_value_errors_eagerly():
    with pytest.raises(ValueError, match="distance"):
        jl.Camera(0.5, 1.0, 6, 4)
    with pytest.raises(ValueError, match="field of view"):
        jl.Camera(20.0, 4.0, 6, 4)
    with pytest.raises(ValueError, match="r_in"):
        jl.Disk(1.2, 12.0, 1.0)
    with pytest.raises(ValueError, match="D > 1.5"):
        jl.Scene(jl.Camera(1.4, 1.0, 6, 4), SKY, motion=jl.CircularOrbit())


def test_trace_checks_its_distance_under_jit():
    f = jax.jit(lambda d: jl.trace(jnp.asarray([0.5, 1.0]), d).phi)
    assert np.all(np.isfinite(np.asarray(f(10.0))))
    with pytest.raises(Exception, match="distance must be finite and > 1"):
        jax.block_until_ready(f(0.9))


def test_the_issue_reproduction_now_raises():
    # jax.jit of a render at a traced distance inside the horizon gave 48 NaN pixels.
    f = jax.jit(lambda d: jl.render_array(jl.Camera(d, 1.0, 4, 4), SKY))
    with pytest.raises(Exception, match="camera distance must be finite and > 1"):
        jax.block_until_ready(f(0.5))


# ---------------------------------------------------------------- the ray-level API

_trace_jit = jax.jit(lambda a, d: jl.trace(a, d).phi)


@pytest.mark.parametrize("distance", [1e300, np.float32(1e35), 1e31])
def test_trace_refuses_a_distance_beyond_the_largest_supported(distance):
    # float64 1e300 (and float32 1e39) gave every ray "unresolved" and a RuntimeWarning.
    message = r"distance=1\.?\d*e\+3\d+ is beyond the largest supported, 1e\+30 R_S"
    with pytest.raises(ValueError, match=message):
        jl.trace(0.5, distance)
    with pytest.raises(Exception, match=r"distance must be finite and > 1 .* at most 1e\+30"):
        jax.block_until_ready(_trace_jit(jnp.asarray([0.5]), distance))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_trace_is_accurate_up_to_the_largest_distance(dtype):
    # float32 overflowed in b^2 (the closed form) and underflowed in u'^2 (the
    # integrators' last step) beyond D ~ 1e19: every ray unresolved. At D = 1e30 the
    # deflection 2/b is below float32's resolution: phi = pi - alpha to a few ulps of pi.
    # RK4 at the default accuracy 1e-6 takes ~70 steps of 0.044 rad, each rounded in
    # the dtype: 1e-6 + 70 eps pi.
    alpha = np.asarray([1e-6, 0.5, 1.5, 2.5], dtype)
    eps = np.finfo(dtype).eps
    for d in (np.asarray(1e30, dtype), np.asarray(1e20, dtype)):
        # flat space plus the weak-field deflection 2/b (2e-14 at b = 1e14)
        a64 = alpha.astype(np.float64)
        want = np.pi - a64 + 2.0 / (float(d) * np.sin(a64))
        for method, tol in (("exact", 8 * eps * np.pi), ("table", 1e-6 + 8 * eps * np.pi),
                            ("rk4", 1e-6 + 70 * eps * np.pi)):  # fmt: skip
            r = jl.trace(alpha, d, method=method)
            assert np.all(np.asarray(r.escaped)), (d, method)
            np.testing.assert_allclose(np.asarray(r.phi), want, atol=tol, rtol=0)
        phi, bound = jl.weak_field_escape_angle(alpha[1:], d)
        assert np.all(np.abs(np.asarray(phi) - want[1:]) <= np.asarray(bound) + 4 * eps)


def test_trace_refuses_a_nan_or_out_of_range_alpha():
    # A NaN alpha was "unresolved" with a message about the winding budget.
    for alpha in (math.nan, -0.1, 3.2, math.inf):
        with pytest.raises(ValueError, match=r"alpha=.* is not a valid local angle: it must "
                           r"be in \[0, pi\] radians"):  # fmt: skip
            jl.trace(np.asarray([0.5, alpha]), 10.0)
    # pi itself, in float32 (rounded up from pi) and float64, is a ray straight away.
    for dtype in (np.float32, np.float64):
        assert np.all(np.asarray(jl.trace(np.asarray([0, np.pi], dtype), 10.0).escaped)[1:])
    with pytest.raises(Exception, match=r"alpha must be in \[0, pi\] radians"):
        jax.block_until_ready(_trace_jit(jnp.asarray([0.5, math.nan]), 10.0))


def test_trace_refuses_wrong_types_by_name():
    with pytest.raises(TypeError, match=r"method=5 must be one of 'auto', 'exact'.*"
                       "AbstractMethod"):  # fmt: skip
        jl.trace(0.5, 10.0, method=5)
    with pytest.raises(TypeError, match=r"distance=\(10\+1j\) must be real numbers"):
        jl.trace(0.5, 10.0 + 1j)
    with pytest.raises(TypeError, match=r"alpha='x' must be real numbers"):
        jl.trace("x", 10.0)
    with pytest.raises(TypeError, match=r"dtype of alpha and distance: float16 is not "
                       "supported, use float32 or float64"):  # fmt: skip
        jl.trace(np.float16(0.5), np.float16(10.0))
    for name, value in (("accuracy", math.nan), ("max_windings", math.inf)):
        with pytest.raises(ValueError, match=f"{name}=(nan|inf) must be finite and > 0"):
            jl.trace(0.5, 10.0, **{name: value})


_build_jit = jax.jit(lambda d: jl.RayMap.build(d, knots=64).alpha_sh)


@pytest.mark.parametrize("distance", [1.0, 0.5, -2.0, math.nan, math.inf, 1e31])
def test_ray_map_refuses_the_distances_trace_refuses(distance):
    # Every ray was "captured" with alpha_sh NaN, without an error.
    with pytest.raises(ValueError, match=r"distance=.* (is not a valid camera radius|is beyond "
                       "the largest supported)"):  # fmt: skip
        jl.RayMap.build(distance, knots=64)
    with pytest.raises(Exception, match="distance must be finite and > 1"):
        jax.block_until_ready(_build_jit(jnp.asarray(distance)))


def test_ray_map_builds_at_the_ends_of_the_range():
    assert math.isclose(float(_build_jit(jnp.asarray(3.0))), math.pi / 4, rel_tol=1e-14)
    with pytest.raises(TypeError, match=r"distance=\(3\+1j\) must be real numbers"):
        jl.RayMap.build(3.0 + 1j)
    # float32 at the largest distance (its closed form overflowed beyond 1e19): alpha_sh
    # = b_c / D, the knots' escape angles finite and falling with alpha (to the float32
    # rounding of values up to 19 rad, 16 ulps: 3e-5); the look-up is checked through
    # trace(method="table").
    m = jl.RayMap.build(np.float32(1e30), accuracy=1e-5)
    np.testing.assert_allclose(float(m.alpha_sh), jl.B_CRIT / 1e30, rtol=1e-6)
    phi = np.asarray(m.phi)
    assert np.all(np.isfinite(phi)) and np.all(np.diff(phi) <= 3e-5)


@pytest.mark.parametrize(
    "args,kwargs,error,match",
    [
        ((1e300, 1.0, 16, 12), {}, ValueError, r"distance=1e\+300 is beyond the largest"),
        # the cast to float32 gave distance=inf
        ((1e300, 1.0, 16, 12), {"dtype": np.float32}, ValueError,
         r"distance=1e\+300 is beyond the largest"),
        (("x", 1.0, 16, 12), {}, TypeError, r"distance='x' must be real numbers"),
        ((20.0 + 1j, 1.0, 16, 12), {}, TypeError, r"distance=\(20\+1j\) must be real numbers"),
        ((20.0, 1.0, 16, 12), {"dtype": np.int32}, TypeError,
         "dtype: int32 is not supported, use float32 or float64"),
        ((20.0, 1.0, 16, 12), {"dtype": np.float16}, TypeError,
         "dtype: float16 is not supported, use float32 or float64"),
        ((np.float16(20.0), np.float16(1.0), 16, 12), {}, TypeError,
         "dtype: float16 is not supported"),
        ((20.0, 1.0, 10**30, 12), {}, ValueError,
         "width=1000000000000000000000000000000 must be a whole number from 1 to 1,048,575"),
        ((20.0, 1.0, 16, 1 << 20), {}, ValueError,
         "height=1048576 must be a whole number from 1 to 1,048,575"),
        ((20.0, 1.0, 16, 12), {"supersample": 65}, ValueError,
         "supersample=65 must be a whole number from 1 to 64"),
        ((20.0, 1.0, 16, 12), {"roll": 1e300, "dtype": np.float32}, ValueError,
         r"roll=1e\+300 must be finite in float32"),
        ((20.0, 1.0, 16, 12), {"yaw": True}, TypeError, "yaw=True must be real numbers"),
    ],
)  # fmt: skip
def test_camera_refuses_bad_values_by_name(args, kwargs, error, match):
    with pytest.raises(error, match=match):
        jl.Camera(*args, **kwargs)


def test_camera_takes_the_largest_values():
    cam = jl.Camera(1e30, 1.0, (1 << 20) - 1, 1, supersample=64, dtype=np.float32)
    assert float(cam.distance) == pytest.approx(1e30, rel=1e-7) and cam.width == 1048575
    assert jl.Camera(np.float32(1e30), np.float32(1.0), 16, 12).dtype == np.float32
    # A float32 camera's 1e30 (1.0000000150e30) widened to float64, as the renderer
    # builds its table, is still in range.
    wide = float(np.float32(1e30))
    assert float(jl.RayMap.build(wide, knots=64).alpha_sh) == pytest.approx(jl.B_CRIT / wide)
    assert float(_build_jit(jnp.asarray(wide))) == pytest.approx(jl.B_CRIT / wide)


def test_weak_field_series_refuses_a_camera_inside_the_horizon():
    # (0.3, 0.5) gave a finite escape angle and bound.
    with pytest.raises(ValueError, match=r"distance=0.5 is not a valid camera radius"):
        jl.weak_field_escape_angle(0.3, 0.5)
    with pytest.raises(ValueError, match=r"alpha=nan is not a valid local angle"):
        jl.weak_field_escape_angle(math.nan, 50.0)
    f = jax.jit(lambda d: jl.weak_field_escape_angle(jnp.asarray([0.3]), d)[0])
    assert np.all(np.isfinite(np.asarray(f(50.0))))
    with pytest.raises(Exception, match="distance must be finite and > 1"):
        jax.block_until_ready(f(0.5))


_MAP = None


def _ray_map():
    global _MAP
    if _MAP is None:
        _MAP = jl.RayMap.build(20.0, accuracy=1e-8)
    return _MAP


def test_point_images_refuse_a_map_of_a_bad_distance():
    # A map's distance set by tree_at (RayMap.build refuses it now): NaN images before.
    bad = eqx.tree_at(lambda m: m.distance, _ray_map(), jnp.asarray(0.5))
    source = np.asarray([0.1, 0.0, 1.0])
    with pytest.raises(ValueError, match="distance=0.5 is not a valid camera radius"):
        jl.point_source_images(source, bad)
    with pytest.raises(ValueError, match="distance=0.5 is not a valid camera radius"):
        jl.magnification(np.asarray([0.3, 0.0]), bad)
    with pytest.raises(ValueError, match=r"direction=\[0.0, 0.0, 0.0\] is not valid: a finite, "
                       "non-zero 3-vector"):  # fmt: skip
        jl.point_source_images(np.zeros(3), _ray_map())
    with pytest.raises(ValueError, match=r"p=\[nan, 0.0\] is not valid"):
        jl.magnification(np.asarray([math.nan, 0.0]), _ray_map())


def test_point_images_check_their_values_under_jit():
    def alpha(d, source):
        ray_map = eqx.tree_at(lambda m: m.distance, _ray_map(), d)
        return jl.point_source_images(source, ray_map).alpha

    f = jax.jit(alpha)
    good = jnp.asarray([0.1, 0.0, 1.0])
    assert np.all(np.isfinite(np.asarray(f(jnp.asarray(20.0), good))))
    with pytest.raises(Exception, match="distance must be finite and > 1"):
        jax.block_until_ready(f(jnp.asarray(0.5), good))
    with pytest.raises(Exception, match="direction must be a finite, non-zero 3-vector"):
        jax.block_until_ready(f(jnp.asarray(20.0), jnp.asarray([math.nan, 0.0, 1.0])))


_ring_angle = jax.jit(jl.einstein_ring_angle)  # a program a dtype, scalar distances


def test_einstein_ring_angle_refuses_rings_no_camera_sees():
    # NaN below D = 1.760309 (the docstring said "D <~ 1.9").
    for d in (1.76, 1.7, 1.6):
        with pytest.raises(ValueError, match=rf"distance={d} is below 1.7603089815759632 R_S"):
            jl.einstein_ring_angle(d)
    with pytest.raises(ValueError, match="is not a valid camera radius"):
        jl.einstein_ring_angle(0.5)
    f = _ring_angle
    with pytest.raises(Exception, match=r"distance is below 1.7603089815759632 R_S"):
        jax.block_until_ready(f(jnp.asarray(1.7)))
    # The bound is where the ring reaches pi/2: Phi(pi/2) = pi there, to 1e-12 rad (the
    # slope dPhi/dD ~ 1 at the bound: the constant's last digit moves Phi by 2e-16).
    d_ring = 1.7603089815759632
    assert abs(float(jl.trace(math.pi / 2, d_ring, accuracy=1e-14).phi) - math.pi) < 1e-12
    assert float(f(jnp.asarray(d_ring))) == pytest.approx(math.pi / 2, abs=1e-9)


def test_einstein_ring_angle_float32_keeps_its_relative_accuracy():
    # Solving Phi = pi on the table in float32 lost eps pi / 2 in alpha ~ sqrt(2/D):
    # relative 3.6e-4 at D = 1e8 and 9 % at 1e12. At 1e3 (the table still) the loss is
    # eps pi / (2 alpha) = 4.1e-6; from 2e3 the weak-field series keeps a few ulps (8:
    # 1e-6).
    for d, rtol in ((1e3, 1e-5), (1e8, 1e-6), (1e12, 1e-6)):
        want = float(_ring_angle(jnp.float64(d)))
        got = _ring_angle(jnp.float32(d))
        assert got.dtype == np.float32
        assert abs(float(got) - want) <= rtol * want, (d, float(got), want)
    # float64 against the weak-field limit sqrt(2/D) (1 + O(1/sqrt(D)): 1e-6 at 1e12)
    assert float(_ring_angle(jnp.float64(1e12))) == pytest.approx(math.sqrt(2e-12), rel=2e-6)


def test_a_forced_weak_field_keeps_the_accuracy():
    # method="weak_field" ignored accuracy: 4.4e-6 rad at D = 50 against 1e-8 asked.
    sky = jl.GaussianStar(math.radians(2.0), 1.0)
    cam = jl.Camera(50.0, math.radians(60.0), 16, 12)
    scene = jl.Scene(cam, sky, method="weak_field", accuracy=1e-8)
    with pytest.raises(ValueError, match=r"method='weak_field' is forced, but the weak-field "
                       r"series' error bound (\d\.\d\de-0\d rad|inf).* not below the accuracy "
                       r"1\.0e-08 rad: use method='auto' or 'table'"):  # fmt: skip
        jl.plan(scene)
    # Far and narrow, the bound is below a looser accuracy: the series is used.
    far = scene.replace(camera=jl.Camera(1e4, math.radians(5.0), 16, 12), accuracy=1e-4)
    p = jl.plan(far)
    assert p.geometry == "weak_field" and p.weak_bound < 1e-4


def test_camera_sweeps_refuse_values_before_their_cast():
    # approach/pan from 1e300 gave distance=inf / yaw=inf (float32) and a RuntimeWarning.
    cam = jl.Camera(20.0, 1.0, 8, 6, dtype=np.float32)
    with pytest.raises(ValueError, match=r"distance=1e\+300 is beyond the largest supported"):
        jl.approach(cam, [10.0, 1e300])
    with pytest.raises(ValueError, match=r"yaw=1e\+300 must be finite in float32"):
        jl.pan(cam, [0.0, 1e300])
    with pytest.raises(TypeError, match=r"azimuth=.* must be real numbers"):
        jl.orbit(cam, [0.0, 1j])
    assert jl.approach(cam, [10.0, 1e30]).batch_shape == (2,)
