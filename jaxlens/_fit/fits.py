"""Astronomers' images: FITS files through `astropy.io.fits` and `astropy.wcs` (the
optional `fits` extra), read into jaxlens's pixel convention with the field of view of
jaxlens's pinhole camera. Plain Python at the edges, never jitted.

Orientation. FITS stores the first row of the data array (pixel row 1) at the bottom of
the picture: the FITS pixel coordinate $p_2$ increases upwards, and north is up for the
usual orientation. jaxlens puts row 0 at the top (PHYSICS.md, "Pixels"), so the
data are flipped vertically, and only vertically: FITS $p_1$ increases to the right as
jaxlens's columns do. jaxlens's pixel (column $i$, row $j$), both from 0, of an image of
$W \\times H$ pixels is the FITS pixel $(p_1, p_2) = (i + 1, H - j)$ (1-based), and
jaxlens's pixel-centre coordinates $x = i + 0.5 - W/2$, $y = H/2 - (j + 0.5)$ are
$p_1 - (W + 1)/2$ and $p_2 - (H + 1)/2$: offsets from the image centre with $y$ up in
both.
"""

import dataclasses
import math
import warnings
from pathlib import Path

import numpy as np

from .._io import MissingExtraError

# jaxlens's camera is a gnomonic pinhole: TAN. "TAN-SIP" (CTYPE "RA---TAN-SIP") is TAN.
_PINHOLE = "TAN"
_SQUARE_TOL = 1e-3  # |scale_x / scale_y - 1| and |cos(angle between pixel axes)|


def _astropy():
    """astropy.io.fits, astropy.wcs and astropy.units, imported on first use."""
    try:
        import astropy.units as u
        from astropy.io import fits
        from astropy.wcs import WCS, FITSFixedWarning
    except ImportError as e:
        raise MissingExtraError(
            "reading FITS files needs astropy: pip install 'jaxlens-bh[fits]' (or astropy>=6)",
            name="astropy",
        ) from e
    return fits, WCS, FITSFixedWarning, u


@dataclasses.dataclass(frozen=True)
class FitsImage:
    """A 2-D image read from a FITS file by `read_fits`, in jaxlens's conventions.

    A host-side record (NumPy arrays and an astropy header), not a pytree: give its
    `data`, `mask` and `fov` to the model, not the record.

    **Fields:**

    - `path`: the file read.
    - `hdu`: the index of the HDU read in the file (0 = primary).
    - `data`: float64 `(H, W)` pixel values, physical (BSCALE and BZERO applied), in
        `unit`; row 0 at the TOP (the file's rows flipped: see the module's docstring);
        NaN where the file has NaN, an infinity or the BLANK value of an integer image.
    - `mask`: bool `(H, W)`, True where a pixel is bad (those NaN pixels).
    - `pixel_scale`: `(scale_x, scale_y)`, radians per pixel along a row and along a
        column at the WCS's reference point (absolute values, from the CD matrix or
        PC x CDELT); None when the image has no celestial WCS.
    - `fov`: the horizontal field of view, in radians, of jaxlens's pinhole camera with
        the same pixel scale: $2\\arctan(W \\,\\mathrm{scale}_x / 2)$ (see `read_fits`);
        None without a celestial WCS.
    - `projection`: the WCS's projection code ("TAN", "SIN", ...), None without a
        celestial WCS.
    - `gain`: detector gain in electrons per data unit (GAIN or EGAIN), None if absent.
    - `exposure`: exposure time in seconds (EXPTIME or EXPOSURE), None if absent.
    - `unit`: the data's unit (BUNIT) as written, None if absent.
    - `header`: the image HDU's header (an `astropy.io.fits.Header`, a copy).
    """

    path: Path
    hdu: int
    data: np.ndarray
    mask: np.ndarray
    pixel_scale: tuple[float, float] | None
    fov: float | None
    projection: str | None
    gain: float | None
    exposure: float | None
    unit: str | None
    header: object


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


