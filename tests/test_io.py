"""Image files: formats and channels, linear floats vs sRGB, atomic writes, bad files."""

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from jaxlens import _io
from jaxlens._io import read_image, srgb_decode, srgb_encode, write_gif, write_image


def _image(h=12, w=16, c=3, seed=0):
    return np.random.default_rng(seed).random((h, w, c)).astype(np.float32)


def test_srgb_transfer_inverts():
    x = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=1e-6)  # float32 pow
    # The standard's anchor points: 0.0031308 -> 0.04045, 0.5 (linear) -> 0.7354.
    assert float(srgb_encode(np.float32(0.0031308))) == pytest.approx(0.04045, abs=1e-5)
    assert float(srgb_encode(np.float32(0.5))) == pytest.approx(0.735357, abs=1e-5)


def test_exr_keeps_linear_floats_exactly(tmp_path):
    img = _image() * 40.0  # HDR values far above 1 survive
    p = write_image(tmp_path / "a.exr", img, exposure=3.0)  # exposure is for PNG/JPEG only
    np.testing.assert_array_equal(read_image(p), img)


def test_hdr_keeps_linear_floats_to_rgbe_precision(tmp_path):
    img = _image() * 40.0 + 0.01
    back = read_image(write_image(tmp_path / "a.hdr", img))
    # RGBE: an 8-bit mantissa shared by the three channels, relative to the largest
    # channel: the step is 2^e / 256 with 2^(e-1) <= max < 2^e, so < max / 128.
    assert np.all(np.abs(back - img) <= img.max(axis=-1, keepdims=True) / 128 + 1e-7)


def test_png_gets_exposure_and_srgb(tmp_path):
    img = _image() * 0.25
    p = write_image(tmp_path / "a.png", img, exposure=2.0)  # x 4
    raw = np.asarray(Image.open(p)).astype(np.float32) / 255.0
    np.testing.assert_allclose(raw, srgb_encode(img * 4.0), atol=0.5 / 255 + 1e-6)
    # Read back: decoded to linear; 8-bit quantisation (half a step in sRGB, at most
    # 0.5/255 * d(linear)/d(srgb) <= 0.5/255 * 2.4) bounds the error.
    np.testing.assert_allclose(read_image(p), np.clip(img * 4.0, 0, 1), atol=0.5 / 255 * 2.4)


def test_jpeg_is_lossy_but_close(tmp_path):
    y, x = np.mgrid[0:32, 0:48] / 48.0
    img = np.stack([x, y, 0.5 * np.ones_like(x)], -1).astype(np.float32) * 0.8
    back = read_image(write_image(tmp_path / "a.jpg", img))
    assert np.abs(srgb_encode(back) - srgb_encode(img)).mean() < 2 / 255  # smooth image


@pytest.mark.parametrize("ext", [".png", ".jpg", ".exr", ".hdr", ".tif"])
@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_every_channel_count_writes_and_reads(tmp_path, ext, channels):
    # A smooth image (JPEG-friendly); with alpha (2 or 4 channels) the colour is
    # associated, colour <= alpha = 0.8, as a linear render's would be.
    y, x = np.mgrid[0:16, 0:16] / 16.0
    planes = [0.1 + 0.6 * x, 0.2 + 0.5 * y, 0.3 + 0.3 * x * y][: 1 if channels <= 2 else 3]
    if channels in (2, 4):
        planes.append(np.full_like(x, 0.8))
    img = np.stack(planes, -1).astype(np.float32)
    back = read_image(write_image(tmp_path / f"a{ext}", img))
    assert back.shape[:2] == (16, 16)
    # What each format stores: HDR is RGB; JPEG grey or RGB; the others all of them.
    expect = {".hdr": 3, ".jpg": 1 if channels <= 2 else 3}.get(ext, channels)
    assert back.shape[2] == expect
    # Tolerances: 8-bit sRGB (half a step, x 2.4 in linear, / alpha 0.8 through the
    # unassociation) 0.01; JPEG (lossy, chroma subsampled; 0.029 measured on this
    # ramp) 0.05; RGBE 1/128 of
    # the largest channel; float files exact.
    tol = {".jpg": 0.05, ".png": 0.01, ".hdr": 0.01}.get(ext, 1e-6)
    assert np.abs(back[..., 0] - img[..., 0]).max() < tol
    if expect == channels and channels in (2, 4):
        assert np.abs(back[..., -1] - 0.8).max() < tol  # alpha kept


