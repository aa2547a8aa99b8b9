"""Image files: formats and channels, linear floats vs sRGB, atomic writes, bad files;
GIF and MP4 animations."""

import os
import stat
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from jaxlens import (
    read_image,
    srgb_decode,
    srgb_encode,
    to_display,
    write_gif,
    write_image,
    write_video,
)


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


def _png_row_filters(path) -> set[int]:
    """The filter type byte of each row of an 8-bit RGB PNG (its IDAT data inflated)."""
    import struct
    import zlib

    data, idat, pos = path.read_bytes(), b"", 8
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        if kind == b"IHDR":
            width, height = struct.unpack(">II", data[pos + 8 : pos + 16])
        if kind == b"IDAT":
            idat += data[pos + 8 : pos + 8 + length]
        pos += 12 + length
    raw = zlib.decompress(idat)
    stride = 1 + 3 * width
    return {raw[r * stride] for r in range(height)}


def test_png_rows_filtered_by_sub_or_up(tmp_path):
    # A smooth gradient with noise: libpng's full search picks "average" or "paeth" for
    # some of its rows.
    y, x = np.mgrid[0:64, 0:96].astype(np.float32)
    img = (0.3 + 0.2 * np.sin(x / 7.0) * np.cos(y / 5.0))[..., None] + 0.02 * _image(64, 96)
    p = write_image(tmp_path / "a.png", img)
    assert _png_row_filters(p) <= {1, 2}  # sub, up
    np.testing.assert_allclose(read_image(p), img, atol=0.01)


def test_to_display_in_pieces_is_the_whole_image_transfer():
    # to_display works through the image in pieces of 2^20 values (bounded temporaries);
    # the result is the transfer applied to the whole image, across piece boundaries,
    # for float64 input and for a non-contiguous view.
    img = np.random.default_rng(1).random((700, 600, 3)) * 1.5 - 0.1  # 1.26e6 values
    img[3, 4] = np.nan
    for x in (img, img[:, ::2]):
        want = np.round(srgb_encode(np.asarray(x, np.float32) * np.float32(0.5)) * 255.0)
        got = to_display(x, exposure=-1.0)
        assert got.dtype == np.uint8 and got.shape == x.shape
        np.testing.assert_array_equal(got, want.astype(np.uint8))


def test_images_too_large_for_memory_are_refused_before_reading(tmp_path, monkeypatch):
    import jaxlens._io as io_

    p = write_image(tmp_path / "a.png", _image(64, 64))
    monkeypatch.setattr(io_, "available_memory", lambda: 100_000)  # bytes
    with pytest.raises(ValueError, match=r"64 x 64 pixels x 3 channels: reading it needs"):
        read_image(p)
    with pytest.raises(ValueError, match=r"2 x 640 x 480 pixels need about"):
        io_.check_render_memory(640, 480, frames=2)
    monkeypatch.setattr(io_, "available_memory", lambda: None)  # unknown: not checked
    io_.check_render_memory(640, 480, frames=2)
    assert read_image(p).shape == (64, 64, 3)


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


def _patch_image_output(monkeypatch, write_image, error=""):
    """Make OpenImageIO's `ImageOutput` open and close real files but write through
    `write_image(out, data)` (`out`: the real output) and report `error`."""
    import OpenImageIO as oiio

    real = oiio.ImageOutput

    class Patched:
        @staticmethod
        def create(name):
            out = real.create(name)

            class Wrapper:
                def open(self, *a):
                    return out.open(*a)

                def write_image(self, data):
                    return write_image(out, data)

                def close(self):
                    return out.close()

                def geterror(self):
                    return error

            return Wrapper()

    monkeypatch.setattr(oiio, "ImageOutput", Patched)


