"""Scene-file tables of the skies: every registered sky type validates its keys with
errors that name the key, the value and what is valid, and builds the sky that the
Python API builds (the same radiance, the same image)."""

import math
import re

import numpy as np
import pytest

import jaxlens as jl

rad = math.radians
CAM = jl.Camera(12.0, rad(100.0), 12, 8, supersample=1)
N = jl.direction_from_angles(
    np.random.default_rng(3).uniform(-math.pi, math.pi, 64),
    np.random.default_rng(4).uniform(-1.5, 1.5, 64),
)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("skies")
    jl.write_image(path / "pano.png", np.random.default_rng(0).random((8, 16, 3)))
    return path


def cases(folder):
    """type -> [(table, the sky built in Python)]: defaults first, then other keys."""
    pano = folder / "pano.png"
    image = jl.to_rgb(jl.read_image(pano))
    return {
        "star": [
            ({}, jl.GaussianStar(rad(1.0), 1.0, lon=0.0, lat=0.0)),
            (
                dict(sigma_deg=20.0, brightness=3.0, lon_deg=10.0, lat_deg=-5.0, color=[1, 0.5, 0]),
                jl.GaussianStar(rad(20.0), 3.0, color=(1.0, 0.5, 0.0), lon=rad(10), lat=rad(-5)),
            ),
        ],
        "stars": [
            ({}, jl.StarField.random(200, seed=0, sigma=rad(0.15), brightness=(0.05, 2.0))),
            (
                dict(count=7, seed=2, sigma_deg=10.0, brightness=[0.5, 3.0, 1.0]),
                jl.StarField.random(7, seed=2, sigma=rad(10.0), brightness=(0.5, 3.0)),
            ),
            (
                dict(lon_deg=[0.0, 10.0], lat_deg=[5.0, -5.0], brightness=[1.0, 0.5]),
                jl.StarField(
                    jl.direction_from_angles(np.radians([0.0, 10.0]), np.radians([5.0, -5.0])),
                    rad(0.15),
                    np.array([1.0, 0.5]),
                ),
            ),
        ],
        "panorama": [
            (dict(path="pano.png"), jl.Panorama.from_file(pano)),
            (
                dict(path="pano.png", brightness=0.5, yaw_deg=90.0, pitch_deg=10.0, roll_deg=5.0),
                jl.Panorama.from_file(
                    pano, brightness=0.5, yaw=rad(90.0), pitch=rad(10.0), roll=rad(5.0)
                ),
            ),
        ],
        "plane": [
            (dict(path="pano.png"), jl.PlaneImage(image, rad(30.0))),
            (
                dict(path="pano.png", width_deg=40.0, brightness=2.0, yaw_deg=3.0),
                jl.PlaneImage(image, rad(40.0), brightness=2.0, yaw=rad(3.0)),
            ),
            (
                dict(path="pano.png", size=10.0, plane_distance=20.0),
                jl.PlaneImage.at_distance(image, 10.0, 20.0),
            ),
        ],
        "checker": [
            ({}, jl.Checker()),
            (
                dict(n_lon=8, n_lat=4, brightness=0.5, roll_deg=20.0),
                jl.Checker(8, 4, brightness=0.5, roll=rad(20.0)),
            ),
        ],
        "default": [
            ({}, jl.DefaultSky()),
            (dict(brightness=2.0, stars=False), jl.DefaultSky(2.0, stars=False)),
        ],
        "uniform": [
            ({}, jl.Uniform(0.0)),
            (dict(level=[0.1, 0.2, 0.3]), jl.Uniform([0.1, 0.2, 0.3])),
        ],
        "blackbody": [
            (
                {},
                jl.BlackbodyStars.random(
                    200, seed=0, sigma=rad(0.2), brightness=(0.2, 2.0), temperature=(2500, 3e4)
                ),
            ),
            (
                dict(count=5, seed=3, sigma_deg=15.0, brightness=[0.5, 1.0], temperature=4000.0),
                jl.BlackbodyStars.random(
                    5, seed=3, sigma=rad(15.0), brightness=(0.5, 1.0), temperature=(4000, 4000)
                ),
            ),
            (
                dict(lon_deg=[0.0, 10.0], lat_deg=[0.0, 5.0], sigma_deg=3.0, brightness=[2, 1],
                     temperature=[3000.0, 9000.0]),
                jl.BlackbodyStars(
                    jl.direction_from_angles(np.radians([0.0, 10.0]), np.radians([0.0, 5.0])),
                    rad(3.0), np.array([2.0, 1.0]), np.array([3000.0, 9000.0]),
                ),
            ),
        ],
    }  # fmt: skip


