"""Image files through OpenImageIO: plain Python at the edges, never jitted."""

import os
import tempfile
from pathlib import Path

import numpy as np

FLOAT_FORMATS = {".exr", ".hdr", ".tif", ".tiff"}


def _oiio():
    import OpenImageIO as oiio

    return oiio


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function on linear values in [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def write_image(path, image: np.ndarray, *, exposure: float = 0.0) -> Path:
    """Write a linear float image, atomically (a temporary file, then a rename).

    EXR/HDR/TIFF keep linear floats (scaled by $2^{exposure}$); PNG/JPEG get the
    exposure, the sRGB transfer and 8 bits. Never leaves a half-written file.

    **Arguments:** `path`; `image`: `(H, W)` or `(H, W, C)` linear radiance;
    `exposure`: stops.

    **Returns:** the path written.
    """
    oiio = _oiio()
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"output folder {str(folder)!r} does not exist")
    if not os.access(folder, os.W_OK):
        raise ValueError(f"output folder {str(folder)!r} is not writable")
    ext = path.suffix.lower()
    img = np.asarray(image, np.float32)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[-1] not in (1, 2, 3, 4):
        raise ValueError(f"image of shape {img.shape} is not (H, W) or (H, W, 1..4)")
    img = img * np.float32(2.0**exposure)
    if ext in FLOAT_FORMATS:
        data, fmt = img, oiio.FLOAT if ext != ".hdr" else oiio.FLOAT
    else:
        data, fmt = np.round(srgb_encode(img) * 255.0).astype(np.uint8), oiio.UINT8
    h, w, c = data.shape
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=folder)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise ValueError(f"cannot write images of type {ext!r}: {oiio.geterror()}")
        spec = oiio.ImageSpec(w, h, c, fmt)
        if not out.open(tmp, spec) or not out.write_image(data) or not out.close():
            raise OSError(f"writing {str(path)!r} failed: {out.geterror()}")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def read_image(path) -> np.ndarray:
    """Read an image as stored, normalised to [0, 1] for integer formats.

    **Returns:** float32 `(H, W, C)`; raises `ValueError` naming the file when it
    cannot be read as an image.
    """
    oiio = _oiio()
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"image file {str(path)!r} does not exist")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ValueError(f"{str(path)!r} is not a readable image: {oiio.geterror()}")
    try:
        data = inp.read_image(oiio.FLOAT)
        err = inp.geterror()
    finally:
        inp.close()
    if data is None or (err and "truncat" in err.lower()):
        raise ValueError(f"{str(path)!r} is not a readable image: {err or 'no pixel data'}")
    data = np.asarray(data, np.float32)
    if data.ndim == 2:
        data = data[..., None]
    return data