def test_temporaries_of_killed_processes_are_found_and_removed(tmp_path, capsys):
    import subprocess

    from jaxlens import _io, cli

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # a process that no longer runs
    host = _io._host()
    names = {
        "killed": f".out{_io._TMP_TAG}{host}.{dead.pid}.abcd1234.png",
        "other_output": f".other{_io._TMP_TAG}{host}.{dead.pid}.abcd1234.png",
        # Written by a running process, which holds its lock (its PID is no proof:
        # this one's is of a process that has ended, as in another PID namespace).
        "running": f".out{_io._TMP_TAG}{host}.{dead.pid}.efgh5678.png",
        "other_host": f".out{_io._TMP_TAG}elsewhere.{dead.pid}.abcd1234.png",
        "not_ours": ".out.abcd1234.png",
    }
    for name in names.values():
        (tmp_path / name).write_bytes(b"partial")
    alive = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, os, sys, time; fd = os.open(sys.argv[1], 0); "
         "fcntl.flock(fd, fcntl.LOCK_EX); print(1, flush=True); time.sleep(60)",
         str(tmp_path / names["running"])], stdout=subprocess.PIPE)  # fmt: skip
    try:
        assert alive.stdout.readline() == b"1\n"  # the lock is held
        # Writing out.png removes its own stale temporary only.
        write_image(tmp_path / "out.png", _image())
        left = set(os.listdir(tmp_path))
        assert names["killed"] not in left and "out.png" in left
        assert {names[k] for k in ("other_output", "running", "other_host", "not_ours")} <= left
        # `jaxlens clean` removes the other output's; a dry run lists it first.
        assert cli.main(["clean", "--dry-run", str(tmp_path)]) == 0
        assert "would remove" in capsys.readouterr().out and names["other_output"] in left
        assert cli.main(["clean", str(tmp_path)]) == 0
        assert names["other_output"] in capsys.readouterr().out
        left = set(os.listdir(tmp_path))
        assert names["other_output"] not in left
        assert {names[k] for k in ("running", "other_host", "not_ours")} <= left
    finally:
        alive.kill()
        alive.wait()


def test_write_is_atomic_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "out.exr"
    target.write_bytes(b"previous")

    def half_then_interrupt(out, data):
        # Half the file is on disk when the failure (or Ctrl-C) comes.
        out.write_scanlines(0, data.shape[0] // 2, 0, data[: data.shape[0] // 2])
        raise KeyboardInterrupt

    _patch_image_output(monkeypatch, half_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        write_image(target, _image())
    # The old file is untouched and no temporary file is left behind.
    assert target.read_bytes() == b"previous"
    assert sorted(os.listdir(tmp_path)) == ["out.exr"]


def test_write_failure_from_the_library_is_an_error_and_leaves_nothing(tmp_path, monkeypatch):
    _patch_image_output(monkeypatch, lambda out, data: False, error="disk full")
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
        assert im.info["duration"] == 100 and im.info["loop"] == 0
        for i in range(4):  # each frame its own palette: close to the 8-bit sRGB frame
            im.seek(i)
            got = np.asarray(im.convert("RGB"), np.float32)
            assert np.abs(got - to_display(frames[i])).mean() < 12
    assert sorted(os.listdir(tmp_path)) == ["a.gif"]
    with pytest.raises(ValueError, match="not a .gif"):
        write_gif(tmp_path / "a.png", frames)
    with pytest.raises(ValueError, match="no frames"):
        write_gif(tmp_path / "b.gif", iter([]))


@pytest.mark.parametrize("name", ["a.gif", "a.mp4"])
def test_animations_stream_from_a_generator(tmp_path, name):
    # A generator is written frame by frame (a long animation never in memory whole):
    # the same file as from the stacked array; a bad frame midway leaves no file.
    write = write_gif if name.endswith(".gif") else write_video
    frames = _smooth_frames(5, 16, 24)
    seen = []

    def gen():
        for f in frames:
            seen.append(len(seen))
            yield f

    a, b = write(tmp_path / name, frames, fps=8), write(tmp_path / f"g{name}", gen(), fps=8)
    assert a.read_bytes() == b.read_bytes() and seen == [0, 1, 2, 3, 4]
    bad = (f if i < 3 else f[:8] for i, f in enumerate(frames))
    with pytest.raises(ValueError, match="differs from the first"):
        write(tmp_path / f"bad{name}", bad)
    assert sorted(os.listdir(tmp_path)) == sorted([name, f"g{name}"])


def _smooth_frames(n, h, w):
    """Smooth colour gradients that drift from frame to frame: what a video codec keeps
    to a few levels (no detail finer than its 4:2:0 chroma)."""
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w], np.float32)[:, None, None]
    frames = [
        0.15 + 0.6 * np.stack([x, y, 0.5 + 0.25 * np.sin(2 * np.pi * (x + y + i / n))], -1) ** 2
        for i in range(n)
    ]
    return np.stack(frames).astype(np.float32)


