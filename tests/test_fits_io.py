"""Reading FITS images: the vertical flip, the pixel scale of every WCS form, the field of
view against astropy's own projections, bad pixels, scaled integers, cubes, HDU choice,
header keywords and the errors.

Every file is written with astropy in `tmp_path`.
"""

import builtins
import gzip
import math

import numpy as np
import pytest

fits = pytest.importorskip("astropy.io.fits")
from astropy.wcs import WCS  # noqa: E402

from jaxlens import FitsImage, MissingExtraError, read_fits  # noqa: E402

ARCSEC = math.pi / (180.0 * 3600.0)


def _tan_header(w, h, scale_deg, *, form="cdelt", rot_deg=0.0, proj="TAN", crval=(150.0, 30.0)):
    """A celestial WCS for a `w` x `h` image: reference pixel at the image centre, RA
    increasing to the left (CDELT1 < 0, the usual orientation), north up, rotated by
    `rot_deg`, written as CDELT, PC + CDELT or CD."""
    hdr = fits.Header()
    hdr["CTYPE1"], hdr["CTYPE2"] = f"RA---{proj}", f"DEC--{proj}"
    hdr["CRPIX1"], hdr["CRPIX2"] = (w + 1) / 2, (h + 1) / 2
    hdr["CRVAL1"], hdr["CRVAL2"] = crval
    c, s = math.cos(math.radians(rot_deg)), math.sin(math.radians(rot_deg))
    pc = np.array([[c, -s], [s, c]])
    if form == "cdelt":
        assert rot_deg == 0.0
        hdr["CDELT1"], hdr["CDELT2"] = -scale_deg, scale_deg
    elif form == "pc":
        hdr["CDELT1"], hdr["CDELT2"] = -scale_deg, scale_deg
        for i in (1, 2):
            for j in (1, 2):
                hdr[f"PC{i}_{j}"] = pc[i - 1, j - 1]
    elif form == "cd":
        cd = pc @ np.diag([-scale_deg, scale_deg])
        for i in (1, 2):
            for j in (1, 2):
                hdr[f"CD{i}_{j}"] = cd[i - 1, j - 1]
    else:
        raise AssertionError(form)
    return hdr


def _write(path, data, header=None, **keys):
    hdu = fits.PrimaryHDU(data, header=header)
    for k, v in keys.items():
        hdu.header[k] = v
    hdu.writeto(path)
    return path


# --- orientation --------------------------------------------------------------------


def test_rows_are_flipped_so_row_zero_is_the_top(tmp_path):
    # An asymmetric image: FITS row 1 (the first stored row, data[0]) is the bottom of
    # the picture and becomes jaxlens's last row; columns keep their order. The pixel
    # correspondence of the module docstring, (i, j) -> FITS (i + 1, H - j), exactly.
    h, w = 5, 7
    raw = np.arange(h * w, dtype=np.float32).reshape(h, w) ** 2
    img = read_fits(_write(tmp_path / "a.fits", raw, _tan_header(w, h, 1e-4)))
    assert isinstance(img, FitsImage) and img.data.dtype == np.float64
    np.testing.assert_array_equal(img.data, raw[::-1])
    for j in range(h):
        for i in range(w):
            p1, p2 = i + 1, h - j
            assert img.data[j, i] == raw[p2 - 1, p1 - 1]
    # and north (the WCS's +Dec, CDELT2 > 0) is up in jaxlens's image: row 0 is the
    # northernmost row, as jaxlens's y = H/2 - (j + 0.5) increases upwards.
    wcs = WCS(img.header)
    dec = [float(wcs.all_pix2world(4.0, h - j, 1)[1]) for j in range(h)]  # FITS p2 = H - j
    assert all(a > b for a, b in zip(dec, dec[1:]))


# --- pixel scale and field of view --------------------------------------------------


@pytest.mark.parametrize(
    ("form", "rot"), [("cdelt", 0.0), ("pc", 0.0), ("pc", 35.0), ("cd", 0.0), ("cd", -120.0)]
)
def test_pixel_scale_of_every_wcs_form(tmp_path, form, rot):
    # 0.2 arcsec pixels however the WCS writes them (a rotation does not change a
    # pixel's size): rtol 1e-12 (the rotation matrix's rounding, a few eps).
    w, h, s = 64, 48, 0.2 / 3600.0
    hdr = _tan_header(w, h, s, form=form, rot_deg=rot)
    img = read_fits(_write(tmp_path / "w.fits", np.ones((h, w)), hdr))
    np.testing.assert_allclose(img.pixel_scale, (0.2 * ARCSEC, 0.2 * ARCSEC), rtol=1e-12)
    assert img.projection == "TAN"
    assert img.fov == pytest.approx(2.0 * math.atan(0.5 * w * 0.2 * ARCSEC), rel=1e-12, abs=0)