def test_write_is_atomic_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "out.exr"
    target.write_bytes(b"previous")
    oiio = _io._oiio()
    real = oiio.ImageOutput

    class Failing:
        @staticmethod
        def create(name):
            out = real.create(name)

            class Wrapper:
                def open(self, *a):
                    return out.open(*a)

                def write_image(self, data):
                    # Half the file is on disk when the failure (or Ctrl-C) comes.
                    out.write_scanlines(0, data.shape[0] // 2, 0, data[: data.shape[0] // 2])
                    raise KeyboardInterrupt

                def close(self):
                    return out.close()

                def geterror(self):
                    return ""

            return Wrapper()

    monkeypatch.setattr(oiio, "ImageOutput", Failing)
    with pytest.raises(KeyboardInterrupt):
        write_image(target, _image())
    # The old file is untouched and no temporary file is left behind.
    assert target.read_bytes() == b"previous"
    assert sorted(os.listdir(tmp_path)) == ["out.exr"]


def test_write_failure_from_the_library_is_an_error_and_leaves_nothing(tmp_path, monkeypatch):
    oiio = _io._oiio()
    real = oiio.ImageOutput

    class Broken:
        @staticmethod
        def create(name):
            out = real.create(name)

            class Wrapper:
                def open(self, *a):
                    return out.open(*a)

                def write_image(self, data):
                    return False

                def close(self):
                    return out.close()

                def geterror(self):
                    return "disk full"

            return Wrapper()

    monkeypatch.setattr(oiio, "ImageOutput", Broken)
    with pytest.raises(OSError, match="disk full"):
        write_image(tmp_path / "x.png", _image())
    assert os.listdir(tmp_path) == []


def test_bad_output_paths(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        write_image(tmp_path / "missing" / "x.png", _image())
    with pytest.raises(ValueError, match="unsupported extension '.bmp'"):
        write_image(tmp_path / "x.bmp", _image())
    with pytest.raises(ValueError, match="is a folder"):
        (tmp_path / "d.png").mkdir()
        write_image(tmp_path / "d.png", _image())
    with pytest.raises(ValueError, match="shape"):
        write_image(tmp_path / "x.png", np.zeros((2, 2, 5)))


def test_read_only_folder(tmp_path):
    # /sys refuses new files even for root; elsewhere a chmod'ed folder does (not for
    # root, who may write anywhere: then the folder is simply writable).
    if os.geteuid() == 0:
        folder = Path("/sys")
    else:
        folder = tmp_path / "ro"
        folder.mkdir()
        folder.chmod(0o555)
    try:
        probe = folder / ".jaxlens-test-probe"
        probe.write_bytes(b"")
        probe.unlink()
        pytest.skip(f"{folder} is writable here")
    except OSError:
        pass
    with pytest.raises(ValueError, match="not writable"):
        write_image(folder / "x.png", _image())


def test_bad_input_files(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        read_image(tmp_path / "nope.png")
    (tmp_path / "empty.exr").write_bytes(b"")
    with pytest.raises(ValueError, match="empty"):
        read_image(tmp_path / "empty.exr")
    (tmp_path / "text.png").write_text("not an image at all")
    with pytest.raises(ValueError, match="not a readable image"):
        read_image(tmp_path / "text.png")
    for ext in (".png", ".exr", ".jpg", ".hdr"):
        good = write_image(tmp_path / f"good{ext}", _image(64, 64))
        data = good.read_bytes()
        cut = tmp_path / f"cut{ext}"
        cut.write_bytes(data[: len(data) // 2])
        with pytest.raises(ValueError, match="not a readable image"):
            read_image(cut)


def test_gif_animation(tmp_path):
    frames = np.stack([_image(10, 14, 3, seed=i) for i in range(4)])
    p = write_gif(tmp_path / "a.gif", frames, fps=10)
    with Image.open(p) as im:
        assert im.n_frames == 4 and im.size == (14, 10)
        assert im.info["duration"] == 100
    assert sorted(os.listdir(tmp_path)) == ["a.gif"]
    with pytest.raises(ValueError, match="not a .gif"):
        write_gif(tmp_path / "a.png", frames)