def _decode(path):
    """A video read back with PyAV: (stream facts, decoded frames as sRGB uint8), decoded
    the way the file is tagged (BT.709 matrix, limited range)."""
    av = pytest.importorskip("av")
    with av.open(str(path)) as c:
        s = c.streams.video[0]
        cc = s.codec_context
        facts = {
            "codec": cc.name, "pix_fmt": cc.pix_fmt, "fps": s.average_rate,
            "size": (s.width, s.height), "colorspace": cc.colorspace, "range": cc.color_range,
            "trc": cc.color_trc, "duration": float(s.duration * s.time_base),
        }  # fmt: skip
        frames = [
            f.to_ndarray(format="rgb24", src_colorspace="itu709", src_color_range="MPEG")
            for f in c.decode(s)
        ]
    return facts, np.stack(frames)


@pytest.mark.parametrize("codec", ["libx264", "mpeg4"])
def test_mp4_video(tmp_path, monkeypatch, codec):
    av = pytest.importorskip("av")
    if codec == "mpeg4":  # the fallback for an FFmpeg without libx264
        real = av.codec.Codec

        def without_x264(name, mode="r"):
            if name == "libx264":
                raise av.codec.codec.UnknownCodecError(name)
            return real(name, mode)

        monkeypatch.setattr(av.codec, "Codec", without_x264)
    frames = _smooth_frames(6, 48, 64)
    p = write_video(tmp_path / "a.mp4", frames, fps=12, exposure=0.5)
    assert sorted(os.listdir(tmp_path)) == ["a.mp4"]
    facts, got = _decode(p)
    assert facts["codec"] == {"libx264": "h264", "mpeg4": "mpeg4"}[codec]
    assert facts["pix_fmt"] == "yuv420p" and facts["size"] == (64, 48)
    assert facts["fps"] == 12 and facts["duration"] == pytest.approx(0.5)
    assert (facts["colorspace"], facts["range"], facts["trc"]) == (1, 1, 13)  # BT.709, sRGB
    assert got.shape == (6, 48, 64, 3)
    # Every decoded frame is its own sRGB frame (exposure applied) to within codec error:
    # a mean of 2.0 to 2.3 levels of 255 measured (libx264 CRF 18 and mpeg4 q2, PyAV 18.1;
    # mostly the 4:2:0 chroma, which alone costs 1.3 to 1.7 on such gradients).
    for i in range(6):
        want = to_display(frames[i], exposure=0.5).astype(int)
        err = np.abs(got[i].astype(int) - want).mean()
        assert err < 5, (i, err)
        # ... and not another frame's, nor the frame without the exposure.
        assert np.abs(got[i].astype(int) - to_display(frames[i]).astype(int)).mean() > 10
        other = to_display(frames[(i + 3) % 6], exposure=0.5).astype(int)
        assert np.abs(got[i].astype(int) - other).mean() > 10


def test_mp4_odd_size_is_padded_with_the_last_row_and_column(tmp_path):
    av = pytest.importorskip("av")
    frames = _smooth_frames(3, 47, 63)
    frames[:, -1, :] = [0.9, 0.1, 0.1]  # a red last row and a blue last column, which
    frames[:, :, -1] = [0.1, 0.1, 0.9]  # the padding repeats (black padding would not)
    path = write_video(tmp_path / "odd.mp4", frames, fps=5)
    facts, got = _decode(path)
    assert facts["size"] == (64, 48) and got.shape == (3, 48, 64, 3) and facts["fps"] == 5
    want = to_display(frames[0]).astype(int)
    assert np.abs(got[0, :45, :61].astype(int) - want[:45, :61]).mean() < 5  # measured 2.1
    # The padding, in the luma plane (full resolution): the padded row (column) is the
    # last one again, to within 1 level measured; black padding differs by > 80.
    with av.open(str(path)) as c:
        luma = np.stack([f.to_ndarray()[:48] for f in c.decode(video=0)]).astype(int)
    assert np.abs(luma[:, 47, :63] - luma[:, 46, :63]).mean() < 3
    assert np.abs(luma[:, :47, 63] - luma[:, :47, 62]).mean() < 3
    facts, got = _decode(write_video(tmp_path / "one.mp4", np.full((1, 1, 1, 3), 0.5)))
    assert facts["size"] == (2, 2) and got.shape == (1, 2, 2, 3)
    assert np.abs(got.astype(int) - to_display(np.float32(0.5))).max() <= 3