def test_every_registered_type_has_cases(folder):
    assert set(cases(folder)) == set(jl.scene_table_types("sky"))
    # scene files list the types in this order (their error messages do too)
    assert jl.scene_table_types("sky")[:7] == (
        "star", "stars", "panorama", "plane", "checker", "default", "uniform"
    )  # fmt: skip


@pytest.mark.parametrize("kind", jl.scene_table_types("sky"))
def test_table_builds_the_python_sky(kind, folder):
    for table, want in cases(folder)[kind]:
        got = jl.sky_from_table({"type": kind, **table}, base=folder)
        assert type(got) is type(want)
        # Built by the same calls on the same numbers: equal to the bit.
        np.testing.assert_array_equal(got(N), want(N), err_msg=f"{kind} {table}")
        np.testing.assert_array_equal(jl.render(CAM, got), jl.render(CAM, want))
    # and the first table that departs from the defaults has a visible effect
    if len(cases(folder)[kind]) > 1:
        (_, default), (_, other) = cases(folder)[kind][:2]
        assert not np.array_equal(default(N), other(N))


def _wrong_kind(key: jl.SceneKey):
    """A value of the wrong type for a key: a string for numbers, a number otherwise."""
    return {"bool": 1, "str": 5}.get(key.kind, "x")


@pytest.mark.parametrize(
    "kind,name",
    [(k, n) for k in jl.scene_table_types("sky") for n in jl.scene_table_keys("sky", k)],
)
def test_a_value_of_the_wrong_type_names_key_value_and_valid(kind, name):
    key = jl.scene_table_keys("sky", kind)[name]
    bad = _wrong_kind(key)
    shown = f'"{bad}"' if isinstance(bad, str) else repr(bad)
    message = f"sky ({kind}) {name} = {shown} is not valid: expected {key.text}"
    with pytest.raises(ValueError, match=re.escape(message)):
        # (image types need a path, else the first error is the missing path)
        path = {"path": "p.png"} if "path" in jl.scene_table_keys("sky", kind) else {}
        jl.sky_from_table({"type": kind, **path, name: bad})


