"""Image files and animated GIFs through OpenImageIO, MP4 videos through
PyAV (the optional `video` extra): plain Python at the edges, never jitted.

Every file is written atomically: to a hidden temporary file in the destination
folder, which is renamed over the destination (`os.replace`) only once it is complete,
and removed on any failure, Ctrl-C included. A reader never sees a half-written file.
A process killed outright (SIGKILL, power loss) cannot remove its temporary file: the
name, `.NAME.jaxlens-tmp.HOST.PID.RANDOM.EXT`, says whose it was, and the next write
to the same destination (or `jaxlens clean FOLDER`) removes those of processes of this
host that no longer run.
"""

import contextlib
import fractions
import glob
import io
import itertools
import math
import os
import re
import shutil
import socket
import tempfile
from pathlib import Path

import numpy as np

FLOAT_FORMATS = {".exr", ".hdr", ".tif", ".tiff"}
DISPLAY_FORMATS = {".png", ".jpg", ".jpeg"}
WRITE_FORMATS = FLOAT_FORMATS | DISPLAY_FORMATS
ANIMATION_FORMATS = {".gif", ".mp4"}


class MissingExtraError(ImportError, ValueError):
    """An optional dependency is not installed; the message names the extra to install.
    A `ValueError` too, so the command line reports it as one line."""


# Where native modules load: a context in which a signal cannot interrupt their set-up,
# where an exception cannot pass and a Ctrl-C aborted the process ("Critical nanobind
# error"). The command line sets one that ends the command at once, as while JAX loads.
native_import = contextlib.nullcontext


def _oiio():
    with native_import():
        import OpenImageIO as oiio

    return oiio


_PNG_SUB, _PNG_UP = 0x10, 0x20  # libpng's PNG_FILTER_SUB and PNG_FILTER_UP


def prepare_write(path) -> None:
    """Load what a first `write_image` to `path` needs (OpenImageIO, its plugin for the
    file's format, NumPy's transfer-function loops), without writing: 0.05-0.07 s of a
    first write, done while a render compiles (`_util.when_idle`)."""
    _oiio().ImageOutput.create(str(path))  # loads the format's plugin; nothing opened
    to_display(np.zeros((1, 1, 3), np.float32))


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) on linear values, clipped to [0, 1]
    (NaN to 0). Plain NumPy, not traceable.

    **Returns:** encoded values in [0, 1], float32, of the shape of `linear`.
    """
    x = np.clip(np.nan_to_num(np.asarray(linear, np.float32), nan=0.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray, dtype=np.float32) -> np.ndarray:
    """Inverse of `srgb_encode`: sRGB-encoded values in [0, 1] to linear. Plain NumPy.

    **Returns:** linear values in `dtype` (float32 unless given), of the shape of
    `encoded`.
    """
    x = np.asarray(encoded, dtype)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(dtype)


def to_display(image: np.ndarray, *, exposure: float = 0.0) -> np.ndarray:
    """Linear radiance to 8-bit sRGB for display: scale by $2^{exposure}$, clip, encode.

    **Returns:** `uint8` array of the same shape.
    """
    img = np.asarray(image)
    out = np.empty(img.shape, np.uint8)
    src, dst = img.reshape(-1), out.reshape(-1)  # views of contiguous arrays
    scale = np.float32(2.0**exposure)
    # In pieces of 2^20 values: the float temporaries of the transfer stay a few MB
    # (whole-image temporaries held five float32 copies of an 8192 x 8192 render).
    step = 1 << 20
    for i in range(0, src.size, step):
        piece = np.asarray(src[i : i + step], np.float32) * scale
        dst[i : i + step] = np.round(srgb_encode(piece) * 255.0)
    return out


def available_memory() -> int | None:
    """Bytes of memory the system can give a process now (Linux `MemAvailable`; else
    the physical memory), `None` where neither is known."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


# What a render needs besides its float32 output: the compiled block's workspace
# (a few hundred MB, `block_memory`) and the 8-bit copy a PNG/JPEG/GIF is written from.
RENDER_WORKSPACE = 512 << 20


def _check_memory(need: int, what: str, advice: str = "") -> None:
    """`ValueError` "`what` about N GiB and M GiB is available`advice`" when `need`
    bytes exceed `available_memory()` (not checked where that is unknown)."""
    have = available_memory()
    if have is not None and need > have:
        raise ValueError(f"{what} about {need / 2**30:.1f} GiB and {have / 2**30:.1f} GiB is "
                         f"available{advice}")  # fmt: skip