def test_mp4_write_is_atomic_on_interrupt_and_failure(tmp_path, monkeypatch):
    av = pytest.importorskip("av")
    target = tmp_path / "v.mp4"
    target.write_bytes(b"previous")
    real = av.VideoFrame
    calls = []

    class Failing:  # PyAV's frames, failing at the fourth (`error` is set below)
        @staticmethod
        def from_ndarray(array, **kw):
            calls.append(sorted(os.listdir(tmp_path)))
            if len(calls) == 4:  # mid-video: the container is open, frames are encoded
                raise error
            return real.from_ndarray(array, **kw)

    monkeypatch.setattr(av, "VideoFrame", Failing)
    for error in (KeyboardInterrupt(), OSError("disk full")):
        calls.clear()
        with pytest.raises(type(error)):
            write_video(target, _smooth_frames(6, 16, 16))
        assert len(calls[-1]) == 2  # the temporary file existed when the failure came
        # The old file is untouched and no temporary file is left behind.
        assert target.read_bytes() == b"previous"
        assert sorted(os.listdir(tmp_path)) == ["v.mp4"]


def test_mp4_bad_input(tmp_path):
    frames = _smooth_frames(2, 8, 8)
    with pytest.raises(ValueError, match="not a .mp4"):
        write_video(tmp_path / "a.gif", frames)
    with pytest.raises(ValueError, match="unsupported extension '.avi'"):
        write_video(tmp_path / "a.avi", frames)
    for bad in (frames[0], frames[..., :2], np.zeros((0, 8, 8, 3)), np.zeros((2, 8, 0, 3))):
        with pytest.raises(ValueError, match=r"not \((N, )?H, W, 3\)"):
            write_video(tmp_path / "a.mp4", bad)
    with pytest.raises(ValueError, match="dtype"):
        write_video(tmp_path / "a.mp4", np.full((1, 2, 2, 3), "x"))
    for fps in (0, -1, 1e-4, 1001, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="fps"):
            write_video(tmp_path / "a.mp4", frames, fps=fps)
    with pytest.raises(ValueError, match="exposure"):
        write_video(tmp_path / "a.mp4", frames, exposure=float("nan"))
    with pytest.raises(ValueError, match="write_video"):
        write_image(tmp_path / "a.mp4", frames[0])
    assert os.listdir(tmp_path) == []


def test_mp4_without_pyav_names_the_extra(tmp_path, monkeypatch):
    # (`jaxlens animate -o x.mp4` makes the same check before rendering: test_cli_render.)
    monkeypatch.setitem(sys.modules, "av", None)  # `import av` raises ImportError
    with pytest.raises(ImportError, match=r"jaxlens-bh\[video\]") as e:
        write_video(tmp_path / "a.mp4", _smooth_frames(2, 8, 8))
    assert isinstance(e.value, ValueError) and e.value.name == "av"
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("name", ["a.png", "a.exr", "a.gif"])
def test_written_files_get_the_usual_permissions(tmp_path, name):
    """The temporary file is private (mkstemp, 0600); the result has the mode a plain
    open() would give it under the process's umask, so others can read a render."""
    mask = os.umask(0o022)
    try:
        frames = np.full((2, 4, 6, 3), 0.5, np.float32)
        path = tmp_path / name
        if name.endswith(".gif"):
            write_gif(path, frames)
        else:
            write_image(path, frames[0])
        assert stat.S_IMODE(path.stat().st_mode) == 0o644
    finally:
        os.umask(mask)