def test_pixel_scale_in_arcseconds(tmp_path):
    # CUNIT in arcsec: wcslib converts celestial axes to degrees; the scale is the same.
    w, h = 32, 32
    hdr = _tan_header(w, h, 0.5)  # numbers in the unit below
    hdr["CUNIT1"] = hdr["CUNIT2"] = "arcsec"
    img = read_fits(_write(tmp_path / "u.fits", np.ones((h, w)), hdr))
    np.testing.assert_allclose(img.pixel_scale, (0.5 * ARCSEC, 0.5 * ARCSEC), rtol=1e-12)


def test_fov_is_astropys_tan_projection_of_the_edges(tmp_path):
    # A 10-degree field, where FOV = 2 atan(W s / 2) and the linear W s differ by
    # (FOV/2)^2 / 3 ~ 2.5e-3: astropy's TAN projection puts the left and right edges of
    # the centre row exactly FOV apart (rtol 1e-12: the formula is exact, astropy's
    # separation and projection are good to ~1e-15 rad), and every pixel at the angle
    # from the optical axis that jaxlens's pinhole camera gives it (PHYSICS.md:
    # f = (W/2) / tan(FOV/2), alpha = atan(hypot(x, y) / f)), through the flip.
    from astropy.coordinates import SkyCoord

    w, h, s = 201, 151, 0.05
    hdr = _tan_header(w, h, s, form="pc", rot_deg=20.0, crval=(40.0, -60.0))
    img = read_fits(_write(tmp_path / "f.fits", np.zeros((h, w), np.float32), hdr))
    wcs = WCS(img.header)
    c = (h + 1) / 2
    left, right = wcs.all_pix2world([[0.5, c], [w + 0.5, c]], 1)
    sep = SkyCoord(*left, unit="deg").separation(SkyCoord(*right, unit="deg")).rad
    assert sep == pytest.approx(img.fov, rel=1e-12, abs=0)
    assert abs(img.fov / (w * math.radians(s)) - 1) > 2e-3  # the test can tell them apart
    f = (w / 2) / math.tan(img.fov / 2)
    axis = SkyCoord(40.0, -60.0, unit="deg")  # CRVAL, the tangent point at the centre
    rng = np.random.default_rng(0)
    for i, j in zip(rng.integers(0, w, 20), rng.integers(0, h, 20)):
        x, y = i + 0.5 - w / 2, h / 2 - (j + 0.5)
        alpha = math.atan(math.hypot(x, y) / f)
        ra, dec = wcs.all_pix2world(i + 1, h - j, 1)  # FITS (p1, p2) of jaxlens (i, j)
        assert SkyCoord(ra, dec, unit="deg").separation(axis).rad == pytest.approx(
            alpha, rel=1e-11, abs=1e-15
        )


@pytest.mark.parametrize(("proj", "order"), [("SIN", 1 / 2), ("ARC", 1 / 3)])
def test_other_projections_refused_or_allowed(tmp_path, proj, order):
    # Refused by default; allowed, the FOV is the pinhole's with the same central scale.
    # The docstring's claim, checked on a 10-degree field: the projection's own edge-
    # to-edge angle differs from it by the fraction (FOV/2)^2 x 1/2 (SIN) or 1/3 (ARC),
    # to 2 % (the next order, (FOV/2)^2 ~ 8e-3 of it).
    from astropy.coordinates import SkyCoord

    w, h, s = 201, 101, 0.05
    path = _write(tmp_path / "p.fits", np.ones((h, w)), _tan_header(w, h, s, proj=proj))
    with pytest.raises(ValueError, match=rf"'{proj}' projection.*allow_projection=True"):
        read_fits(path)
    img = read_fits(path, allow_projection=True)
    assert img.projection == proj
    assert img.fov == pytest.approx(2.0 * math.atan(0.5 * w * math.radians(s)), rel=1e-12, abs=0)
    wcs = WCS(img.header)
    c = (h + 1) / 2
    left, right = wcs.all_pix2world([[0.5, c], [w + 0.5, c]], 1)
    sep = SkyCoord(*left, unit="deg").separation(SkyCoord(*right, unit="deg")).rad
    assert (sep / img.fov - 1) == pytest.approx(order * (img.fov / 2) ** 2, rel=0.02, abs=0)


