"""A scene's sky on a sphere at a finite distance (`Scene(..., source_distance=R)`):
`None` is the sky at infinity unchanged, a far sphere agrees with it, a star on the
sphere is imaged where `point_source_images_at` puts it (beyond the camera, and inside
its radius through the second crossing), the hard radii render finite, bad values are
refused eagerly and under `jit`, and the redshift of a static emitter at R."""

import math
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl

D = 20.0
SMOOTH = jl.GaussianStar(0.6, direction=(0.3, 0.2, 1.0)) + jl.Uniform(0.05)
# One image size and sky structure for the renders: they share one compiled program
# (the distances, the field of view and the sky's values are arguments).
W, H, FOV = 96, 64, math.radians(90.0)


def _camera(width=W, height=H, fov=FOV, k=2, **kw):
    return jl.Camera(D, fov, width, height, supersample=k, **kw)


def test_none_is_the_sky_at_infinity_bit_for_bit():
    cam = _camera()
    before, after = jl.Scene(cam, SMOOTH), jl.Scene(cam, SMOOTH, source_distance=None)
    assert jax.tree.structure(before) == jax.tree.structure(after)
    assert jl.plan(before) == jl.plan(after)
    assert np.array_equal(jl.render(before), jl.render(after))  # bit for bit
    # A concrete inf is the sky at infinity: the same structure, plan and program.
    far = jl.Scene(cam, SMOOTH, source_distance=float("inf"))
    assert far.source_distance is None
    assert jl.plan(far).geometry == jl.plan(before).geometry != "crossings"


def test_far_sphere_agrees_with_infinity_and_float32_works():
    cam = _camera()
    ref = jl.render(jl.Scene(cam, SMOOTH))
    scene = jl.Scene(cam, SMOOTH, source_distance=1e12)
    assert jl.plan(scene).geometry == "table"  # the ray map of (D, R)
    far = jl.render(scene)
    # At R = 1e12 a crossing's azimuth differs from the escape angle by ~b/R ~ 1e-11
    # rad: the pixels agree to float32 output rounding, far below 1e-6 of the peak.
    assert np.max(np.abs(far - ref)) <= 1e-6 * np.max(ref)
    # ... and so do the exact crossings per ray.
    exact = jl.render(scene.replace(method="trace"))
    assert jl.plan(scene.replace(method="trace")).geometry == "crossing"  # one a ray
    assert np.max(np.abs(exact - ref)) <= 1e-6 * np.max(ref)
    f32 = jl.render(scene, dtype="float32")
    # float32 sky directions are good to ~1e-6 rad, the sky's slope ~1/sigma per rad,
    # and the shadow-edge ramp moves by float32's share of a sample: 1e-3 of the peak.
    assert np.all(np.isfinite(f32)) and np.max(np.abs(f32 - ref)) <= 1e-3 * np.max(ref)


def test_ray_map_of_the_sphere_agrees_with_the_exact_crossings():
    cam = _camera()
    scene = jl.Scene(cam, SMOOTH, source_distance=2.0 * D)
    plan = jl.plan(scene)
    assert plan.geometry == "table" and any("ray map of (D, R)" in r for r in plan.reasons)
    table = jl.render(scene)
    exact = jl.render(scene.replace(method="trace"))
    # The table's interpolation error (1e-8 rad, the scene's accuracy) times the sky's
    # slope (~1/sigma = 1.7 a radian) is far below the float32 output's rounding: 1e-6.
    assert np.max(np.abs(table - exact)) <= 1e-6 * np.max(exact)
    assert not np.allclose(table, jl.render(jl.Scene(cam, SMOOTH)), rtol=1e-3)  # R shows
    # Between D and 1.25 D the crossing bends sharply near alpha = pi/2: exact per ray.
    near = jl.plan(jl.Scene(cam, SMOOTH, source_distance=1.1 * D))
    assert near.geometry == "crossing" and any("< 1.25 D" in r for r in near.reasons)
    # ... the same pixels as the two-crossing form (a traced R takes it), whose second
    # crossing never occurs beyond the camera: to float32 output rounding.
    once = jl.render(jl.Scene(cam, SMOOTH, source_distance=1.1 * D))
    traced = eqx.filter_jit(jl.render_array)(jl.Scene(cam, SMOOTH, source_distance=1.1 * D))
    assert np.max(np.abs(once - np.asarray(traced))) <= 1e-6 * np.max(once)


# A star 6 degrees off the axis behind the hole, on the sphere: each of its two
# order-0 images must be the brightest pixel of its half of the image.
THETA = math.radians(6.0)
STAR_DIR = (math.sin(THETA), 0.0, math.cos(THETA))