def _number(header, keys, *, positive: bool) -> float | None:
    """The first of `keys` in `header` that holds a finite number (> 0 if `positive`,
    else >= 0), numeric strings included; None if there is none."""
    for key in keys:
        value = header.get(key)
        if value is None or isinstance(value, bool):
            continue
        try:
            x = float(value)
        except (TypeError, ValueError):
            continue
        if math.isfinite(x) and (x > 0 if positive else x >= 0):
            return x
    return None


def _image_axes(shape: tuple[int, ...], where: str) -> tuple[int, ...]:
    """The NumPy axes of a data array of `shape` that hold the image (two of them), or
    a ValueError for data that are not a 2-D image."""
    n = len(shape)
    if n == 2:
        return (0, 1)
    if n < 2:
        raise ValueError(f"{where} holds {n}-D data of shape {shape}, not a 2-D image")
    if all(s == 1 for s in shape[:-2]):  # (..., 1, NAXIS2, NAXIS1): the usual case
        return (n - 2, n - 1)
    big = tuple(k for k, s in enumerate(shape) if s > 1)
    if len(big) == 2:
        return big
    raise ValueError(
        f"{where} holds {len(big)}-D data of shape {shape} (NumPy order); only a 2-D image, "
        "or a cube whose other axes have length 1, can be read: pass one plane"
    )


def _choose_hdu(hdul, hdu, where: str) -> int:
    """The index of the HDU to read: `hdu` (an index, EXTNAME or (EXTNAME, EXTVER)) or
    the first image HDU with 2-D data (singleton axes aside)."""
    if hdu is not None:
        try:
            index = hdul.index_of(hdu)
            h = hdul[index]
        except (KeyError, IndexError, TypeError):
            names = ", ".join(f"{i}: {x.name or '-'}" for i, x in enumerate(hdul))
            raise ValueError(f"{where} has no HDU {hdu!r} (it has {names})") from None
        if not getattr(h, "is_image", False):
            raise ValueError(f"HDU {hdu!r} of {where} is a {type(h).__name__}, not an image")
        if not h.shape:
            raise ValueError(f"HDU {hdu!r} of {where} has no data (NAXIS = 0)")
        return index
    refused = None
    for index, h in enumerate(hdul):
        if not getattr(h, "is_image", False) or not h.shape:
            continue
        try:
            _image_axes(tuple(h.shape), f"HDU {index} of {where}")
        except ValueError as e:
            refused = refused or e
            continue
        return index
    if refused is not None:
        raise refused
    raise ValueError(f"{where} has no 2-D image in any of its {len(hdul)} HDUs")


def _pixels(h, axes: tuple[int, ...], where: str) -> tuple[np.ndarray, np.ndarray]:
    """Physical float64 pixel values of the image HDU `h` (read unscaled), in the
    file's row order, and the bad-pixel mask (NaN, infinite or BLANK)."""
    try:
        raw = np.asarray(h.data)
    except Exception as e:  # astropy's errors for short or corrupt data
        raise ValueError(f"{where} has unreadable pixels (truncated?): {_one_line(e)}") from None
    header = h.header
    if raw.ndim > 2:
        index = tuple(slice(None) if k in axes else 0 for k in range(raw.ndim))
        raw = raw[index]
    bad = np.zeros(raw.shape, bool)
    if np.issubdtype(raw.dtype, np.integer) and "BLANK" in header:
        bad |= raw == int(header["BLANK"])
    data = raw.astype(np.float64)
    scale, zero = float(header.get("BSCALE", 1.0)), float(header.get("BZERO", 0.0))
    if scale != 1.0 or zero != 0.0:
        data = data * scale + zero
    bad |= ~np.isfinite(data)
    data[bad] = np.nan
    return data, bad


def _celestial(WCS, header, hdul, fits_axes: list[int], where: str):
    """The 2-D celestial WCS of the image axes `fits_axes` (FITS numbering, x first),
    or None when those axes carry no celestial coordinates."""
    try:
        w = WCS(header, fobj=hdul, naxis=fits_axes)
    except Exception as e:  # wcslib's errors, or astropy's (SIP in a cube, ...)
        first = e
        try:  # is it the choice of axes (celestial axes elsewhere in a cube)?
            full = WCS(header, fobj=hdul)
            lng, lat = full.wcs.lng + 1, full.wcs.lat + 1
        except Exception:
            lng = lat = None
        if lng is not None and (lng < 1 or lat < 1 or {lng, lat} != set(fits_axes)):
            return None
        raise ValueError(f"{where} has a WCS astropy cannot read: {_one_line(first)}") from None
    if w.wcs.lng < 0 or w.wcs.lat < 0:
        return None
    return w