def test_non_square_and_skewed_pixels(tmp_path):
    w, h, s = 40, 30, 1e-4
    hdr = _tan_header(w, h, s)
    hdr["CDELT2"] = 1.01 * s  # 1 % taller
    path = _write(tmp_path / "n.fits", np.ones((h, w)), hdr)
    with pytest.raises(ValueError, match=r"not square: .*ratio 0\.990099.*allow_nonsquare=True"):
        read_fits(path)
    img = read_fits(path, allow_nonsquare=True)
    np.testing.assert_allclose(
        img.pixel_scale, (math.radians(s), math.radians(1.01 * s)), rtol=1e-12
    )
    assert img.fov == pytest.approx(2.0 * math.atan(0.5 * w * math.radians(s)), rel=1e-12, abs=0)
    # skewed: pixel axes at 91 degrees (89 before the flip of RA), same lengths
    hdr = _tan_header(w, h, s, form="cd")
    hdr["CD1_2"] = s * math.sin(math.radians(1.0))
    hdr["CD2_2"] = s * math.cos(math.radians(1.0))
    with pytest.raises(ValueError, match=r"not square: .*axes at 91\.0000 deg"):
        read_fits(_write(tmp_path / "k.fits", np.ones((h, w)), hdr))
    # within the tolerance (|ratio - 1| = 5e-4 < 1e-3): accepted
    hdr = _tan_header(w, h, s)
    hdr["CDELT2"] = 1.0005 * s
    assert read_fits(_write(tmp_path / "ok.fits", np.ones((h, w)), hdr)).fov is not None


def test_no_celestial_wcs_is_not_an_error(tmp_path):
    img = read_fits(_write(tmp_path / "plain.fits", np.ones((6, 8))))
    assert img.pixel_scale is None and img.fov is None and img.projection is None
    lin = fits.Header({"CTYPE1": "LINEAR", "CTYPE2": "LINEAR", "CDELT1": 2.0, "CDELT2": 2.0})
    img = read_fits(_write(tmp_path / "lin.fits", np.ones((6, 8)), lin))
    assert img.pixel_scale is None and img.fov is None


# --- pixel values -------------------------------------------------------------------


def test_nan_and_infinite_pixels_are_masked(tmp_path):
    raw = np.arange(20, dtype=np.float32).reshape(4, 5)
    raw[0, 1], raw[2, 3], raw[3, 4] = np.nan, np.inf, -np.inf
    img = read_fits(_write(tmp_path / "nan.fits", raw))
    bad = ~np.isfinite(raw[::-1])
    np.testing.assert_array_equal(img.mask, bad)
    assert np.all(np.isnan(img.data[bad]))
    np.testing.assert_array_equal(img.data[~bad], raw[::-1][~bad])


def test_blank_pixels_of_integer_images(tmp_path):
    raw = np.arange(-6, 6, dtype=np.int16).reshape(3, 4)
    img = read_fits(_write(tmp_path / "b.fits", raw, BLANK=-2))
    expect = raw[::-1].astype(np.float64)
    bad = raw[::-1] == -2
    np.testing.assert_array_equal(img.mask, bad)
    assert np.all(np.isnan(img.data[bad]))
    np.testing.assert_array_equal(img.data[~bad], expect[~bad])


def test_bscale_bzero_in_float64(tmp_path):
    # Physical = BSCALE * stored + BZERO, computed in float64 (exactly numpy's float64
    # result: astropy itself would give float32 for 16-bit data), BLANK checked on the
    # stored integers before scaling.
    raw = np.array([[0, 1, 2], [-32768, 32767, 7]], np.int16)
    img = read_fits(_write(tmp_path / "s.fits", raw, BSCALE=0.1, BZERO=1000.0, BLANK=7))
    expect = raw.astype(np.float64) * 0.1 + 1000.0
    expect[1, 2] = np.nan
    np.testing.assert_array_equal(img.data, expect[::-1])
    np.testing.assert_array_equal(img.mask, np.isnan(expect[::-1]))
    # unsigned 16-bit, stored as signed with BZERO = 32768 (astropy's convention)
    u16 = np.array([[0, 1, 65535], [40000, 32768, 12]], np.uint16)
    img = read_fits(_write(tmp_path / "u16.fits", u16))
    assert img.header["BZERO"] == 32768
    np.testing.assert_array_equal(img.data, u16[::-1].astype(np.float64))
    # 32-bit integers with a non-dyadic scale
    i32 = np.array([[2_000_000_001, -5], [3, 123_456_789]], np.int32)
    img = read_fits(_write(tmp_path / "i32.fits", i32, BSCALE=1e-3, BZERO=-7.5))
    np.testing.assert_array_equal(img.data, (i32.astype(np.float64) * 1e-3 - 7.5)[::-1])


