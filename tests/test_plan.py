"""The plan: which stages and paths a scene's program contains, and why."""

import math
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl

CAM = jl.Camera(25.0, math.radians(60), 32, 24)
SKY = jl.Uniform(0.3)


def _ops(text, name):
    return len(re.findall(rf"\bstablehlo\.{name}\b", text))


def lowered_text(scene):
    """The lowered program of the traceable render of `scene`, with its debug
    locations (the `jaxlens.<stage>` scopes)."""
    return eqx.filter_jit(jl.render_array).lower(scene).lowered.as_text(debug_info=True)


def test_plan_follows_the_scene_structure():
    p = jl.plan(jl.Scene(CAM, SKY))
    assert p.stages == ("samples", "table", "sky") and p.symmetric and not p.disk
    p = jl.plan(jl.Scene(CAM, SKY, motion=jl.RadialInfall()))
    assert p.aberration == "radial" and p.geometry == "table" and p.symmetric
    p = jl.plan(jl.Scene(CAM, SKY, motion=jl.CircularOrbit(0.3), redshift=jl.Redshift()))
    assert p.aberration == "boost" and p.redshift == "spectral" and not p.symmetric
    assert p.stages == ("samples", "aberration", "redshift", "table", "sky")
    assert any("Doppler" in r for r in p.reasons)
    # a far camera: the disk covers a small part of the view; only those rays are traced
    far = jl.Camera(200.0, math.radians(30), 64, 48)
    p = jl.plan(jl.Scene(far, SKY, disk=jl.Disk(3.0, 10.0, 1.2)))
    samples = 64 * 48
    assert p.disk and 0 < p.disk_reach <= p.disk_rays < samples / 10
    # the rays of impact parameter b < r^1.5 / sqrt(r - 1) come within r = r_out
    r, d = 10.0, 200.0
    bound = math.asin(r * math.sqrt(r / (r - 1.0)) * math.sqrt(1.0 - 1.0 / d) / d)
    a, _, _ = far.rays()
    assert p.disk_reach == int(np.sum(np.asarray(a) < bound))  # every reachable ray, no more
    assert "traced through the disk plane" in str(p)


def test_plan_blocks_effect_scenes_like_bare_ones():
    # A scene with effects is blocked like a bare one: same rows a block for the same
    # sample budget, many blocks for a small budget, and the blocks give the image.
    orbit = jl.Scene(CAM, SKY, motion=jl.CircularOrbit(0.2), redshift=jl.Redshift())
    p = jl.plan(orbit, chunk_samples=32 * 5)
    assert p.rows == 5 and p.blocks == 5 and not p.pair  # 24 rows: 5 blocks of 5
    np.testing.assert_allclose(
        jl.render(orbit, chunk_samples=32 * 5), jl.render(orbit), rtol=0, atol=1e-7
    )
    assert "5 compiled block(s)" in str(p)


def test_stage_not_named_is_not_compiled():
    orbit, red = jl.CircularOrbit(0.0), jl.Redshift("bolometric")
    plain = lowered_text(jl.Scene(CAM, SKY, motion=orbit, redshift=red))
    disk = lowered_text(jl.Scene(CAM, SKY, motion=orbit, redshift=red, disk=jl.Disk()))
    assert "jaxlens.disk" not in plain and "jaxlens.disk" in disk
    assert "jaxlens.aberration" in plain and "jaxlens.redshift" in plain
    # the disk's RK4 scans are the only loops of these programs (a Uniform sky)
    assert _ops(plain, "while") == 0 and _ops(disk, "while") >= 2
    static = lowered_text(jl.Scene(CAM, SKY, redshift=red))
    assert "jaxlens.aberration" not in static and "jaxlens.disk" not in static
    assert _ops(static, "divide") < _ops(plain, "divide")
    # no effects at all: none of their stages
    bare = lowered_text(jl.Scene(CAM, SKY))
    for stage in ("aberration", "redshift", "disk"):
        assert f"jaxlens.{stage}" not in bare
    assert "jaxlens.table" in bare and _ops(bare, "divide") < _ops(static, "divide")


FAR = jl.Camera(1e4, math.radians(2.0), 24, 16, yaw=math.radians(5.0))
STAR = jl.GaussianStar(0.002, 1.0, lon=math.radians(5.5), lat=0.002)


@pytest.mark.parametrize("accuracy", [1e-6, 1e-9, 1e-12])
def test_weak_field_only_below_its_bound(accuracy):
    scene = jl.Scene(FAR, STAR, redshift=jl.Redshift("bolometric"), accuracy=accuracy)
    p = jl.plan(scene)
    # b >= D sin(4 deg) ~ 700: bound ~ pi c_4 (1.5 / 700)^4 ~ 2e-11
    assert p.weak_bound is not None and 1e-12 < p.weak_bound < 1e-9
    assert (p.geometry == "weak_field") == (p.weak_bound < accuracy)
    # the bound holds on the view's own rays
    a, _, _ = FAR.rays()
    phi, bound = jl.weak_field_escape_angle(a, FAR.distance)
    exact = jl.trace(a, FAR.distance, method=jl.Exact(iterations=12)).phi
    assert float(jnp.max(jnp.abs(phi - exact))) <= p.weak_bound
    # and a view with the hole in it never takes the series
    near = jl.plan(jl.Scene(CAM, STAR, accuracy=accuracy))
    assert near.geometry == "table" and not math.isfinite(near.weak_bound)