@pytest.mark.parametrize("radius", [40.0, 10.0])  # beyond the camera; inside its radius
def test_star_on_the_sphere_is_imaged_where_point_source_images_at_says(radius):
    sky = jl.GaussianStar(math.radians(0.7), direction=STAR_DIR) + jl.Uniform(0.0)
    img = jl.render(jl.Scene(_camera(), sky, source_distance=radius))[..., 0]
    images = jl.point_source_images_at(np.asarray(STAR_DIR), D, radius)
    f = (W / 2) / math.tan(FOV / 2)
    at_inf = jl.point_source_images_at(np.asarray(STAR_DIR), D)
    for k in range(2):  # primary (right, beta = 0), secondary (left, beta = pi)
        a, b = float(images.alpha[k]), float(images.beta[k])
        col = f * math.tan(a) * math.cos(b) + W / 2 - 0.5
        row = H / 2 - 0.5 - f * math.tan(a) * math.sin(b)
        half = slice(W // 2, W) if math.cos(b) > 0 else slice(0, W // 2)
        r, c = np.unravel_index(np.argmax(img[:, half]), (H, W // 2))
        c += half.start
        # Each image is an arc along its circle about the centre (tangentially
        # stretched, |mu| 1.2-2.7), symmetric about the middle rows: the brightest
        # pixel lies on the predicted circle, and on the middle rows the brightest
        # column is the image's own; both within one pixel.
        radius_px = math.hypot(c + 0.5 - W / 2, H / 2 - r - 0.5)
        assert abs(radius_px - f * math.tan(a)) <= 1.0, (k, (c, r), (col, row))
        middle = img[H // 2 - 1 : H // 2 + 1, half].max(axis=0)
        assert abs(np.argmax(middle) + half.start - col) <= 1.0, (k, col)
        # ... and the sphere moved it: the image at infinity lies >= 2 pixels away.
        a_inf = float(at_inf.alpha[k])
        assert abs(f * (math.tan(a_inf) - math.tan(a))) >= 2.0


def test_hard_radii_render_finite():
    cam = _camera(fov=math.radians(120.0))
    # Inside the photon sphere (1.3), on it, through the camera, just beyond it, and
    # R = 10, whose grazing rays (periapsis at R) lie in the view.
    for radius in (1.3, 1.5, D, D * (1 + 1e-12), 10.0):
        img = jl.render(jl.Scene(cam, SMOOTH, source_distance=radius))
        assert np.all(np.isfinite(img)), radius
    # Inside the photon sphere only captured rays reach the sphere: light inside the
    # shadow, none outside it (the centre pixels see the sky, the corners do not).
    img = jl.render(jl.Scene(cam, SMOOTH, source_distance=1.3))
    assert img[H // 2, W // 2].sum() > 0 and img[0, 0].sum() == 0
    # The exact crossings in float32: sky directions to ~1e-6 rad (the closed form's
    # float32 floor) against float64, the sky's slope ~2 a radian: 1e-5 of the peak.
    inner = jl.Scene(cam, SMOOTH, source_distance=10.0)
    ref = jl.render(inner)
    assert np.max(np.abs(jl.render(inner, dtype="float32") - ref)) <= 1e-5 * np.max(ref)


@pytest.mark.parametrize("radius", [0.5, 1.0, math.nan, -math.inf, 1e31])
def test_bad_radius_is_refused_eagerly(radius):
    with pytest.raises(ValueError, match="source_distance="):
        jl.Scene(_camera(), SMOOTH, source_distance=radius)


_SMALL = jl.Scene(_camera(6, 4, k=1), SMOOTH, source_distance=10.0)
_TRACED = eqx.filter_jit(
    lambda r: jl.render_array(eqx.tree_at(lambda s: s.source_distance, _SMALL, r))
)


@pytest.mark.parametrize("radius", [0.5, math.nan, math.inf])
def test_bad_radius_raises_under_jit(radius):
    with pytest.raises(Exception, match="source distance must be > 1"):
        jax.block_until_ready(_TRACED(jnp.asarray(radius)))


def test_redshift_of_a_static_emitter_on_the_sphere():
    cam = jl.Camera(3.0, math.radians(150.0), 24, 16)  # the shadow fills 90 of 150 deg
    shift = jl.Redshift("bolometric")
    level = jl.Uniform(1.0)
    at_inf = jl.render(jl.Scene(cam, level, redshift=shift))
    radius = 4.0
    at_r = jl.render(jl.Scene(cam, level, redshift=shift, source_distance=radius))
    # R > D: every escaping ray crosses the sphere once; g^4 scales by (1 - 1/R)^2.
    lit = at_inf > 0.5 * at_inf.max()
    ratio = at_r[lit] / at_inf[lit]
    assert np.allclose(ratio, (1.0 - 1.0 / radius) ** 2, rtol=1e-6)  # float32 pixels
    plan = jl.plan(jl.Scene(cam, level, redshift=shift, source_distance=radius))
    assert any("sqrt(1 - 1/R)" in r for r in plan.reasons)


def test_disk_needs_the_sphere_outside_camera_and_disk():
    cam = _camera(24, 16, k=1)
    disk = jl.Disk(3.0, 12.0, 1.3)
    with pytest.raises(ValueError, match="source_distance=10.0 with a Disk"):
        jl.Scene(cam, SMOOTH, disk=disk, source_distance=10.0)
    # The disk is opaque in front of the sphere: where it covers a pixel (the pixels
    # that differ from the bare sky at infinity), the pixel is the disk's, at any R.
    at_r = jl.render(jl.Scene(cam, SMOOTH, disk=disk, source_distance=25.0))
    at_inf = jl.render(jl.Scene(cam, SMOOTH, disk=disk))
    bare = jl.render(jl.Scene(cam, SMOOTH))
    hit = np.any(at_inf != bare, axis=-1)
    assert hit.sum() > 20 and np.array_equal(at_r[hit], at_inf[hit])
    assert not np.array_equal(at_r[~hit], at_inf[~hit])  # the sky around it moved


def test_plan_refuses_what_has_no_finite_form():
    scene = jl.Scene(_camera(), SMOOTH, source_distance=10.0, method="table")
    with pytest.raises(ValueError, match="method='table' has no form"):
        jl.plan(scene)
    gauss = jl.Scene(_camera(sampling="gauss"), SMOOTH, source_distance=10.0)
    with pytest.raises(ValueError, match='sampling="gauss" with a source_distance needs'):
        jl.plan(gauss)
    reasons = jl.plan(jl.Scene(_camera(), SMOOTH, source_distance=10.0)).reasons
    assert any(r.startswith("source_distance: the sky lies on the sphere") for r in reasons)
    # Area-exact cells read the ray map of (D, R), thin rings included.
    cells = jl.Scene(_camera(24, 16, sampling="gauss"), SMOOTH, source_distance=40.0)
    img = jl.render(cells)
    ref = jl.render(cells.replace(source_distance=None))
    assert np.all(np.isfinite(img)) and not np.allclose(img, ref, rtol=1e-3)


def test_scene_file_key_and_command_line_flag(tmp_path, capsys, monkeypatch):
    from helpers import run

    from jaxlens import cli

    scene = jl.Scene.from_dict({"effects": {"source_distance": 40.0}})
    assert float(scene.source_distance) == 40.0
    assert jl.Scene.from_dict({}).source_distance is None
    for value, shown in ((0.5, "0.5"), (1, "1"), (1e31, "1e+31")):
        with pytest.raises(ValueError, match=re.escape(f"[effects] source_distance = {shown}")):
            jl.Scene.from_dict({"effects": {"source_distance": value}})
    with pytest.raises(ValueError, match="expected a number > 1 \\(units of R_S"):
        jl.Scene.from_dict({"effects": {"source_distance": 0.5}})
    with pytest.raises(SystemExit):
        cli.main(["render", "--scene-keys"])
    keys = capsys.readouterr().out
    assert "source_distance    # a number > 1 (units of R_S" in keys

    def render(s, **kw):  # what the command would render, without rendering it
        render.scene = s
        return np.zeros((s.camera.height, s.camera.width, 3), np.float32)

    monkeypatch.setattr(jl, "render", render)
    out = str(tmp_path / "o.exr")
    assert run(["render", "--size", "12x8", "--source-distance", "40", "-o", out], capsys)[0] == 0
    assert float(render.scene.source_distance) == 40.0
    for value in ("0.5", "nan", "inf"):
        code, _, err = run(["render", "--source-distance", value, "-o", out], capsys)
        assert code == 2 and f"--source-distance {value} is not valid: expected a number > 1" in err

    # The plane behind the hole: its key, listed, its flag, and both refused by value.
    assert float(jl.Scene.from_dict({"effects": {"source_plane": 200.0}}).source_plane) == 200.0
    with pytest.raises(ValueError, match=re.escape("[effects] source_plane = -1")):
        jl.Scene.from_dict({"effects": {"source_plane": -1}})
    assert "source_plane    # a number > 0 (units of R_S" in keys
    assert run(["render", "--size", "12x8", "--source-plane", "200", "-o", out], capsys)[0] == 0
    assert float(render.scene.source_plane) == 200.0 and render.scene.source_distance is None
    code, _, err = run(["render", "--source-plane", "-3.5", "-o", out], capsys)
    assert code == 2 and "--source-plane -3.5 is not valid: expected a number > 0" in err
    # Not both: the scene refuses the pair by name.
    code, _, err = run(["render", "--source-plane", "200", "--source-distance", "40", "-o", out],
                       capsys)  # fmt: skip
    assert code == 2 and "source_plane" in err


def test_plane_crossings_meet_the_far_field_line():
    # Far behind the hole a ray is a straight line at impact parameter b from it, along
    # its asymptote: it meets the plane z = L at rho = -L tan(Phi) - b / cos(Phi) (the
    # through-the-centre projection -L tan(Phi) of PlaneImage.at_distance, plus b /
    # |cos Phi|). At L = 1e5 the rest of the bending beyond L is O(b / L) of the offset.
    d, plane = 20.0, 1e5
    alpha = np.asarray([0.1275, 0.16, 0.2, 0.3, 0.45])  # outside the shadow (0.1270)
    hits = jl.plane_crossings(alpha, d, plane)
    assert np.all(np.asarray(hits.hit))
    phi_inf = np.asarray(jl.trace(alpha, d, method="exact").phi)
    b = np.asarray(jl.impact_parameter(alpha, d))
    phi = np.asarray(hits.phi)
    assert np.allclose(-np.asarray(hits.radius) * np.cos(phi), plane, rtol=1e-12)
    offset = -plane * np.tan(phi) + plane * np.tan(phi_inf)
    assert np.allclose(offset, -b / np.cos(phi_inf), rtol=1e-3)
    # Captured rays and rays whose asymptote heads toward the camera cross no plane.
    none = jl.plane_crossings(np.asarray([0.05, 0.14, 2.5]), d, plane)  # Phi 5.06 at 0.14
    assert not np.any(np.asarray(none.hit)) and np.all(np.asarray(none.radius) == 0)


def test_a_picture_on_a_plane_behind_the_hole():
    cam = jl.Camera(D, math.radians(60.0), 24, 16)
    yy, xx = np.mgrid[0:16, 0:16] / 15.0
    picture = np.stack([xx, yy, 0.5 + 0.0 * xx], axis=-1)  # smooth, so nearness shows
    plane_distance = 200.0
    sky = jl.PlaneImage.at_distance(picture, 300.0, plane_distance)
    scene = jl.Scene(cam, sky, source_plane=plane_distance)
    assert jl.plan(scene).geometry == "plane"
    exact = jl.render(scene)
    sphere = jl.render(jl.Scene(cam, sky, source_distance=plane_distance))
    at_inf = jl.render(jl.Scene(cam, sky))
    lit = exact.sum(-1) > 0
    assert np.all(np.isfinite(exact)) and lit.sum() > 100
    # Read at the ray's crossing of the sphere r = L, the picture is off by about
    # (rho/L)^2 b/2 on the plane; read along the asymptote through the hole's centre,
    # by b/|cos Phi| (PHYSICS: b >= 2.6): an order of magnitude more here.
    near = np.abs(exact - sphere)[lit].mean()
    far = np.abs(exact - at_inf)[lit].mean()
    assert near < 0.2 * far, (near, far)
    with pytest.raises(ValueError, match="source_plane=0.0 is not valid"):
        jl.Scene(cam, sky, source_plane=0.0)
    with pytest.raises(ValueError, match="not both"):
        jl.Scene(cam, sky, source_plane=plane_distance, source_distance=plane_distance)


def test_gradient_with_respect_to_the_radius():
    # R traced (as a fit traces it): the exact crossings, differentiable in R. Forward
    # mode against a central difference of step 1e-4 R, whose error (~h^2 f''' ~ 1e-8 R^2
    # of the pixel sums' scale) is far below the 1e-5 asked.
    scene = jl.Scene(_camera(8, 6, k=1), SMOOTH, source_distance=10.0)

    def total(r):
        return jnp.sum(jl.render_array(eqx.tree_at(lambda s: s.source_distance, scene, r)))

    f = jax.jit(lambda r: jax.jvp(total, (r,), (jnp.ones_like(r),)))
    for radius in (40.0, 10.0):  # beyond the camera, inside its radius
        value, slope = f(jnp.asarray(radius))
        h = 1e-4 * radius
        fd = (f(jnp.asarray(radius + h))[0] - f(jnp.asarray(radius - h))[0]) / (2 * h)
        assert np.isfinite(float(slope)) and abs(float(slope)) > 0
        assert abs(float(slope) - float(fd)) <= 1e-5 * abs(float(slope)), radius