def check_render_memory(width: int, height: int, frames: int = 1) -> None:
    """`ValueError` with the numbers when a render of `frames` images of `width` x
    `height` pixels (float32 RGB, kept until written) and its 8-bit copy would not fit
    in the memory available, before anything is allocated."""
    _check_memory(frames * width * height * 3 * (4 + 1) + RENDER_WORKSPACE,
                  f"{frames} x {width} x {height} pixels need",
                  " (float32 RGB and an 8-bit copy): render a smaller size or fewer "
                  "frames")  # fmt: skip


def check_output_path(path) -> Path:
    """Check that `path` can be written: a supported image extension and an existing,
    writable folder. Raises `ValueError` naming the path otherwise.

    **Returns:** `path` as a `Path`.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in WRITE_FORMATS | ANIMATION_FORMATS:
        valid = ", ".join(sorted(WRITE_FORMATS | ANIMATION_FORMATS))
        raise ValueError(f"output {str(path)!r} has an unsupported extension {ext!r}; use one of "
                         f"{valid}")  # fmt: skip
    folder = path.parent
    if not folder.is_dir():
        raise ValueError(f"output folder {str(folder)!r} of {str(path)!r} does not exist")
    if path.is_dir():
        raise ValueError(f"output {str(path)!r} is a folder, not a file name")
    try:  # the real test of writability (also on read-only mounts, and for root)
        fd, probe = tempfile.mkstemp(prefix=".jaxlens-probe.", dir=folder)
    except OSError as e:
        raise ValueError(f"output folder {str(folder)!r} is not writable: {e.strerror}") from None
    os.close(fd)
    os.unlink(probe)
    return path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_TMP_TAG = ".jaxlens-tmp."


def _host() -> str:
    return "".join(c if c.isalnum() or c == "-" else "-" for c in socket.gethostname()) or "-"


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, owned by another user
        return True
    return True


def stale_temporaries(folder, stem: str | None = None) -> list[Path]:
    """This library's temporary files in `folder` (of destination stem `stem`, if given)
    left by processes of this host that no longer run."""
    host = _host()
    out = []
    pattern = f".{glob.escape(stem) if stem is not None else '*'}{_TMP_TAG}{host}.*"
    for p in Path(folder).glob(pattern):
        parts = p.name.rsplit(_TMP_TAG, 1)[1].split(".")
        if len(parts) >= 3 and parts[0] == host and parts[1].isdigit():
            if int(parts[1]) != os.getpid() and not _running(int(parts[1])):
                out.append(p)
    return sorted(out)


def remove_temporary(path: Path) -> None:
    """Remove a temporary file, or a temporary folder of frames, quietly."""
    with contextlib.suppress(OSError):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()


@contextlib.contextmanager
def atomic_output(path):
    """Context manager: yields a temporary path beside `path`; on a normal exit it
    is renamed to `path`, on any exception (KeyboardInterrupt too) it is removed.
    Temporaries of `path` left by killed processes are removed first."""
    path = Path(path)
    for stale in stale_temporaries(path.parent, path.stem):
        remove_temporary(stale)
    prefix = f".{path.stem}{_TMP_TAG}{_host()}.{os.getpid()}."
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        # mkstemp makes the file private (0600); give it the mode a plain open() would.
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _for_format(img: np.ndarray, ext: str) -> np.ndarray:
    """Adapt the channel count to what the format stores: HDR (RGBE) holds RGB only,
    JPEG grey or RGB; PNG, EXR and TIFF take 1 to 4 channels as they are."""
    c = img.shape[-1]
    if ext == ".hdr" or ext in (".jpg", ".jpeg"):
        if c == 2:  # grey + alpha
            img = img[..., :1]
        elif c == 4:  # RGBA
            img = img[..., :3]
        if ext == ".hdr" and img.shape[-1] == 1:
            img = np.repeat(img, 3, axis=-1)
    return img


def write_image(path, image: np.ndarray, *, exposure: float = 0.0) -> Path:
    """Write a linear float image, atomically (a temporary file, then a rename).

    EXR, HDR and TIFF keep the linear floats as they are (32-bit float; HDR is RGBE);
    PNG and JPEG get the exposure ($2^{exposure}$), the sRGB transfer and 8 bits.
    Never leaves a half-written file, also when interrupted.

    **Arguments:** `path` (its extension picks the format); `image`: `(H, W)` or
    `(H, W, C)` linear radiance with 1 to 4 channels; `exposure`: stops (PNG/JPEG).

    **Returns:** the path written. Raises `ValueError` for an unusable path or image.
    """
    oiio = _oiio()
    path = check_output_path(path)
    ext = path.suffix.lower()
    if ext == ".gif":
        raise ValueError(f"{str(path)!r}: write GIF animations with write_gif")
    if ext == ".mp4":
        raise ValueError(f"{str(path)!r}: write MP4 videos with write_video")
    img = np.asarray(image, np.float32)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[-1] not in (1, 2, 3, 4) or min(img.shape[:2]) < 1:
        raise ValueError(f"image of shape {img.shape} is not (H, W) or (H, W, 1..4)")
    if not np.isfinite(exposure):
        raise ValueError(f"exposure={exposure!r} must be finite (stops)")
    img = _for_format(img, ext)
    c = img.shape[-1]
    alpha = c in (2, 4)
    if ext in FLOAT_FORMATS:
        data, fmt, space = np.ascontiguousarray(img), oiio.FLOAT, "lin_rec709"
    elif alpha:
        # Linear colour with associated (premultiplied) alpha -> the file's convention:
        # unassociated sRGB colour, linear alpha, 8 bits.
        a = np.clip(img[..., -1:], 0.0, 1.0)
        colour = np.where(a > 0, img[..., :-1] / np.where(a > 0, a, 1.0), 0.0)
        data = np.concatenate([to_display(colour, exposure=exposure),
                               np.round(a * 255.0).astype(np.uint8)], axis=-1)  # fmt: skip
        fmt, space = oiio.UINT8, "sRGB"
    else:
        data, fmt, space = to_display(img, exposure=exposure), oiio.UINT8, "sRGB"
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    if c == 2:
        spec.channelnames = ("Y", "A")
        spec.alpha_channel = 1
    if alpha and fmt == oiio.UINT8:
        spec.attribute("oiio:UnassociatedAlpha", 1)  # written as given, not divided again
    spec.attribute("oiio:ColorSpace", space)
    spec.attribute("Software", "jaxlens")
    # zlib level 3, not 6: a 960 x 540 render written in 0.05 s instead of 0.13 s, the
    # file 10 % larger. Rows filtered by the better of libpng's "sub" and "up" filters,
    # not of all five: its encoding 27 ms instead of 36 ms, the file as large.
    spec.attribute("png:compressionLevel", 3)
    spec.attribute("png:filter", _PNG_SUB | _PNG_UP)
    with atomic_output(path) as tmp:
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise ValueError(f"cannot write images of type {ext!r}: {oiio.geterror()}")
        ok = out.open(tmp, spec) and out.write_image(data)
        ok = out.close() and ok
        if not ok:
            raise OSError(f"writing {str(path)!r} failed: {out.geterror() or oiio.geterror()}")
    return path


# GIF stores a frame's time as a 16-bit count of centiseconds: at most 655.35 s.
GIF_MIN_FPS = 1.0 / 655.35
VIDEO_FPS = (1e-3, 1000.0)


def check_fps(fps, video: bool) -> None:
    """`ValueError` unless `fps` (frames a second) is a rate the format can store: GIF from
    1/655.35 (a frame's time is at most 655.35 s) to 1000, MP4 from 0.001 to 1000."""
    lo, hi = VIDEO_FPS if video else (GIF_MIN_FPS, 1000.0)
    if not lo <= fps <= hi:  # NaN too
        kind = "an MP4" if video else "a GIF"
        raise ValueError(f"fps={fps!r} is not valid for {kind}: expected a number in "
                         f"[{lo:.4g}, {hi:g}] frames a second")  # fmt: skip


_FRAME_NAME = re.compile(r"frame_[0-9]{4,}\.(png|jpg|exr|hdr)")


@contextlib.contextmanager
def frame_folder(folder, fmt: str = "png"):
    """Context manager for an animation's frame files: yields `save(i, image, *,
    exposure)`. Frames go to a hidden folder inside `folder` and are moved in only when
    the block ends normally, replacing the `frame_NNNN.*` files of an earlier run (none
    of theirs is left beside the new ones); on any exception, Ctrl-C included, the new
    frames are removed and `folder` is as it was. `folder=None`: `save` does nothing.
    """
    if folder is None:
        yield lambda i, image, *, exposure=0.0: None
        return
    folder = Path(folder)
    made = not folder.exists()
    folder.mkdir(exist_ok=True)
    staging = None
    try:
        check_output_path(folder / f"frame_0000.{fmt}")
        for stale in stale_temporaries(folder, "frames"):
            remove_temporary(stale)
        prefix = f".frames{_TMP_TAG}{_host()}.{os.getpid()}."
        staging = Path(tempfile.mkdtemp(prefix=prefix, dir=folder))
        names = []

        def save(i, image, *, exposure=0.0):
            names.append(f"frame_{i:04d}.{fmt}")
            write_image(staging / names[-1], image, exposure=exposure)

        yield save
        for name in names:
            os.replace(staging / name, folder / name)
        keep = set(names)
        for old in folder.iterdir():
            if _FRAME_NAME.fullmatch(old.name) and old.name not in keep:
                old.unlink(missing_ok=True)
        made = False
    finally:
        if staging is not None:
            remove_temporary(staging)
        if made:
            with contextlib.suppress(OSError):
                folder.rmdir()


def _frames(frames):
    """`frames` as `(shape, iterator of checked frames)`: an `(N, H, W, 3)` array or any
    iterable of `(H, W, 3)` frames (a generator streams them: a long animation need not
    be in memory). Each frame is checked as it comes: real numbers, of the first's shape.
    Raises `ValueError` for no frame or a bad one."""
    if hasattr(frames, "shape") and hasattr(frames, "dtype"):
        arr = np.asarray(frames)
        if arr.ndim != 4 or arr.shape[0] < 1:
            raise ValueError(f"frames of shape {arr.shape} are not (N, H, W, 3) with N >= 1")
        frames = iter(arr)
    else:
        frames = iter(frames)
    try:
        first = _check_frame(next(frames))
    except StopIteration:
        raise ValueError("no frames to write") from None
    rest = (_check_frame(f, first.shape) for f in frames)
    return first.shape, itertools.chain([first], rest)


def _check_frame(frame, shape=None) -> np.ndarray:
    f = np.asarray(frame)
    if not np.issubdtype(f.dtype, np.number) or np.iscomplexobj(f):
        raise ValueError(f"frames of dtype {f.dtype} are not real numbers")
    if f.ndim != 3 or f.shape[-1] != 3 or min(f.shape) < 1:
        raise ValueError(f"a frame of shape {f.shape} is not (H, W, 3) with H, W >= 1")
    if shape is not None and f.shape != shape:
        raise ValueError(f"a frame of shape {f.shape} differs from the first, {shape}")
    return f


def _gif_delay(fps: float) -> int:
    """A GIF frame's time in centiseconds (what the format stores), at least 2: browsers
    show shorter delays as 0.1 s."""
    return max(int(round(100.0 / fps)), 2)


def write_gif(path, frames, *, exposure: float = 0.0, fps: float = 12.0, loop: int = 0) -> Path:
    """Write an animated GIF of linear frames (OpenImageIO), atomically, one frame at a
    time: a generator of frames is written as it yields, never held in memory whole.

    Each frame gets the exposure ($2^{exposure}$), the sRGB transfer and 8 bits, then
    its own 256-colour palette.

    **Arguments:** `path` (.gif); `frames`: `(N, H, W, 3)` linear radiance, or an
    iterable of `(H, W, 3)` frames; `exposure` (stops); `fps`: frames a second
    (GIF keeps a frame's time in whole centiseconds, at least 2); `loop`: 0 loops
    forever, else the number of plays.

    **Returns:** the path written. Raises `ValueError` for an unusable path, frames,
    exposure or fps. Never leaves a half-written file, also when interrupted.
    """
    path = check_output_path(path)
    if path.suffix.lower() != ".gif":
        raise ValueError(f"{str(path)!r} is not a .gif file name")
    if not math.isfinite(exposure):
        raise ValueError(f"exposure={exposure!r} must be finite (stops)")
    check_fps(fps, video=False)
    shape, frames = _frames(frames)
    oiio = _oiio()
    with atomic_output(path) as tmp:
        out = oiio.ImageOutput.create(tmp)
        spec = oiio.ImageSpec(shape[1], shape[0], 3, oiio.UINT8)
        spec.attribute("FramesPerSecond", oiio.TypeDesc("rational"), (100, _gif_delay(fps)))
        spec.attribute("gif:LoopCount", int(loop))
        mode = "create"
        try:
            for frame in frames:
                if not out.open(tmp, spec, mode):
                    raise OSError(f"cannot write {str(path)!r}: {out.geterror()}")
                mode = "AppendSubimage"
                img = to_display(frame, exposure=exposure)
                if not out.write_image(np.ascontiguousarray(img)):
                    raise OSError(f"cannot write {str(path)!r}: {out.geterror()}")
        finally:
            out.close()
    return path


def _av():
    """PyAV, imported on first use: the optional `video` extra."""
    try:
        with native_import():
            import av
    except ImportError as e:
        raise MissingExtraError(
            "writing MP4 video needs PyAV: pip install 'jaxlens[video]' (or pip install av)",
            name="av",
        ) from e
    return av


def require_video() -> None:
    """Check that MP4 video can be written (PyAV is installed); raises
    `MissingExtraError` naming the extra to install otherwise."""
    _av()


def _video_codec(av) -> str:
    """The encoder: H.264 (`libx264`, in PyAV's binary wheels) or, in an FFmpeg built
    without it, MPEG-4 Part 2 (`mpeg4`, always built in)."""
    try:
        av.codec.Codec("libx264", "w")
    except Exception:  # av.codec.codec.UnknownCodecError, or an FFmpeg without x264
        return "mpeg4"
    return "libx264"


def write_video(path, frames, *, exposure: float = 0.0, fps: float = 12.0) -> Path:
    """Write an MP4 video of linear frames (PyAV), atomically.

    The frames get the exposure ($2^{exposure}$), the sRGB transfer and 8 bits, as
    for `write_gif`, and are encoded as H.264 (`libx264`, constant quality CRF 18,
    close to visually lossless) in 4:2:0 YUV (`yuv420p`, BT.709 limited range, tagged
    so): the format every player and browser plays. Where the FFmpeg inside PyAV
    lacks libx264 (PyAV's binary wheels have it), the encoder is `mpeg4` (MPEG-4 Part
    2, fixed quantiser 2). 4:2:0 needs an even width and height: an odd width (height)
    is padded by repeating the last column (row), so the video is then one pixel wider
    (taller) than the frames. PyAV is the optional `video` extra
    (`pip install 'jaxlens[video]'`); without it this raises `MissingExtraError`
    (an `ImportError` and a `ValueError`) saying so.

    **Arguments:** `path` (.mp4); `frames`: `(N, H, W, 3)` linear radiance, or an
    iterable of `(H, W, 3)` frames, encoded as they come (a generator streams them);
    `exposure` (stops); `fps`: frames a second, 0.001 to 1000 (kept as a fraction with a
    denominator up to 1001: 29.97 is 2997/100).

    **Returns:** the path written. Raises `ValueError` for an unusable path, frames,
    exposure or fps. Never leaves a half-written file, also when interrupted.
    """
    path = check_output_path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"{str(path)!r} is not a .mp4 file name")
    if not math.isfinite(exposure):
        raise ValueError(f"exposure={exposure!r} must be finite (stops)")
    check_fps(fps, video=True)
    (h, w, _), frames = _frames(frames)
    av = _av()
    codec = _video_codec(av)
    pad = ((0, h % 2), (0, w % 2), (0, 0))
    rate = fractions.Fraction(fps).limit_denominator(1001)
    with atomic_output(path) as tmp:
        with av.open(tmp, "w", format="mp4", container_options={"movflags": "+faststart"}) as c:
            options = {"crf": "18"} if codec == "libx264" else {"qmin": "2", "qmax": "2"}
            stream = c.add_stream(codec, rate=rate, options=options)
            stream.width, stream.height = w + w % 2, h + h % 2
            stream.pix_fmt = "yuv420p"
            cc = stream.codec_context
            cc.colorspace = cc.color_primaries = 1  # BT.709 matrix; primaries as sRGB's
            cc.color_trc = 13  # IEC 61966-2-1, the sRGB transfer the data has
            cc.color_range = 1  # limited ("MPEG", 16-235)
            if codec == "mpeg4":
                cc.bit_rate = 100_000_000  # a cap only: the fixed quantiser decides
            for i, f in enumerate(frames):
                rgb = np.pad(to_display(f, exposure=exposure), pad, mode="edge")
                frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
                frame = frame.reformat(format="yuv420p", dst_colorspace="itu709",
                                       dst_color_range="MPEG")  # fmt: skip
                frame.pts = i
                c.mux(stream.encode(frame))
            c.mux(stream.encode(None))  # flush the encoder
    return path