# --- cubes and HDUs -----------------------------------------------------------------


def test_cube_with_singleton_axes_is_squeezed(tmp_path):
    # (1, H, W) with a spectral third axis, and a radio-style (1, 1, H, W) (Stokes,
    # frequency) in SIN: the image and the celestial axes' scale, the flip as in 2-D.
    h, w, s = 6, 9, 2e-4
    raw = np.arange(h * w, dtype=np.float32).reshape(h, w)
    hdr = _tan_header(w, h, s)
    hdr["CTYPE3"], hdr["CRVAL3"], hdr["CDELT3"], hdr["CRPIX3"] = "FREQ", 1.4e9, 1e6, 1.0
    img = read_fits(_write(tmp_path / "c3.fits", raw[None], hdr))
    np.testing.assert_array_equal(img.data, raw[::-1])
    np.testing.assert_allclose(img.pixel_scale, (math.radians(s),) * 2, rtol=1e-12)
    hdr = _tan_header(w, h, s, proj="SIN")
    hdr["CTYPE3"], hdr["CRVAL3"], hdr["CDELT3"], hdr["CRPIX3"] = "FREQ", 1.4e9, 1e6, 1.0
    hdr["CTYPE4"], hdr["CRVAL4"], hdr["CDELT4"], hdr["CRPIX4"] = "STOKES", 1.0, 1.0, 1.0
    img = read_fits(_write(tmp_path / "c4.fits", raw[None, None], hdr), allow_projection=True)
    np.testing.assert_array_equal(img.data, raw[::-1])
    assert img.projection == "SIN"
    np.testing.assert_allclose(img.pixel_scale, (math.radians(s),) * 2, rtol=1e-12)


def test_celestial_axes_not_on_the_image_give_no_scale(tmp_path):
    # A position-velocity slice (RA, singleton Dec, velocity): an image, but not of the
    # sky: no pixel scale, no error.
    data = np.ones((5, 1, 7), np.float32)  # NumPy order: (VELO, DEC, RA)
    hdr = _tan_header(7, 1, 1e-3)
    hdr["CTYPE3"], hdr["CRVAL3"], hdr["CDELT3"], hdr["CRPIX3"] = "VELO-LSR", 0.0, 1e3, 1.0
    img = read_fits(_write(tmp_path / "pv.fits", data, hdr))
    assert img.data.shape == (5, 7) and img.pixel_scale is None and img.fov is None


def test_real_cubes_are_refused(tmp_path):
    cube = np.ones((3, 4, 5), np.float32)
    with pytest.raises(ValueError, match=r"3-D data of shape \(3, 4, 5\).*pass one plane"):
        read_fits(_write(tmp_path / "cube.fits", cube))
    # with hdu=None a later 2-D image is chosen instead
    fits.HDUList([fits.PrimaryHDU(cube), fits.ImageHDU(np.ones((4, 5)))]).writeto(
        tmp_path / "later.fits"
    )
    assert read_fits(tmp_path / "later.fits").hdu == 1


def test_hdu_choice(tmp_path):
    sci = np.arange(12, dtype=np.float32).reshape(3, 4)
    table = fits.BinTableHDU.from_columns([fits.Column(name="x", format="E", array=[1.0])])
    hdul = fits.HDUList([fits.PrimaryHDU(), table, fits.ImageHDU(sci, name="SCI")])
    hdul.append(fits.ImageHDU(2 * sci, name="ERR"))
    hdul.writeto(tmp_path / "mef.fits")
    path = tmp_path / "mef.fits"
    first = read_fits(path)  # the empty primary and the table are skipped
    assert first.hdu == 2
    np.testing.assert_array_equal(first.data, sci[::-1])
    assert read_fits(path, hdu="ERR").hdu == 3
    assert read_fits(path, hdu=("SCI", 1)).hdu == 2
    with pytest.raises(ValueError, match="HDU 1 of .* is a BinTableHDU, not an image"):
        read_fits(path, hdu=1)
    with pytest.raises(ValueError, match="HDU 0 of .* has no data"):
        read_fits(path, hdu=0)
    with pytest.raises(ValueError, match=r"has no HDU 'DQ' \(it has 0: PRIMARY, 1: -, 2: SCI"):
        read_fits(path, hdu="DQ")
    fits.HDUList([fits.PrimaryHDU(), table]).writeto(tmp_path / "tab.fits")
    with pytest.raises(ValueError, match="no 2-D image in any of its 2 HDUs"):
        read_fits(tmp_path / "tab.fits")