def test_large_far_view_takes_the_table():
    # The series meets the accuracy, but the view is past the measured break-even size:
    # the table's build is amortised and its look-up is cheaper a ray.
    # The view's bound is not even computed (no host work for a choice already made).
    big = jl.Camera(1e4, math.radians(2.0), 640, 480, yaw=math.radians(5.0))
    p = jl.plan(jl.Scene(big, STAR))
    assert p.weak_bound is None
    assert p.geometry == "table" and any("amortised" in r for r in p.reasons)


def test_weak_field_image_matches_the_table():
    weak = jl.Scene(FAR, STAR, redshift=jl.Redshift("bolometric"))
    assert jl.plan(weak).geometry == "weak_field"
    table = weak.replace(method="table")
    exact = weak.replace(method="trace")
    assert jl.plan(table).geometry == "table" and jl.plan(exact).geometry == "trace"
    a, b, c = (jl.render(s) for s in (weak, table, exact))
    assert a.max() > 0.5  # the star is in view
    # sky directions agree to ~1e-8 rad; the star's profile varies by 1/sigma per rad
    np.testing.assert_allclose(a, c, atol=1e-5)
    np.testing.assert_allclose(b, c, atol=1e-5)


def test_plan_under_tracing_is_safe():
    seen = {}

    def f(d):
        cam = jl.Camera(d, math.radians(60), 16, 16)
        seen["plan"] = jl.plan(jl.Scene(cam, SKY, disk=jl.Disk()))
        return d

    jax.make_jaxpr(f)(30.0)
    p = seen["plan"]
    assert p.geometry == "table" and p.disk and p.disk_rays is None
    assert any("traced" in r for r in p.reasons)


def test_gradient_through_a_moving_scene():
    # d image / d (sky level) through aberration, Doppler factor and table: the image is
    # linear in the level, so the gradient is image / level.
    rm = eqx.filter_jit(jl.RayMap.build)(CAM.distance, accuracy=1e-8)
    motion, red = jl.CircularOrbit(0.5), jl.Redshift("bolometric")

    def img(level):
        s = jl.Scene(CAM, jl.Uniform(level), motion=motion, redshift=red)
        return jl.render_array(s, ray_map=rm)

    g = jax.jit(jax.grad(lambda x: jnp.sum(img(x))))(0.3)
    assert float(g) == pytest.approx(float(jnp.sum(img(0.3))) / 0.3, rel=1e-10)


def test_effects_from_a_scene_file(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text(
        """
accuracy = 1e-8
[camera]
distance = 40.0
width = 16
height = 12
[[sky]]
type = "uniform"
level = 0.5
[effects.motion]
type = "orbit"
angle_deg = 90.0
[effects.redshift]
mode = "bolometric"
[effects.disk]
r_out = 15.0
inclination_deg = 80.0
crossings = 2
"""
    )
    scene = jl.load_scene(path)
    assert isinstance(scene.motion, jl.CircularOrbit)
    assert float(scene.motion.angle) == pytest.approx(math.pi / 2)
    assert scene.redshift.mode == "bolometric" and scene.accuracy == 1e-8
    assert float(scene.disk.inclination) == pytest.approx(math.radians(80))
    assert scene.disk.crossings == 2 and float(scene.disk.r_in) == 3.0
    img = jl.render(scene)
    assert img.shape == (12, 16, 3) and np.all(np.isfinite(img))
    for bad, msg in [
        ({"motion": {"type": "spin"}}, "expected one of orbit, infall"),
        ({"redshift": {"mode": "x"}}, "spectral | bolometric"),
        ({"disk": {"r_in": "3"}}, "r_in"),
        ({"disk": {"radius": 3}}, "unknown key 'radius'"),
        ({"disk": {"inclination_deg": 200.0}}, "inclination_deg"),
        ({"colour": 1}, "unknown key 'colour'"),
        ({"method": "fast"}, "method"),
    ]:
        with pytest.raises(ValueError, match=re.escape(msg)):
            jl.Scene.from_dict({"effects": bad})
    with pytest.raises(ValueError, match="method"):
        jl.Scene(CAM, SKY, method="fast")


def test_disk_scenes_take_smaller_blocks_and_render_array_wants_one():
    # A traced disk ray holds several times a plain sample's memory: the plan gives
    # disk scenes blocks of a quarter of chunk_samples (and says so), and the blocks
    # still make the image.
    cam = jl.Camera(30.0, math.radians(40), 32, 24)
    scene = jl.Scene(cam, SKY, disk=jl.Disk(3.0, 12.0, 1.2))
    p = jl.plan(scene, chunk_samples=32 * 8)
    assert p.samples == 32 * 2 and p.blocks == 12
    assert any("chunk_samples / 4" in r for r in p.reasons)
    np.testing.assert_allclose(
        jl.render(scene, chunk_samples=32 * 8), jl.render(scene), rtol=0, atol=1e-7
    )
    # render_array gathers disk rays over the whole image: a plan of many blocks would
    # drop rays, so it is refused
    with pytest.raises(ValueError, match="disk rays a block"):
        jl.render_array(scene, plan=p)
