"""How the pixels sampled the light: a render with one ray a pixel samples each at its
centre, a camera averages over its area. A fit that takes point samples for area
averages sees a sharper ring and puts the camera elsewhere (a default render of D = 20,
fitted as area averages: D 19.75, 26 standard errors off, and valid); `pixels` says
which, and the files jaxlens writes record it."""

import math

import numpy as np
import pytest
from helpers import run

import jaxlens as jl
from jaxlens import _io
from jaxlens._fit.observation import observe

STAR = math.radians(1.0)


def _render(w=200, h=150, supersample=1):
    cam = jl.Camera(20.0, math.radians(60.0), w, h, supersample=supersample, dtype=np.float64)
    scene = jl.Scene(cam, jl.GaussianStar(STAR) + jl.Uniform(0.05))
    return np.asarray(jl.render(scene), np.float64).mean(-1)


@pytest.mark.parametrize("ext", ["png", "exr"])
def test_render_records_how_its_pixels_were_sampled(tmp_path, capsys, ext):
    for k, how in ((1, "point"), (2, "area")):
        out = tmp_path / f"k{k}.{ext}"
        args = ["--sky", "star", "--size", "48x32", "--supersample", str(k), "-o", str(out)]
        code, _, err = run(["render", *args], capsys)
        assert code == 0, err
        obs = observe(out)
        assert obs.pixels == how and "records" in obs.pixels_reason
        # What the caller says wins over the record.
        other = "area" if how == "point" else "point"
        assert observe(out, pixels=other).pixels == other


def test_pixels_default_to_area_and_bad_values_are_refused(tmp_path):
    img = _render(64, 48)
    assert observe(img).pixels == "area"
    # A file jaxlens did not write says nothing: area.
    path = tmp_path / "plain.exr"
    _io.write_image(path, img)
    assert observe(path).pixels == "area"
    with pytest.raises(ValueError, match="pixels='sampled'|'auto', 'area', 'point'"):
        observe(img, pixels="sampled")
    # Point samples under a PSF image, or a Gaussian PSF narrower than a pixel's box,
    # cannot be modelled by narrowing the PSF.
    with pytest.raises(ValueError, match="PSF image"):
        observe(img, pixels="point", psf=np.ones((3, 3)))
    with pytest.raises(ValueError, match="narrower than a pixel"):
        observe(img, pixels="point", psf=0.2)
    with pytest.raises(ValueError, match="narrower than a pixel"):
        observe(observe(img, pixels="point"), psf=0.2)


def test_a_default_render_is_fitted_as_point_samples_from_its_file(tmp_path):
    # The library's own render at its default sampling, with pixel noise, written
    # by the library (EXR): the fit reads its record and models point samples.
    rng = np.random.default_rng(11)
    img = _render() + 0.01 * rng.standard_normal((150, 200))
    path = tmp_path / "render.exr"
    _io.write_image(path, img, sampling="point")
    fit = jl.fit_ring(path, star_sigma=STAR)
    assert fit.pixels == "point" and "records" in fit.pixels_reason
    assert "pixels" in fit.to_dict() and "point" in fit.summary()
    d, e = fit.values["distance"], fit.errors["distance"]
    assert fit.valid, fit.message
    assert abs(d - 20.0) < 0.01 * 20.0 and abs(d - 20.0) < 3.0 * e
    assert math.degrees(fit.values["fov"]) == pytest.approx(60.0, rel=0.01)