def test_compressed_and_gzipped_files(tmp_path):
    raw = np.arange(30, dtype=np.int32).reshape(5, 6)
    comp = fits.CompImageHDU(raw)
    comp.header["BLANK"] = 4
    fits.HDUList([fits.PrimaryHDU(), comp]).writeto(tmp_path / "c.fits")
    img = read_fits(tmp_path / "c.fits")
    assert img.hdu == 1 and img.mask[::-1][0, 4] and img.mask.sum() == 1
    np.testing.assert_array_equal(img.data[~img.mask], raw[::-1][~img.mask].astype(float))
    data = (_write(tmp_path / "p.fits", raw.astype(np.float32))).read_bytes()
    (tmp_path / "p.fits.gz").write_bytes(gzip.compress(data))
    np.testing.assert_array_equal(read_fits(tmp_path / "p.fits.gz").data, raw[::-1])


# --- header keywords ----------------------------------------------------------------


def test_gain_exposure_and_unit(tmp_path):
    img = read_fits(
        _write(tmp_path / "a.fits", np.ones((3, 3)), GAIN=2.5, EXPTIME=300.0, BUNIT="ADU")
    )
    assert (img.gain, img.exposure, img.unit) == (2.5, 300.0, "ADU")
    img = read_fits(_write(tmp_path / "b.fits", np.ones((3, 3)), EGAIN=1.7, EXPOSURE=12))
    assert (img.gain, img.exposure, img.unit) == (1.7, 12.0, None)
    img = read_fits(_write(tmp_path / "c.fits", np.ones((3, 3))))
    assert (img.gain, img.exposure, img.unit) == (None, None, None)
    # numeric strings are numbers; junk and non-positive gains are absent
    img = read_fits(_write(tmp_path / "d.fits", np.ones((3, 3)), GAIN="3.25", EXPTIME="n/a"))
    assert (img.gain, img.exposure) == (3.25, None)
    img = read_fits(_write(tmp_path / "e.fits", np.ones((3, 3)), GAIN=0.0, EGAIN=4.0))
    assert img.gain == 4.0
    # multi-extension files keep them in the primary header
    primary = fits.PrimaryHDU()
    primary.header["EXPTIME"], primary.header["GAIN"] = 60.0, 1.1
    ext = fits.ImageHDU(np.ones((3, 3)), name="SCI")
    ext.header["BUNIT"] = "electron/s"
    fits.HDUList([primary, ext]).writeto(tmp_path / "m.fits")
    img = read_fits(tmp_path / "m.fits")
    assert (img.gain, img.exposure, img.unit) == (1.1, 60.0, "electron/s")
    assert "EXPTIME" not in img.header  # the image HDU's own header


# --- errors -------------------------------------------------------------------------


def _one_line_error(path, match, **kw):
    with pytest.raises(ValueError, match=match) as err:
        read_fits(path, **kw)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_unreadable_files(tmp_path):
    _one_line_error(tmp_path / "missing.fits", "does not exist")
    _one_line_error(tmp_path, r"does not exist \(a folder\)")
    (tmp_path / "empty.fits").write_bytes(b"")
    _one_line_error(tmp_path / "empty.fits", "is empty")
    (tmp_path / "text.fits").write_text("SIMPLE? no, just some text\n" * 200)
    _one_line_error(tmp_path / "text.fits", "is not a readable FITS file")
    whole = _write(tmp_path / "whole.fits", np.ones((200, 300), np.float32)).read_bytes()
    (tmp_path / "short.fits").write_bytes(whole[: len(whole) // 2])
    _one_line_error(tmp_path / "short.fits", "truncated")
    _write(tmp_path / "spec.fits", np.ones(10))
    _one_line_error(tmp_path / "spec.fits", r"1-D data of shape \(10,\), not a 2-D image", hdu=0)
    bad = fits.Header({"CTYPE1": "RA---TAN", "CTYPE2": "DEC--TAN", "PV2_1": "x"})
    bad["CTYPE1"] = "RA---ZZZ"
    _one_line_error(_write(tmp_path / "badwcs.fits", np.ones((4, 4)), bad), "WCS astropy cannot")


def test_missing_astropy_names_the_extra(tmp_path, monkeypatch):
    path = _write(tmp_path / "a.fits", np.ones((3, 3)))
    real_import = builtins.__import__

    def no_astropy(name, *args, **kwargs):
        if name.startswith("astropy"):
            raise ImportError(f"No module named {name!r}", name=name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_astropy)
    with pytest.raises(MissingExtraError, match=r"jaxlens-bh\[fits\]"):
        read_fits(path)