@pytest.mark.parametrize(
    "table,message",
    [
        (
            dict(type="star", sigma_deg=0.0),
            "sigma_deg = 0.0 is not valid: expected a number in (0, 180) (degrees)",
        ),
        (
            dict(type="star", sigma_deg=180),
            "sigma_deg = 180 is not valid: expected a number in (0, 180)",
        ),
        (
            dict(type="star", color=[1, 2]),
            "color = [1, 2] is not valid: expected a number or a list of 3",
        ),
        (
            dict(type="star", brightness=math.inf),
            "brightness = inf is not valid: expected a finite number",
        ),
        (
            dict(type="stars", count=0),
            "count = 0 is not valid: expected a whole number from 1 to 100000",
        ),
        (dict(type="stars", count=2.0), "count = 2.0 is not valid: expected a whole number"),
        (
            dict(type="stars", lon_deg=[]),
            "lon_deg = [] is not valid: expected a list of finite numbers",
        ),
        (dict(type="stars", lon_deg=[1.0]), "(stars): lon_deg and lat_deg go together"),
        (dict(type="stars", lon_deg=[1, 2], lat_deg=[1]), "different lengths (2 and 1)"),
        (
            dict(type="stars", lon_deg=[1], lat_deg=[1], brightness=[1, 2]),
            "brightness has 2 values for 1 stars",
        ),
        (dict(type="panorama"), 'sky (panorama) needs a path = "IMAGE"'),
        (
            dict(type="panorama", path=""),
            'path = "" is not valid: expected the path of an image file',
        ),
        (
            dict(type="panorama", path="p.png", brightness=-1.0),
            "brightness = -1.0 is not valid: expected a finite number >= 0",
        ),
        (
            dict(type="panorama", path="p.png", yaw_deg=math.nan),
            "yaw_deg = nan is not valid: expected a finite number (degrees)",
        ),
        (dict(type="plane"), 'sky (plane) needs a path = "IMAGE"'),
        (
            dict(type="plane", path="p.png", width_deg=180.0),
            "width_deg = 180.0 is not valid: expected a number in (0, 180)",
        ),
        (
            dict(type="plane", path="p.png", size=0.0),
            "size = 0.0 is not valid: expected a number > 0 (units of R_S)",
        ),
        (
            dict(type="plane", path="p.png", plane_distance=-1.0),
            "plane_distance = -1.0 is not valid: expected a number > 0",
        ),
        (
            dict(type="plane", path="p.png", size=3.0),
            "(plane): size and plane_distance go together",
        ),
        (
            dict(type="plane", path="p.png", width_deg=3.0, size=3.0, plane_distance=3.0),
            "give width_deg or size and plane_distance, not both",
        ),
        (
            dict(type="checker", n_lon=0),
            "n_lon = 0 is not valid: expected a whole number from 1 to 100000",
        ),
        (
            dict(type="checker", n_lat=100001),
            "n_lat = 100001 is not valid: expected a whole number from 1 to 100000",
        ),
        (
            dict(type="stars", seed=-1),
            "sky (stars) seed = -1 is not valid: expected a whole number >= 0",
        ),
        (
            dict(type="stars", lon_deg=[1.0] * 99 + [math.inf], lat_deg=[0.0] * 100),
            "sky (stars) lon_deg[99] = inf is not valid: expected a list of finite numbers",
        ),
        (dict(type="default", stars="yes"), 'stars = "yes" is not valid: expected true or false'),
        (
            dict(type="uniform", level=[1, 2, 3, 4]),
            "level = [1, 2, 3, 4] is not valid: expected a number or a list of 3",
        ),
        (
            dict(type="blackbody", temperature=-5.0),
            "temperature = -5.0 is not valid: expected a number > 0 or a list of them (K)",
        ),
        (dict(type="blackbody", temperature=[3000, 0]), "temperature = [3000.0, 0.0] is not valid"),
        (
            dict(type="blackbody", brightness=0.0),
            "brightness = 0.0 is not valid: expected a number or a list of numbers (peak lum",
        ),
        (
            dict(type="blackbody", lon_deg=[1], lat_deg=[1], temperature=[1e3, 2e3]),
            "temperature has 2 values for 1 stars",
        ),
        (
            dict(type="blackbody", sigma_deg=-1.0),
            "sigma_deg = -1.0 is not valid: expected a number in (0, 180)",
        ),
        (
            dict(type="star", sigma=1.0),
            "sky (star) has an unknown key 'sigma'; valid keys: sigma_deg, brightness,",
        ),
        (
            dict(type="nebula"),
            'type = "nebula" is not valid: expected one of star, stars, panorama, plane, checker, '
            "default, uniform, blackbody",
        ),
        (dict(sigma_deg=1.0), "sky type = None is not valid: expected one of star,"),
    ],
)
def test_bad_values_name_key_value_and_valid(table, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        jl.sky_from_table(table)


def test_a_list_of_tables_is_their_sum(folder):
    sky = jl.sky_from_table(
        [{"type": "uniform", "level": 0.25}, {"type": "panorama", "path": "pano.png"}], base=folder
    )
    assert isinstance(sky, jl.SkySum) and len(sky.parts) == 2
    want = 0.25 + jl.Panorama.from_file(folder / "pano.png")(N)
    np.testing.assert_allclose(sky(N), want, rtol=1e-15)  # one addition, rounded once
    with pytest.raises(ValueError, match=re.escape("sky #2 (star) sigma_deg = -1.0")):
        jl.sky_from_table([{"type": "uniform"}, {"type": "star", "sigma_deg": -1.0}])
    with pytest.raises(ValueError, match="non-empty list"):
        jl.sky_from_table([])


def test_image_paths_are_relative_to_base(folder, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a folder without the image
    sky = jl.sky_from_table({"type": "panorama", "path": "pano.png"}, base=folder)
    assert sky.image.shape == (8, 16, 3)
    with pytest.raises(ValueError, match="does not exist"):
        jl.sky_from_table({"type": "panorama", "path": "pano.png"})