def png_bytes(image: np.ndarray, *, exposure: float = 0.0) -> bytes:
    """Encode a linear image as PNG bytes (8-bit sRGB), for notebooks and widgets."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(to_display(image, exposure=exposure)).save(buf, format="PNG")
    return buf.getvalue()


def read_pixels(path, *, unassociated_alpha: bool = False) -> tuple[np.ndarray, dict]:
    """Every channel of an image file as stored, as float32 `(H, W, C)` (OpenImageIO;
    integer formats normalised to [0, 1], no colour-space decoding), and a dict of what
    the file says: `space` (colour space, lower case), `format`, `alpha` (the alpha
    channel's index, -1 if none) and `unassociated` (whether the colour is not
    multiplied by alpha; asked for with `unassociated_alpha`).

    Raises `ValueError` naming the file when it is missing, empty, not an image,
    truncated or otherwise unreadable, or too large for the memory available.
    """
    oiio = _oiio()
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"image file {str(path)!r} does not exist")
    if path.stat().st_size == 0:
        raise ValueError(f"image file {str(path)!r} is empty")
    config = oiio.ImageSpec()
    if unassociated_alpha:
        config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        msg = " ".join(oiio.geterror().split()) or "unknown format"
        raise ValueError(f"{str(path)!r} is not a readable image: {msg}")
    try:
        spec = inp.spec()
        # Refused before reading when its pixels and the copies its readers make (the
        # float32 read, the linear decode, the fit's float64: ~24 bytes a value) would
        # not fit: a small file can hold a huge image (a 1.5 MB PNG of 40000 x 40000).
        _check_memory(24 * spec.width * spec.height * spec.nchannels,
                      f"{str(path)!r} is {spec.width} x {spec.height} pixels x "
                      f"{spec.nchannels} channels: reading it needs")  # fmt: skip
        data = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        err = inp.geterror()
        info = {
            "space": str(spec.get_string_attribute("oiio:ColorSpace", "")).lower(),
            "format": str(spec.format),
            "alpha": spec.alpha_channel,
            "unassociated": bool(spec.get_int_attribute("oiio:UnassociatedAlpha", 0)),
        }
    finally:
        inp.close()
    if data is None or err:
        msg = " ".join((err or "no pixel data").split())
        raise ValueError(f"{str(path)!r} is not a readable image (truncated or corrupt?): {msg}")
    data = np.asarray(data, np.float32)
    if data.ndim == 2:
        data = data[..., None]
    if data.ndim != 3 or min(data.shape) < 1:
        raise ValueError(f"{str(path)!r} has pixel data of shape {data.shape}; expected 2-D")
    return data, info


def transfer_of(info) -> str:
    """How a file's stored values relate to linear light, from `read_pixels`' `info`:
    `"srgb"` for 8- and 16-bit files tagged sRGB or untagged (the default of PNG and
    JPEG; OpenImageIO reports both as sRGB), `"linear"` for float files and integer
    files tagged linear (e.g. a PNG whose gAMA chunk is 1.0)."""
    integer = info["format"].startswith(("uint", "int"))
    space = info["space"]
    return "srgb" if integer and ("srgb" in space or space == "") else "linear"


def read_image(path) -> np.ndarray:
    """Read an image file (any format OpenImageIO reads) as linear float32.

    8- and 16-bit files in sRGB (PNG, JPEG, ... as tagged by OpenImageIO, and untagged
    ones) are decoded to linear; float files (EXR, HDR, float TIFF) and integer files
    tagged linear are taken as linear already (`transfer_of`). Alpha,
    where present, is kept as a channel, and the colour is returned multiplied by it
    (associated alpha, the convention of linear images and of `write_image`).

    **Returns:** float32 `(H, W, C)`; raises `ValueError` naming the file when it is
    missing, not an image, truncated or otherwise unreadable.
    """
    data, info = read_pixels(path, unassociated_alpha=True)  # sRGB decoded before alpha
    alpha, unassociated = info["alpha"], info["unassociated"]
    colour = [i for i in range(data.shape[-1]) if i != alpha][:3]
    if transfer_of(info) == "srgb":
        data[..., colour] = srgb_decode(data[..., colour])
    if 0 <= alpha < data.shape[-1] and unassociated:
        data[..., colour] *= data[..., alpha : alpha + 1]  # associated (premultiplied)
    return data
