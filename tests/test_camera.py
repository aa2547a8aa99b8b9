"""Camera conventions (PHYSICS.md, "Pixels"), orientation, batches and bad input."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl

# Pixel positions are sums of a few exactly representable numbers: compare to 1e-12.
# Angles from them go through atan2/hypot: float64 round-off, 1e-12 rad.
EXACT = 1e-12


def reference_samples(w, h, k, fov):
    """PHYSICS.md written out directly: sample (m, n) of pixel (i, j) at column
    i + (m + 0.5)/k, row j + (n + 0.5)/k; x = column - W/2, y = H/2 - row."""
    f = (w / 2) / math.tan(fov / 2)
    xs = np.empty((h, w, k * k))
    ys = np.empty((h, w, k * k))
    for j in range(h):
        for i in range(w):
            for n in range(k):
                for m in range(k):
                    xs[j, i, n * k + m] = i + (m + 0.5) / k - w / 2
                    ys[j, i, n * k + m] = h / 2 - (j + (n + 0.5) / k)
    return xs, ys, f


@pytest.mark.parametrize("w,h,k", [(6, 4, 1), (5, 3, 1), (4, 3, 2), (3, 5, 3)])
def test_sample_positions_and_angles_follow_physics_md(w, h, k):
    fov = math.radians(70.0)
    cam = jl.Camera(10.0, fov, w, h, supersample=k)
    x, y = cam.sample_xy()
    xr, yr, f = reference_samples(w, h, k, fov)
    np.testing.assert_allclose(x, xr, atol=EXACT, rtol=0)
    np.testing.assert_allclose(y, yr, atol=EXACT, rtol=0)
    assert float(cam.focal) == pytest.approx(f, rel=1e-15)
    alpha, cb, sb = cam.rays()
    np.testing.assert_allclose(alpha, np.arctan(np.hypot(xr, yr) / f), atol=EXACT, rtol=0)
    beta = np.arctan2(yr, xr)
    centre = np.hypot(xr, yr) == 0  # beta is arbitrary on the axis (alpha = 0)
    np.testing.assert_allclose(np.where(centre, 1, cb), np.where(centre, 1, np.cos(beta)),
                               atol=EXACT)  # fmt: skip
    np.testing.assert_allclose(np.where(centre, 0, sb), np.where(centre, 0, np.sin(beta)),
                               atol=EXACT)  # fmt: skip


def test_pixel_centres_one_sample():
    # Pixel (0, 0) of a 4 x 2 image: centre x = 0.5 - 2 = -1.5, y = 1 - 0.5 = 0.5.
    cam = jl.Camera(10.0, math.radians(90.0), 4, 2)
    x, y = cam.sample_xy()
    assert (float(x[0, 0, 0]), float(y[0, 0, 0])) == (-1.5, 0.5)
    assert (float(x[1, 3, 0]), float(y[1, 3, 0])) == (1.5, -0.5)
    # 90 degree FOV: f = W/2 = 2 pixels; the right edge (x = 2) is 45 degrees.
    assert float(cam.focal) == pytest.approx(2.0, rel=1e-15)


def test_supersample_positions():
    # k = 3: sub-sample centres at 1/6, 1/2, 5/6 of a pixel.
    cam = jl.Camera(10.0, 1.0, 1, 1, supersample=3)
    x, y = cam.sample_xy()
    np.testing.assert_allclose(np.unique(np.asarray(x)), np.array([1, 3, 5]) / 6 - 0.5,
                               atol=EXACT)  # fmt: skip
    np.testing.assert_allclose(np.unique(np.asarray(y)), 0.5 - np.array([5, 3, 1]) / 6,
                               atol=EXACT)  # fmt: skip
    assert x.shape == (1, 1, 9)


def test_yaw_moves_the_hole_left_and_pitch_down():
    f = 50.0
    fov = 2 * math.atan(50 / f)  # W = 100
    yaw = math.radians(10.0)
    cam = jl.Camera(10.0, fov, 100, 60, yaw=yaw)
    # Turning the view right by yaw puts the hole (alpha = 0) at x = -f tan(yaw).
    x = jnp.asarray([[-f * math.tan(yaw)]])
    alpha, _, _ = cam._angles(x, jnp.zeros_like(x), oriented=True)
    assert float(alpha[0, 0]) == pytest.approx(0.0, abs=1e-7)
    pitch = math.radians(5.0)
    cam = jl.Camera(10.0, fov, 100, 60, pitch=pitch)
    y = jnp.asarray([[-f * math.tan(pitch)]])
    alpha, _, _ = cam._angles(jnp.zeros_like(y), y, oriented=True)
    assert float(alpha[0, 0]) == pytest.approx(0.0, abs=1e-7)


def test_roll_turns_beta():
    roll = 0.3
    a = jl.Camera(10.0, 1.0, 8, 6)
    b = jl.Camera(10.0, 1.0, 8, 6, roll=roll)
    alpha_a, cb_a, sb_a = a.rays()
    alpha_b, cb_b, sb_b = b.rays()
    np.testing.assert_allclose(alpha_b, alpha_a, atol=EXACT)
    # Roll turns every pixel's ray plane by +roll: the view turns from +x toward +y
    # (counter-clockwise), the scene on the image clockwise.
    turned = np.angle(np.exp(1j * (np.arctan2(sb_a, cb_a) + roll)))
    np.testing.assert_allclose(np.arctan2(sb_b, cb_b), turned, atol=1e-12)


def test_rotation_matrix_convention():
    # R maps +z to the direction at (lon = yaw, lat = pitch) and is orthonormal.
    for yaw, pitch, roll in [(0.3, 0.2, 0.1), (-2.0, -1.0, 3.0)]:
        r = np.asarray(jl.rotation_matrix(yaw, pitch, roll))
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(r[:, 2], jl.direction_from_angles(yaw, pitch), atol=1e-14)


def test_position_rotation_puts_the_hole_in_front_of_the_sky_point():
    cam = jl.Camera(10.0, 1.0, 4, 4, azimuth=0.7, elevation=-0.4)
    behind = cam.to_world(jnp.asarray([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(behind, jl.direction_from_angles(0.7, -0.4), atol=1e-14)


def test_sky_direction_flat_space():
    # Flat space: Phi = pi - alpha gives back the ray's own direction.
    alpha, beta = 0.4, 1.1
    n = jl.sky_direction(math.pi - alpha, math.cos(beta), math.sin(beta))
    expect = [math.sin(alpha) * math.cos(beta), math.sin(alpha) * math.sin(beta), math.cos(alpha)]
    np.testing.assert_allclose(n, expect, atol=1e-15)


def test_batches_of_cameras():
    cam = jl.Camera(20.0, 1.0, 8, 6, supersample=2)
    d = np.geomspace(1e5, 3.0, 5)
    a = jl.approach(cam, d)
    assert a.batch_shape == (5,)
    np.testing.assert_array_equal(a.distance, d)
    np.testing.assert_array_equal(a.fov, np.ones(5))
    o = jl.orbit(cam, np.linspace(0, 2 * np.pi, 4, endpoint=False))
    assert o.azimuth.shape == (4,) and (o.width, o.height, o.supersample) == (8, 6, 2)
    z = jl.zoom(cam, [1.0, 0.5])
    np.testing.assert_array_equal(z.fov, [1.0, 0.5])
    p = jl.pan(cam, [0.0, 0.1, 0.2])
    np.testing.assert_array_equal(p.yaw, [0.0, 0.1, 0.2])
    s = jl.stack_cameras([cam, jl.Camera(30.0, 0.5, 8, 6, supersample=2)])
    np.testing.assert_array_equal(s.distance, [20.0, 30.0])
    # A batch is a pytree: vmap sees one camera at a time.
    focal = jax.vmap(lambda c: c.focal)(s)
    np.testing.assert_allclose(focal, 4.0 / np.tan(np.array([0.5, 0.25])), rtol=1e-14)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(distance=1.0), "distance=1.0"),
        (dict(distance=0.5), "distance=0.5"),
        (dict(distance=-3.0), "distance=-3.0"),
        (dict(distance=float("nan")), "distance=nan"),
        (dict(distance=float("inf")), "distance=inf"),
        (dict(fov=0.0), r"fov=0.0 degrees"),
        (dict(fov=math.pi), r"fov=180.0 degrees"),
        (dict(fov=-0.1), "fov="),
        (dict(width=0), "width=0"),
        (dict(height=-5), "height=-5"),
        (dict(width=2.5), "width=2.5"),
        (dict(supersample=0), "supersample=0"),
        (dict(yaw=float("nan")), "yaw="),
    ],
)
def test_bad_camera_raises_naming_the_argument(kwargs, match):
    args = dict(distance=10.0, fov=1.0, width=4, height=4)
    args.update(kwargs)
    d, f, w, h = (args.pop(k) for k in ("distance", "fov", "width", "height"))
    with pytest.raises(ValueError, match=match):
        jl.Camera(d, f, w, h, **args)


def test_distance_too_close_for_the_dtype():
    message = r"distance=1.000000001 rounds to 1\.0 \(the horizon\) in float32"
    with pytest.raises(ValueError, match=message):
        jl.Camera(1 + 1e-9, 1.0, 4, 4, dtype=np.float32)
    assert float(jl.Camera(1 + 1e-9, 1.0, 4, 4).distance) == 1 + 1e-9  # float64 holds it


def test_bad_batch_raises():
    cam = jl.Camera(20.0, 1.0, 8, 6)
    with pytest.raises(ValueError, match="distance=0.5"):
        jl.approach(cam, [10.0, 0.5])
    with pytest.raises(ValueError, match="share width"):
        jl.stack_cameras([cam, jl.Camera(20.0, 1.0, 8, 7)])


def test_roll_turns_the_scene_clockwise_on_the_image():
    # A star to the right of the hole (longitude +25 degrees, toward +x): at roll = +90
    # degrees its image moves from the right of the centre to below it (row 0 is the
    # top), as the docstring says (it said counter-clockwise).
    sky = jl.GaussianStar(math.radians(3.0), 1.0, lon=math.radians(25.0), lat=0.0)
    spots = []
    for roll in (2 * math.pi, math.pi / 2):  # a full turn: no roll, the same program
        img = np.asarray(jl.render(jl.Camera(50.0, math.radians(90.0), 16, 12, roll=roll), sky))
        row, col = np.unravel_index(np.argmax(img.sum(-1)), img.shape[:2])
        spots.append((col + 0.5 - 8.0, 6.0 - (row + 0.5)))  # x right, y up, pixels
    (x0, y0), (x1, y1) = spots
    assert x0 > 2.5 and abs(y0) < 1.0  # right of the centre
    assert y1 < -2.5 and abs(x1) < 1.0  # below it: turned clockwise
