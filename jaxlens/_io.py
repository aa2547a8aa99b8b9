"""Image files and animated GIFs through OpenImageIO, MP4 videos through
PyAV (the optional `video` extra): plain Python at the edges, never jitted.

Every file is written atomically: to a hidden temporary file in the destination
folder, which is flushed to the disk (`fsync`) and renamed over the destination
(`os.replace`) only once it is complete, and removed on any failure, Ctrl-C included.
A reader never sees a half-written file, and a full disk leaves the old file as it was
("no space left on device writing NAME"). Every write is checked: images are encoded
in memory (Linux) and copied to the disk with checked writes, GIFs are read back to
their last byte, video errors come from FFmpeg.

While it writes, a process holds an advisory lock (`flock`) on its temporary file. A
process killed outright (SIGKILL, power loss) cannot remove its temporary file: the
name, `.NAME.jaxlens-tmp.HOST.PID.RANDOM.EXT`, says what it was, and the next write to
the same destination (or `jaxlens clean FOLDER`) removes those of this host's name
whose lock no process holds, whatever the PID says (a container's processes have ids
of their own).
"""

import contextlib
import errno
import fcntl
import fractions
import glob
import io
import itertools
import json
import mmap
import os
import re
import resource
import shutil
import socket
import sys
import tempfile
from pathlib import Path

import numpy as np

from ._messages import shown

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


# Exposures in stops, -100 < exposure < 100: 2^100 keeps float32 pixels finite (2^128
# is their largest power of two). Scene files and the command line accept the same.
EXPOSURE_MAX = 100.0


def check_exposure(exposure) -> float:
    """`exposure` (stops) as a float: `ValueError` unless a finite real number in
    (-EXPOSURE_MAX, EXPOSURE_MAX) = (-100, 100), `TypeError` for a string or complex."""
    valid = f"expected a number of stops in ({-EXPOSURE_MAX:g}, {EXPOSURE_MAX:g})"
    if isinstance(exposure, (str, bytes)) or np.iscomplexobj(exposure):
        raise TypeError(f"exposure={shown(exposure)} is not valid: {valid}")
    try:
        x = float(exposure)
    except (TypeError, ValueError):
        raise TypeError(f"exposure={shown(exposure)} is not valid: {valid}") from None
    if not -EXPOSURE_MAX < x < EXPOSURE_MAX:  # NaN too
        raise ValueError(f"exposure={shown(exposure)} is not valid: {valid}")
    return x


def _check_real(array: np.ndarray, what: str) -> np.ndarray:
    """`array` unless its values are not real numbers (complex, object, strings): then
    `ValueError` naming its dtype. Booleans are 0 and 1."""
    real = np.issubdtype(array.dtype, np.number) or array.dtype == np.bool_
    if not real or np.iscomplexobj(array):
        raise ValueError(f"{what} of dtype {array.dtype} is not valid: expected real numbers "
                         "(an integer, floating-point or boolean array)")  # fmt: skip
    return array


def to_display(image: np.ndarray, *, exposure: float = 0.0) -> np.ndarray:
    """Linear radiance to 8-bit sRGB for display: scale by $2^{exposure}$, clip, encode.

    **Arguments:** `image`: linear radiance, real numbers of any shape; `exposure`:
    stops, in (-100, 100).

    **Returns:** `uint8` array of the same shape. Raises `ValueError` for an exposure out
    of range or an image that is not real numbers (complex, object).
    """
    exposure = check_exposure(exposure)
    img = _check_real(np.asarray(image), "image")
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


def _first_int(path, key: str | None = None) -> int | None:
    """The number in a small system file (`key`'s value where given: the first number
    after `key` on its line); `None` where there is none (or "max")."""
    try:
        with open(path) as f:
            for line in f:
                words = line.split()
                if key is None or (words and words[0] == key):
                    return int(words[0 if key is None else 1])
    except (OSError, ValueError, IndexError):
        pass
    return None