def read_fits(
    path,
    *,
    hdu: int | str | tuple[str, int] | None = None,
    allow_projection: bool = False,
    allow_nonsquare: bool = False,
) -> FitsImage:
    """Read a 2-D image from a FITS file, with its pixel scale and the field of view of
    jaxlens's pinhole camera.

    Pixels: flipped vertically into jaxlens's convention (row 0 at the top; the module's
    docstring gives the pixel correspondence), as float64 physical values (BSCALE and
    BZERO applied in float64, also for unsigned integers stored with BZERO), NaN and
    `mask` True where the file has NaN, an infinity or an integer image's BLANK value.

    Which HDU: `hdu` if given, else the first image HDU whose data are 2-D once axes of
    length 1 are dropped (the primary HDU of a multi-extension file is often empty);
    cubes with singleton axes (e.g. radio images `(1, 1, H, W)`: Stokes and frequency)
    are squeezed to their two image axes; real 3-D data are refused. GAIN/EGAIN and
    EXPTIME/EXPOSURE are looked up in the image HDU's header, then in the primary
    header (where multi-extension files keep them); BUNIT in the image HDU's header.

    Field of view. The WCS maps a pixel offset $p$ from the reference pixel to
    intermediate coordinates $(x, y) = \\mathrm{CD}\\, p$ (CD, or PC times CDELT, in
    degrees). For the gnomonic projection (TAN) the angle $\\theta$ from the projection's
    tangent point satisfies $\\tan\\theta = \\sqrt{x^2 + y^2}$ (radians), so a pixel $n$
    pixels from the centre along a row lies at $\\theta = \\arctan(n\\,s)$, $s$ =
    `scale_x` in radians per pixel. jaxlens's pinhole camera puts it at
    $\\arctan(n/f)$ with focal length $f = (W/2)/\\tan(\\mathrm{FOV}/2)$ pixels. The two
    agree for every $n$ when $f = 1/s$: $\\mathrm{FOV} = 2\\arctan(W s / 2)$, exactly (not
    only for small angles); `tests/test_fits_io.py` checks it against astropy's own
    TAN projection of the image's two edges. The camera's optical axis is the image
    centre; a reference pixel elsewhere is the same camera turned, which for fields of
    a few degrees changes positions by $O(\\theta^2)$ of the offset. Distortions (SIP,
    lookup tables) are not in the scale: it is the linear part at the reference point.

    Other projections: SIN (orthographic) has $\\sin\\theta = n s$, ARC (zenithal
    equidistant) $\\theta = n s$, against TAN's $\\tan\\theta = n s$; all three agree to
    first order, and the angles differ by a fraction $O(\\theta^2)$: $\\theta^2/2$ between
    TAN and SIN, $\\theta^2/3$ between TAN and ARC (1.5e-4 at 1 degree, 1.2e-11 at 1
    arcsecond). So for the small fields of telescope images (Einstein rings are
    arcseconds) the pinhole camera with the same central scale describes them well;
    `allow_projection=True` accepts any projection and reports that camera's `fov`.

    **Arguments:**

    - `path`: the FITS file (`str` or path; gzip-compressed files too).
    - `hdu`: the HDU to read: index, EXTNAME or (EXTNAME, EXTVER); None picks the first
        2-D image.
    - `allow_projection`: accept a celestial projection other than TAN (see above).
    - `allow_nonsquare`: accept pixels that are not square (|scale_x / scale_y - 1| >
        1e-3) or not orthogonal (|cos| of the angle between the pixel axes > 1e-3);
        `fov` then uses `scale_x`, and the camera's square pixels do not describe the
        image's columns exactly.

    **Returns:** a `FitsImage`. Raises `ValueError` naming the file (one line) when it is
    missing, empty, not FITS, truncated or unreadable, when the HDU asked for is not an
    image or there is no 2-D image, for 3-D data, an unreadable WCS, a projection other
    than TAN or non-square pixels (unless allowed), and `MissingExtraError` (also a
    `ValueError`) when astropy is not installed.
    """
    fits, WCS, FITSFixedWarning, u = _astropy()
    path = Path(path)
    where = f"FITS file {str(path)!r}"
    if not path.is_file():
        raise ValueError(f"{where} does not exist" + (" (a folder)" if path.is_dir() else ""))
    if path.stat().st_size == 0:
        raise ValueError(f"{where} is empty")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        warnings.filterwarnings("ignore", message=".*truncated")  # refused below instead
        try:
            hdul = fits.open(path, memmap=False, do_not_scale_image_data=True)
        except Exception as e:
            raise ValueError(f"{where} is not a readable FITS file: {_one_line(e)}") from None
        with hdul:
            try:
                hdul.readall()  # every header now, so that a corrupt one fails here
            except Exception as e:
                raise ValueError(f"{where} is not a readable FITS file: {_one_line(e)}") from None
            index = _choose_hdu(hdul, hdu, where)
            h = hdul[index]
            at = f"HDU {index} of {where}"
            axes = _image_axes(tuple(h.shape), at)
            data, mask = _pixels(h, axes, at)
            header, primary = h.header.copy(), hdul[0].header.copy()
            ndim = len(h.shape)
            fits_axes = [ndim - axes[1], ndim - axes[0]]  # FITS numbering: x (NAXIS1) first
            w = _celestial(WCS, header, hdul, fits_axes, at)
    data, mask = np.ascontiguousarray(data[::-1]), np.ascontiguousarray(mask[::-1])

    def keyword(keys, *, positive):
        found = _number(header, keys, positive=positive)
        return found if found is not None else _number(primary, keys, positive=positive)

    unit = str(header["BUNIT"]).strip() if "BUNIT" in header else ""
    pixel_scale = fov = projection = None
    if w is not None:
        projection = w.wcs.ctype[w.wcs.lng][5:8].strip("-") or None
        m = np.asarray(w.pixel_scale_matrix, np.float64)  # columns: the pixel axes' steps
        to_rad = u.Unit(w.wcs.cunit[w.wcs.lng]).to(u.rad)
        sx, sy = (float(np.hypot(*m[:, k])) * to_rad for k in (0, 1))
        if not (sx > 0 and sy > 0 and math.isfinite(sx) and math.isfinite(sy)):
            raise ValueError(f"{at} has a singular WCS (pixel scale 0)")
        cos = float(m[:, 0] @ m[:, 1]) / (float(np.hypot(*m[:, 0])) * float(np.hypot(*m[:, 1])))
        arcsec = 180.0 * 3600.0 / math.pi
        if not allow_nonsquare and (abs(sx / sy - 1.0) > _SQUARE_TOL or abs(cos) > _SQUARE_TOL):
            raise ValueError(
                f"{at} has pixels that are not square: "
                f"{sx * arcsec:.6g} x {sy * arcsec:.6g} arcsec (ratio {sx / sy:.6f}), axes at "
                f"{math.degrees(math.acos(max(-1.0, min(1.0, cos)))):.4f} deg; jaxlens's camera "
                "has square pixels: resample the image, or pass allow_nonsquare=True"
            )
        if projection != _PINHOLE and not allow_projection:
            raise ValueError(
                f"{at} has the {projection!r} projection "
                f"(CTYPE {w.wcs.ctype[w.wcs.lng]!r}); jaxlens's pinhole camera is gnomonic "
                "(TAN): pass allow_projection=True to use the same central pixel scale "
                "(SIN and ARC agree with TAN to a fraction theta^2 / 2 of the angle theta)"
            )
        pixel_scale = (sx, sy)
        fov = 2.0 * math.atan(0.5 * data.shape[1] * sx)
    return FitsImage(
        path=path,
        hdu=index,
        data=data,
        mask=mask,
        pixel_scale=pixel_scale,
        fov=fov,
        projection=projection,
        gain=keyword(("GAIN", "EGAIN"), positive=True),
        exposure=keyword(("EXPTIME", "EXPOSURE"), positive=False),
        unit=unit or None,
        header=header,
    )
