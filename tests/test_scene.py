"""Scene files: the TOML schema, its validation messages, every sky layer."""

import math

import numpy as np
import pytest

import jaxlens as jl
from jaxlens import (
    Camera,
    Checker,
    DefaultSky,
    GaussianStar,
    Panorama,
    PlaneImage,
    Scene,
    SkySum,
    StarField,
    Uniform,
    load_scene,
    write_image,
)

FULL = """
accuracy = 1e-7

[camera]
distance = 12.5
fov_deg = 45.0
width = 32
height = 18
supersample = 3
yaw_deg = 5.0
pitch_deg = -2.0
roll_deg = 1.0
azimuth_deg = 30.0
elevation_deg = 10.0

[output]
exposure = 1.5

[animation]
path = "zoom"
frames = 5

[[sky]]
type = "star"
sigma_deg = 0.5
brightness = 2.0
lon_deg = 10.0
lat_deg = -5.0
color = [1.0, 0.8, 0.6]

[[sky]]
type = "panorama"
path = "pano.png"
yaw_deg = 90.0

[[sky]]
type = "plane"
path = "pano.png"
size = 10.0
plane_distance = 20.0

[[sky]]
type = "stars"
lon_deg = [0.0, 10.0]
lat_deg = [5.0, -5.0]
brightness = [1.0, 0.5]

[[sky]]
type = "checker"
n_lon = 8

[[sky]]
type = "default"
stars = false

[[sky]]
type = "uniform"
level = 0.01
"""


def test_full_scene_file(tmp_path):
    write_image(tmp_path / "pano.png", np.random.default_rng(0).random((8, 16, 3)))
    (tmp_path / "scene.toml").write_text(FULL)
    scene = load_scene(tmp_path / "scene.toml")
    cam = scene.camera
    assert isinstance(cam, Camera) and (cam.width, cam.height, cam.supersample) == (32, 18, 3)
    assert float(cam.distance) == 12.5
    assert float(cam.fov) == pytest.approx(math.radians(45.0), rel=1e-15)
    assert float(cam.azimuth) == pytest.approx(math.radians(30.0), rel=1e-15)
    assert scene.accuracy == 1e-7 and scene.exposure == 1.5
    kinds = [type(p) for p in scene.sky.parts]
    assert kinds == [GaussianStar, Panorama, PlaneImage, StarField, Checker, DefaultSky, Uniform]
    star = scene.sky.parts[0]
    np.testing.assert_allclose(star.color, [1.0, 0.8, 0.6])
    assert float(star.sigma) == pytest.approx(math.radians(0.5), rel=1e-15)
    # Paths are relative to the scene file, not to the working directory.
    assert scene.sky.parts[1].image.shape == (8, 16, 3)
    assert float(scene.sky.parts[2].width) == pytest.approx(2 * math.atan(0.25), rel=1e-15)
    assert float(scene.sky.parts[1].yaw) == pytest.approx(math.pi / 2, rel=1e-15)


def test_defaults_and_render():
    scene = Scene.from_dict({"camera": {"width": 8, "height": 6, "supersample": 1}})
    assert isinstance(scene.sky, SkySum)  # the default: procedural sky + a star
    assert float(scene.camera.distance) == 20.0
    img = jl.render(scene)
    assert img.shape == (6, 8, 3) and np.all(np.isfinite(img))
    default = Scene.from_dict({})
    assert (default.camera.width, default.camera.height) == (960, 540)
    assert default.motion is None and default.redshift is None and default.disk is None


@pytest.mark.parametrize(
    "data,message",
    [
        ({"camra": {}}, "unknown key 'camra'"),
        ({"camera": {"fov": 60}}, r"\[camera\] has an unknown key 'fov'; valid keys: distance,"),
        ({"camera": {"distance": 1.0}}, r"\[camera\] distance = 1.0 is not valid: expected a fin"),
        ({"camera": {"distance": "far"}}, r'distance = "far" is not valid'),
        ({"camera": {"fov_deg": 180}}, r"fov_deg = 180 is not valid: expected a number in \(0, "),
        ({"camera": {"width": 0}}, "width = 0 is not valid"),
        ({"camera": {"width": 10.5}}, "width = 10.5 is not valid: expected a whole number"),
        ({"camera": {"height": True}}, "height = True is not valid"),
        ({"camera": 5}, r"\[camera\] must be a table"),
        ({"accuracy": -1.0}, "accuracy = -1.0 is not valid"),
        ({"sky": [{"type": "nebula"}]}, r'type = "nebula" is not valid: expected one of star,'),
        ({"sky": [{"type": "star", "sigma": 1}]}, r"\(star\) has an unknown key 'sigma'"),
        ({"sky": [{"type": "star", "color": [1, 2]}]}, "color = \\[1, 2\\] is not valid"),
        ({"sky": [{"type": "panorama"}]}, "needs a path"),
        ({"sky": [{"type": "plane", "path": "x.png", "size": 3.0}]}, "go together"),
        ({"sky": [{"type": "stars", "lon_deg": [1, 2], "lat_deg": [1]}]}, "different lengths"),
        ({"sky": []}, "sky must be a list"),
        ({"animation": {"path": "spiral"}}, r'path = "spiral" is not valid: expected approach'),
    ],
)  # fmt: skip
def test_validation_names_key_value_and_valid_range(data, message):
    with pytest.raises(ValueError, match=message):
        Scene.from_dict(data, source="s.toml")


def test_file_errors(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        load_scene(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera\ndistance = ")
    with pytest.raises(ValueError, match="is not valid TOML"):
        load_scene(bad)
    img = tmp_path / "missing_image.toml"
    img.write_text('[[sky]]\ntype = "panorama"\npath = "nowhere.exr"\n')
    with pytest.raises(ValueError, match="nowhere.exr' does not exist"):
        load_scene(img)


def test_scene_is_a_pytree():
    import equinox as eqx
    import jax

    scene = Scene.from_dict({"camera": {"width": 4, "height": 4}, "sky": [{"type": "star"}]})
    leaves = jax.tree.leaves(eqx.filter(scene, eqx.is_array))
    assert len(leaves) > 5  # camera and star arrays: differentiable fields