def _cgroup_memory_left() -> int | None:
    """Bytes the process's cgroup may still take: its memory limit less what it uses,
    page cache that can be dropped not counted as used (the least over the group and
    those above it, cgroup v2; v1's memory controller), `None` without a limit."""
    lefts = []
    try:
        with open("/proc/self/cgroup") as f:
            groups = dict(line.rstrip("\n").split(":", 2)[1:] for line in f if line.count(":") >= 2)
    except (OSError, ValueError):
        groups = {}
    for root, ctrl, limit, usage, cache in (
        ("/sys/fs/cgroup", "", "memory.max", "memory.current", "inactive_file"),
        ("/sys/fs/cgroup/memory", "memory", "memory.limit_in_bytes", "memory.usage_in_bytes",
         "total_inactive_file"),
    ):  # fmt: skip
        if ctrl not in groups and not os.path.exists(f"{root}/{limit}"):
            continue
        folder = Path(root + groups.get(ctrl, "/"))
        for d in (folder, *folder.parents):
            if len(d.parts) < len(Path(root).parts):
                break
            cap = _first_int(d / limit)
            if cap is not None and cap < 1 << 60:  # v1 writes "no limit" as ~2^63
                used = _first_int(d / usage) or 0
                used -= _first_int(d / "memory.stat", cache) or 0
                lefts.append(max(cap - max(used, 0), 0))
    return min(lefts, default=None)


def memory_limit() -> tuple[int, str] | None:
    """The bytes of memory this process can still take, and what limits it: the least
    of the memory the system has available (Linux `MemAvailable`; else the physical
    memory), the address-space limit (`ulimit -v`, `RLIMIT_AS`) and the data limit
    (`RLIMIT_DATA`) less what the process has mapped, and its cgroup's limit less what
    the group uses (a container's). `None` where none is known."""
    found = []
    avail = _first_int("/proc/meminfo", "MemAvailable:")
    if avail is not None:
        found.append((avail * 1024, "available memory"))
    else:
        with contextlib.suppress(ValueError, OSError, AttributeError):
            found.append((os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"),
                          "physical memory"))  # fmt: skip
    for which, used, name in ((resource.RLIMIT_AS, "VmSize:", "address-space limit"),
                              (resource.RLIMIT_DATA, "VmData:", "data-size limit")):  # fmt: skip
        soft = resource.getrlimit(which)[0]
        if soft != resource.RLIM_INFINITY:
            mapped = (_first_int("/proc/self/status", used) or 0) * 1024
            found.append((max(soft - mapped, 0), name))
    left = _cgroup_memory_left()
    if left is not None:
        found.append((left, "cgroup memory limit"))
    return min(found) if found else None


def available_memory() -> int | None:
    """Bytes of memory this process can still take (`memory_limit`), `None` where that
    is not known."""
    limit = memory_limit()
    return None if limit is None else limit[0]


# What a render needs besides its float32 output: the compiled block's workspace
# (a few hundred MB, `block_memory`) and the 8-bit copy a PNG/JPEG/GIF is written from.
RENDER_WORKSPACE = 512 << 20


def _check_memory(need: int, what: str, advice: str = "") -> None:
    """`ValueError` "`what` about N GiB, and this process can take M GiB (WHY)`advice`"
    when `need` bytes exceed `available_memory()` (not checked where that is unknown;
    WHY: the limit that decides, `memory_limit`)."""
    have = available_memory()
    if have is not None and need > have:
        limit = memory_limit()
        why = limit[1] if limit is not None and limit[0] == have else "available memory"
        raise ValueError(f"{what} about {need / 2**30:.1f} GiB, and this process can take "
                         f"{have / 2**30:.1f} GiB ({why}){advice}")  # fmt: skip


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
_NEW_TAG = ".jaxlens-new."  # a temporary's name until its lock is held


def _host() -> str:
    return "".join(c if c.isalnum() or c == "-" else "-" for c in socket.gethostname()) or "-"


def _locked(path: Path) -> bool:
    """Whether a process holds the advisory lock (`flock`) of `path`, a file or folder
    (one that cannot be opened counts as locked: it is left alone)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW)
    except OSError:
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:  # BlockingIOError: held by a writer (ENOLCK: cannot know)
        return True
    finally:
        os.close(fd)  # (and with it the lock just taken)
    return False


def stale_temporaries(folder, stem: str | None = None) -> list[Path]:
    """This library's temporary files and frame folders in `folder` (of destination stem
    `stem`, if given) that no process is writing: a writer holds an advisory lock
    (`flock`) on its temporary while it writes, so one whose lock is free is stale,
    whatever the process id in its name says (a render in a container, another PID
    namespace, has the same host name and ids of its own). Only those named for this
    host: a lock need not reach other hosts on a network file system."""
    host = _host()
    out = []
    pattern = f".{glob.escape(stem) if stem is not None else '*'}{_TMP_TAG}{host}.*"
    for p in Path(folder).glob(pattern):
        parts = p.name.rsplit(_TMP_TAG, 1)[1].split(".")
        if len(parts) >= 3 and parts[0] == host and parts[1].isdigit() and not _locked(p):
            out.append(p)
    return sorted(out)


def remove_temporary(path: Path, *, quiet: bool = True) -> None:
    """Remove a temporary file, or a temporary folder of frames; an `OSError` (a
    read-only folder) is ignored unless `quiet=False`."""
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    except FileNotFoundError:
        pass
    except OSError:
        if not quiet:
            raise


def _locked_temporary(folder: Path, stem: str, suffix: str, directory: bool = False):
    """A new temporary file (or folder) `.STEM.jaxlens-tmp.HOST.PID.RANDOM SUFFIX` in
    `folder`, locked (`flock`) from before it has that name, so that no `clean` takes
    it for a killed process's. **Returns:** `(fd, path)`: the lock is held until `fd` is
    closed."""
    prefix = f".{stem}{_NEW_TAG}"
    if directory:
        new = tempfile.mkdtemp(prefix=prefix, suffix=suffix, dir=folder)
        fd = os.open(new, os.O_RDONLY)
    else:
        fd, new = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=folder)
    try:
        # (A file system without locks, ENOLCK: written all the same; `_locked` then
        # takes its temporaries for held, and nothing there is removed as stale.)
        with contextlib.suppress(OSError):
            fcntl.flock(fd, fcntl.LOCK_EX)
        rest = Path(new).name[len(prefix) :]  # RANDOM SUFFIX
        path = Path(folder) / f".{stem}{_TMP_TAG}{_host()}.{os.getpid()}.{rest}"
        os.rename(new, path)
    except BaseException:
        os.close(fd)
        remove_temporary(Path(new))
        raise
    return fd, path


def _write_failure(path, e: OSError) -> OSError:
    """An error of a write to `path` as a user reads it: "no space left on device
    writing PATH" (the `errno` kept) for a full disk or quota; others as they are."""
    reason = {errno.ENOSPC: "no space left on device", errno.EDQUOT: "disk quota exceeded",
              errno.EFBIG: "file too large for the file system"}.get(e.errno)  # fmt: skip
    if reason is None or str(e).startswith(reason):  # (said so already)
        return e
    err = OSError(f"{reason} writing {_shown(path)}")
    err.errno = e.errno
    return err


def _shown(path) -> str:
    """A path as messages show it: quoted, and cut to a readable length."""
    return shown(str(path))


@contextlib.contextmanager
def atomic_output(path):
    """Context manager: yields a temporary path beside `path`, locked (`flock`) while
    the block runs; on a normal exit the file is flushed to the disk (`fsync`) and
    renamed to `path`, on any exception (KeyboardInterrupt too) it is removed and `path`
    is as it was. Temporaries of `path` that no process holds are removed first.
    A full disk raises `OSError` "no space left on device writing PATH"."""
    path = Path(path)
    for stale in stale_temporaries(path.parent, path.stem):
        remove_temporary(stale)
    try:
        fd, tmp = _locked_temporary(path.parent, path.stem, path.suffix)
    except OSError as e:  # no inode left, too
        raise _write_failure(path, e) from e
    try:
        yield str(tmp)
        # mkstemp makes the file private (0600); give it the mode a plain open() would.
        os.chmod(tmp, 0o666 & ~_umask())
        _fsync(tmp)  # the data on the disk before the name: never a renamed empty file
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        failure = _write_failure(path, e) if isinstance(e, OSError) else e
        if failure is not e:
            raise failure from e
        raise
    finally:
        os.close(fd)


def _fsync(path) -> None:
    """Flush a file's data to the disk (a write error the disk reports only now, too)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _copy_in(src: int, path) -> None:
    """Write the bytes of the file `src` (a descriptor) to `path`, every write checked."""
    size, done = os.fstat(src).st_size, 0
    fd = os.open(path, os.O_WRONLY | os.O_TRUNC)
    try:
        while done < size:
            n = os.sendfile(fd, src, done, min(size - done, 1 << 30))
            if n == 0:  # (never for a regular file: an error is raised)
                raise OSError(errno.EIO, f"short write to {_shown(path)}")
            done += n
    finally:
        os.close(fd)


@contextlib.contextmanager
def _encoded_in_memory(path):
    """Context manager for a native writer that does not report every failed write
    (libpng's and libjpeg's, through OpenImageIO: a full disk left a truncated PNG and
    "success"; libjpeg ends the process): yields a file name to give the writer, in
    memory (Linux `memfd`), whose bytes are then written to `path` with checked
    writes. Where there is no `memfd`, yields `path` itself."""
    if not hasattr(os, "memfd_create") or not os.path.isdir("/proc/self/fd"):
        yield str(path)
        return
    fd = os.memfd_create("jaxlens-image")
    try:
        yield f"/proc/self/fd/{fd}"
        _copy_in(fd, path)
    finally:
        os.close(fd)


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


def write_image(
    path, image: np.ndarray, *, exposure: float = 0.0, sampling: str | None = None
) -> Path:
    """Write a linear float image, atomically (a temporary file, then a rename).

    EXR, HDR and TIFF keep the linear floats as they are (32-bit float; HDR is RGBE);
    PNG and JPEG get the exposure ($2^{exposure}$), the sRGB transfer and 8 bits.
    Never leaves a half-written file, also when interrupted.

    **Arguments:** `path` (its extension picks the format); `image`: `(H, W)` or
    `(H, W, C)` linear radiance with 1 to 4 channels, real numbers; `exposure`: stops,
    in (-100, 100) (applied to PNG/JPEG); `sampling`: how the pixels were sampled,
    `"point"` (one ray a pixel, at its centre) or `"area"` (averaged over the pixel),
    recorded as the attribute `jaxlens:sampling` (PNG and EXR keep it) for a fit that
    reads the file (`read_pixels`'s `sampling`).

    **Returns:** the path written. Raises `ValueError` for an unusable path, image or
    exposure, `OSError` when the file cannot be written ("no space left on device
    writing PATH"): the file at `path`, if any, is then as it was.
    """
    oiio = _oiio()
    path = check_output_path(path)
    ext = path.suffix.lower()
    if ext == ".gif":
        raise ValueError(f"{str(path)!r}: write GIF animations with write_gif")
    if ext == ".mp4":
        raise ValueError(f"{str(path)!r}: write MP4 videos with write_video")
    exposure = check_exposure(exposure)
    img = _check_real(np.asarray(image), "image").astype(np.float32, copy=False)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[-1] not in (1, 2, 3, 4) or min(img.shape[:2]) < 1:
        raise ValueError(f"image of shape {img.shape} is not (H, W) or (H, W, 1..4)")
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
    if sampling is not None:
        spec.attribute("jaxlens:sampling", str(sampling))
    # zlib level 3, not 6: a 960 x 540 render written in 0.05 s instead of 0.13 s, the
    # file 10 % larger. Rows filtered by the better of libpng's "sub" and "up" filters,
    # not of all five: its encoding 27 ms instead of 36 ms, the file as large.
    spec.attribute("png:compressionLevel", 3)
    spec.attribute("png:filter", _PNG_SUB | _PNG_UP)
    with atomic_output(path) as tmp, _encoded_in_memory(tmp) as name:
        out = oiio.ImageOutput.create(tmp)  # the plugin of the file name's extension
        if out is None:
            raise ValueError(f"cannot write images of type {ext!r}: {oiio.geterror()}")
        ok = out.open(name, spec) and out.write_image(data)
        # A failed write may be reported only here (libpng's: "success" and a message);
        # after `close` TIFF always reports a harmless one about its Exif data.
        error = out.geterror()
        ok = out.close() and ok and not error
        if not ok:
            error = " ".join((error or out.geterror() or oiio.geterror()).split())
            raise OSError(f"writing {_shown(path)} failed: {error[:500]}")
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

# The record of the frame files jaxlens wrote in a frames folder: only those are ever
# replaced or removed there, never a file whose name merely looks like a frame's.
FRAMES_MANIFEST = ".jaxlens-frames.json"


def _recorded_frames(folder: Path) -> set[str]:
    """The names of the frame files the last run recorded writing in `folder` (none
    where there is no readable record; only plain frame names: `frame_NNNN.EXT`)."""
    try:
        names = json.loads((folder / FRAMES_MANIFEST).read_text())["frames"]
    except (OSError, ValueError, KeyError, TypeError):
        return set()
    if not isinstance(names, list):
        return set()
    return {n for n in names if isinstance(n, str) and _FRAME_NAME.fullmatch(n)}


def _record_frames(folder: Path, names) -> None:
    with atomic_output(folder / FRAMES_MANIFEST) as tmp, open(tmp, "w") as f:
        json.dump({"written_by": "jaxlens", "frames": sorted(names)}, f, indent=0)


def _check_not_users(folder: Path, name: str, ours: set[str]) -> None:
    if name not in ours and os.path.lexists(folder / name):
        raise ValueError(f"frames folder {_shown(folder)} has a file {name!r} that jaxlens did "
                         f"not write there (it is not in its {FRAMES_MANIFEST}); it is left "
                         "as it is and nothing was written: move it away or choose another "
                         "folder")  # fmt: skip


@contextlib.contextmanager
def frame_folder(folder, fmt: str = "png"):
    """Context manager for an animation's frame files: yields `save(i, image, *,
    exposure)`, which writes `frame_NNNN.FMT` (`i` as NNNN; FMT: png, jpg, exr, hdr).

    Frames go to a hidden folder inside `folder` (locked while it is written) and are
    moved in only when the block ends normally. The names written are recorded in
    `folder`'s hidden `.jaxlens-frames.json`: the frames an earlier run recorded there
    are replaced, and those of them this run does not write again are removed; no other
    file is ever touched. A file of a new frame's name that jaxlens did not write (not
    in the record) is an error (`ValueError` naming it; nothing is written). On any
    exception, Ctrl-C included, the new frames are removed and `folder` is as it was.
    `folder=None`: `save` does nothing.
    """
    if folder is None:
        yield lambda i, image, *, exposure=0.0: None
        return
    folder = Path(folder)
    made = not folder.exists()
    folder.mkdir(exist_ok=True)
    staging = lock = None
    try:
        check_output_path(folder / f"frame_0000.{fmt}")
        ours = _recorded_frames(folder)
        for stale in stale_temporaries(folder, "frames"):
            remove_temporary(stale)
        lock, staging = _locked_temporary(folder, "frames", "", directory=True)
        names = []

        def save(i, image, *, exposure=0.0):
            name = f"frame_{i:04d}.{fmt}"
            _check_not_users(folder, name, ours)
            names.append(name)
            try:
                write_image(staging / name, image, exposure=exposure)
            except OSError as e:  # named as the frame, not as its hidden staging file
                if e.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
                    raise
                raise _write_failure(folder / name, OSError(e.errno, "")) from e

        yield save
        for name in names:  # (one may have come since its frame was rendered)
            _check_not_users(folder, name, ours)
        # The record lists the earlier frames and the new ones until the earlier are
        # gone: a run killed on the way leaves nothing of its own unrecorded.
        _record_frames(folder, ours | set(names))
        for name in names:
            os.replace(staging / name, folder / name)
        for old in sorted(ours - set(names)):
            (folder / old).unlink(missing_ok=True)
        _record_frames(folder, names)
        made = False
    finally:
        if staging is not None:
            remove_temporary(staging)
        if lock is not None:
            os.close(lock)
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
    f = _check_real(np.asarray(frame), "frames")
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
    forever, else the number of plays, up to 65535 (a 16-bit field).

    **Returns:** the path written. Raises `ValueError` for an unusable path, frames,
    exposure (stops, in (-100, 100)), fps or loop, `OSError` when the file cannot be
    written (a full disk: "no space left on device writing PATH"; the old file, if
    any, is then as it was). Never leaves a half-written file, also when interrupted.
    """
    path = check_output_path(path)
    if path.suffix.lower() != ".gif":
        raise ValueError(f"{str(path)!r} is not a .gif file name")
    exposure = check_exposure(exposure)
    check_fps(fps, video=False)
    if isinstance(loop, bool) or not isinstance(loop, (int, np.integer)) or not 0 <= loop <= 65535:
        raise ValueError(f"loop={shown(loop)} is not valid: expected a whole number "
                         "from 0 (loop forever) to 65535 (plays)")  # fmt: skip
    shape, frames = _frames(frames)
    oiio = _oiio()
    with atomic_output(path) as tmp:
        out = oiio.ImageOutput.create(tmp)
        spec = oiio.ImageSpec(shape[1], shape[0], 3, oiio.UINT8)
        spec.attribute("FramesPerSecond", oiio.TypeDesc("rational"), (100, _gif_delay(fps)))
        spec.attribute("gif:LoopCount", int(loop))
        mode, count = "create", 0
        try:
            for frame in frames:
                if not out.open(tmp, spec, mode):
                    raise OSError(f"cannot write {_shown(path)}: {out.geterror()}")
                mode = "AppendSubimage"
                img = to_display(frame, exposure=exposure)
                if not out.write_image(np.ascontiguousarray(img)):
                    raise OSError(f"cannot write {_shown(path)}: {out.geterror()}")
                count += 1
        finally:
            closed = out.close()
        if not closed:
            raise OSError(f"cannot write {_shown(path)}: {out.geterror()}")
        _check_gif(tmp, path, count)
    return path


def _check_gif(tmp, path, frames: int) -> None:
    """Read a GIF written by OpenImageIO back, block by block, to its trailer: `OSError`
    unless it is whole, with `frames` images (its GIF writer does not check its writes:
    a full disk left a truncated file and "success")."""
    with open(tmp, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
    try:
        pos, images = 13, 0
        if size < 14 or data[:3] != b"GIF":
            raise EOFError
        if data[10] & 0x80:  # a global colour table
            pos += 3 << ((data[10] & 7) + 1)
        while data[pos] != 0x3B:  # until the trailer
            if data[pos] == 0x21:  # an extension: its label, then sub-blocks
                pos += 2
            elif data[pos] == 0x2C:  # an image: its descriptor, colour table, LZW data
                flags, images = data[pos + 9], images + 1
                pos += 10 + (3 << ((flags & 7) + 1) if flags & 0x80 else 0) + 1
            else:
                raise EOFError
            while data[pos]:  # sub-blocks, to the empty one
                pos += data[pos] + 1
            pos += 1
        if pos + 1 != size or images != frames:
            raise EOFError
    except (EOFError, IndexError):
        err = OSError(f"writing {_shown(path)} failed: the GIF written is incomplete")
        with contextlib.suppress(OSError):
            disk = os.statvfs(tmp)
            if disk.f_bavail * disk.f_frsize < 1 << 20:  # full: the failed writes' cause
                err.errno = errno.ENOSPC
        raise err from None
    finally:
        if size:
            data.close()


def _av():
    """PyAV, imported on first use: the optional `video` extra."""
    try:
        with native_import():
            import av
    except ImportError as e:
        raise MissingExtraError(
            "writing MP4 video needs PyAV: pip install 'jaxlens-bh[video]' (or pip install av)",
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
    (`pip install 'jaxlens-bh[video]'`); without it this raises `MissingExtraError`
    (an `ImportError` and a `ValueError`) saying so.

    **Arguments:** `path` (.mp4); `frames`: `(N, H, W, 3)` linear radiance, or an
    iterable of `(H, W, 3)` frames, encoded as they come (a generator streams them);
    `exposure` (stops, in (-100, 100)); `fps`: frames a second, 0.001 to 1000 (kept as
    a fraction with a denominator up to 1001: 29.97 is 2997/100).

    **Returns:** the path written. Raises `ValueError` for an unusable path, frames,
    exposure or fps, `OSError` when the file cannot be written (a full disk: "no space
    left on device writing PATH"; the old file, if any, is then as it was). Never
    leaves a half-written file, also when interrupted.
    """
    path = check_output_path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"{str(path)!r} is not a .mp4 file name")
    exposure = check_exposure(exposure)
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
    """Encode a linear image as PNG bytes (8-bit sRGB), for notebooks and widgets.
    `exposure`: stops, in (-100, 100); `ValueError` for one out of range or an image
    that is not real numbers."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(to_display(image, exposure=exposure)).save(buf, format="PNG")
    return buf.getvalue()


@contextlib.contextmanager
def _native_stderr():
    """Context manager around a native reader that writes its errors to the process's
    stderr itself (libpng: "libpng error: ..." before jaxlens's own line): file
    descriptor 2 goes to a temporary file meanwhile. Yields a list whose one item is
    then what was written there (its first 64 KiB), for the caller to say or not."""
    said = [""]
    with contextlib.suppress(Exception):
        sys.stderr.flush()
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile() as f:
            os.dup2(f.fileno(), 2)
            try:
                yield said
            finally:
                os.dup2(saved, 2)
                f.seek(0)
                said[0] = f.read(1 << 16).decode(errors="replace")
    finally:
        os.close(saved)


def read_pixels(path, *, unassociated_alpha: bool = False) -> tuple[np.ndarray, dict]:
    """Every channel of an image file as stored, as float32 `(H, W, C)` (OpenImageIO;
    integer formats normalised to [0, 1], no colour-space decoding), and a dict of what
    the file says: `space` (colour space, lower case), `format`, `alpha` (the alpha
    channel's index, -1 if none), `unassociated` (whether the colour is not
    multiplied by alpha; asked for with `unassociated_alpha`), `tagged` (whether the
    file states its colour space: `colour_tag`) and `sampling` (how jaxlens sampled
    the pixels of a file it wrote, `write_image`'s `sampling`; "" where unrecorded).

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
    with _native_stderr() as said:
        inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        msg = " ".join((oiio.geterror() or said[0]).split()) or "unknown format"
        raise ValueError(f"{_shown(path)} is not a readable image: {msg[:500]}")
    warned = said[0]
    try:
        spec = inp.spec()
        # Refused before reading when its pixels and the copies its readers make (the
        # float32 read, the linear decode, the fit's float64: ~24 bytes a value) would
        # not fit: a small file can hold a huge image (a 1.5 MB PNG of 40000 x 40000).
        _check_memory(24 * spec.width * spec.height * spec.nchannels,
                      f"{_shown(path)} is {spec.width} x {spec.height} pixels x "
                      f"{spec.nchannels} channels: reading it needs")  # fmt: skip
        with _native_stderr() as said:
            data = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        err = inp.geterror()
        info = {
            "space": str(spec.get_string_attribute("oiio:ColorSpace", "")).lower(),
            "format": str(spec.format),
            "alpha": spec.alpha_channel,
            "unassociated": bool(spec.get_int_attribute("oiio:UnassociatedAlpha", 0)),
            "tagged": colour_tag(path, spec),
            "sampling": str(spec.get_string_attribute("jaxlens:sampling", "")),
        }
    finally:
        inp.close()
    if data is None or err:
        msg = " ".join((err or said[0] or "no pixel data").split())
        raise ValueError(f"{_shown(path)} is not a readable image (truncated or corrupt?): "
                         f"{msg[:500]}")  # fmt: skip
    if warned + said[0]:  # warnings of a file read well (libpng's of a colour profile)
        os.write(2, (warned + said[0]).encode())
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
    files tagged linear (e.g. a PNG whose gAMA chunk is 1.0). `info["tagged"]` says
    whether the file itself said so (`colour_tag`)."""
    integer = info["format"].startswith(("uint", "int"))
    space = info["space"]
    # A gamma-encoded file (a PNG's gAMA of 1/2.2: OpenImageIO's "g22_rec709_scene") is
    # decoded as sRGB, whose curve is within 0.009 of a 2.2 power's.
    gamma = space.startswith(("g22", "g18", "gamma"))
    return "srgb" if integer and ("srgb" in space or space == "" or gamma) else "linear"


# PNG chunks that state how the stored values relate to light (PNG 1.2, 11.3.3).
_PNG_COLOUR_CHUNKS = (b"sRGB", b"iCCP", b"gAMA")


def _png_colour_chunks(path) -> set[bytes]:
    """The colour chunks (`_PNG_COLOUR_CHUNKS`) a PNG file holds before its image data:
    the chunk headers are read, not the pixels."""
    found = set()
    with open(path, "rb") as f:
        if f.read(8) != b"\x89PNG\r\n\x1a\n":
            return found
        while True:
            head = f.read(8)
            if len(head) < 8:
                return found
            size, kind = int.from_bytes(head[:4], "big"), head[4:]
            if kind in (b"IDAT", b"IEND"):
                return found
            if kind in _PNG_COLOUR_CHUNKS:
                found.add(kind)
            f.seek(size + 4, 1)  # the chunk's data and CRC


def colour_tag(path, spec) -> bool:
    """Whether an image file states how its values relate to light: float formats
    (linear by definition); a PNG with an sRGB, iCCP or gAMA chunk; another format with
    an ICC profile, an Exif colour space, a gamma, or (not JPEG) a colour space
    OpenImageIO read from the file. OpenImageIO reports an untagged 8/16-bit PNG or
    JPEG as sRGB, their formats' default, so its colour space alone cannot tell."""
    if str(spec.format).startswith(("half", "float", "double")):
        return True
    with open(path, "rb") as f:
        png = f.read(8) == b"\x89PNG\r\n\x1a\n"
    if png:
        return bool(_png_colour_chunks(path))
    names = {a.name for a in spec.extra_attribs}
    if "ICCProfile" in names or "oiio:Gamma" in names:
        return True
    if spec.get_int_attribute("Exif:ColorSpace", 0) == 1:  # 1: sRGB (Exif 2.3, 4.6.5)
        return True
    jpeg = spec.get_string_attribute("jpeg:subsampling", "") != "" or Path(path).suffix.lower() in (
        ".jpg", ".jpeg")  # fmt: skip
    return "oiio:ColorSpace" in names and not jpeg


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
