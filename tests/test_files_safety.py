"""Files are written whole or not at all, and nothing of a user's is deleted: a full disk
(a small tmpfs mounted by the test), temporaries locked by their writers, `jaxlens
clean` in a read-only folder, a frames folder holding a user's files, images whose
header declares more pixels than the process may hold, bad exposures, dtypes and loops.
"""

import errno
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from helpers import run

import jaxlens as jl
from jaxlens import cli


@pytest.fixture(autouse=True)
def _no_persistent_cache(monkeypatch):
    monkeypatch.setenv("JAXLENS_CACHE_DIR", "")


@pytest.fixture
def small_disk(tmp_path):
    """`mount(size)`: a folder on a tmpfs of `size` (mount(8) options), unmounted at the
    end; the test is skipped where a tmpfs cannot be mounted (not root, a container
    without the right)."""
    mounted = []

    def mount(size="2m", name="disk"):
        folder = tmp_path / name
        folder.mkdir()
        if os.geteuid() != 0:
            pytest.skip("mounting a small tmpfs needs root")
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                           capture_output=True, text=True)  # fmt: skip
        if r.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
        mounted.append(folder)
        return folder

    yield mount
    for folder in reversed(mounted):
        if subprocess.run(["umount", str(folder)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def _fill(folder: Path, leave: int = 0) -> None:
    """Fill the file system of `folder`, then free about `leave` bytes of it again (a
    write then fails part-way, as on a disk that fills while it is written)."""
    fd = os.open(folder / "filler", os.O_WRONLY | os.O_CREAT)
    try:
        for chunk in (1 << 16, 1 << 12, 1):
            with pytest.raises(OSError) as e:
                while True:
                    os.write(fd, b"\0" * chunk)
            assert e.value.errno == errno.ENOSPC
        os.ftruncate(fd, max(os.fstat(fd).st_size - leave, 0))
    finally:
        os.close(fd)


def _noise(h=192, w=256, c=3, seed=0):
    return np.random.default_rng(seed).random((h, w, c)).astype(np.float32)


def _write(path, seed):
    ext = Path(path).suffix
    if ext == ".gif":
        return jl.write_gif(path, np.stack([_noise(seed=seed + i) for i in range(3)]))
    if ext == ".mp4":
        pytest.importorskip("av")
        return jl.write_video(path, np.stack([_noise(seed=seed + i) for i in range(3)]))
    return jl.write_image(path, _noise(seed=seed))


LEAVE = 16 << 10  # bytes left free on the full disk: less than any file written here


@pytest.mark.parametrize("ext", [".png", ".jpg", ".exr", ".tif", ".hdr", ".gif", ".mp4"])
def test_a_full_disk_is_an_error_and_keeps_the_old_file(tmp_path, small_disk, ext):
    # Every format, and no "success" with a truncated file (PNG and GIF gave one; a
    # JPEG ended the process): the error names the cause and the file, the old file is
    # byte for byte as it was, and no temporary is left.
    assert _write(tmp_path / f"probe{ext}", seed=7).stat().st_size > 2 * LEAVE  # (a test)
    disk = small_disk("2m")
    keep = _write(disk / f"keep{ext}", seed=0)
    old = keep.read_bytes()
    _fill(disk, leave=LEAVE)
    with pytest.raises(OSError, match="no space left on device writing") as e:
        _write(keep, seed=1)
    assert e.value.errno == errno.ENOSPC and str(keep) in str(e.value)
    assert keep.read_bytes() == old
    assert sorted(os.listdir(disk)) == sorted(["filler", keep.name])


def test_a_full_disk_in_the_command_line_is_one_line_and_keeps_the_old_file(small_disk, capsys):
    disk = small_disk("1m")
    keep = disk / "keep.png"
    args = ["render", "--sky", "star", "--size", "12x8", "-o", str(keep)]
    assert run(args, capsys)[0] == 0
    old = keep.read_bytes()
    _fill(disk)
    code, out, err = run([*args, "--exposure", "1"], capsys)  # (another image)
    assert code == 2 and out == "" and err.count("\n") == 1, err
    assert f"no space left on device writing '{keep}'" in err
    assert keep.read_bytes() == old and sorted(os.listdir(disk)) == ["filler", "keep.png"]


def test_frames_of_an_animation_on_a_full_disk_leave_the_folder_as_it_was(
    tmp_path, small_disk, capsys
):
    disk = small_disk("1m")
    frames_dir = disk / "f"
    args = ["animate", "--sky", "checker", "--size", "16x12", "--frames", "3", "--path", "orbit",
            "--supersample", "1", "--frames-dir", str(frames_dir)]  # fmt: skip
    assert run([*args, "-o", str(tmp_path / "a.gif")], capsys)[0] == 0
    before = {p.name: p.read_bytes() for p in frames_dir.iterdir()}
    _fill(disk)
    code, _, err = run([*args, "-o", str(tmp_path / "b.gif"), "--frame-format", "exr"], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert f"no space left on device writing '{frames_dir / 'frame_0000.exr'}'" in err
    assert {p.name: p.read_bytes() for p in frames_dir.iterdir()} == before
    assert sorted(os.listdir(tmp_path)) == ["a.gif", "disk"]


# -- temporaries: locked while written, stale only when no process holds them ---------


def _temporary(folder: Path, stem: str, pid: int) -> Path:
    import socket

    host = "".join(c if c.isalnum() or c == "-" else "-" for c in socket.gethostname()) or "-"
    path = folder / f".{stem}.jaxlens-tmp.{host}.{pid}.abcd1234.png"
    path.write_bytes(b"partial")
    return path


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid  # a process that no longer runs (here)


def test_a_temporary_whose_writer_holds_its_lock_is_kept_whatever_its_pid(tmp_path, capsys):
    # A render in a container (another PID namespace, the same host name) writes a
    # temporary whose PID means nothing here: it holds the lock, so neither `clean` nor
    # another write to the same output removes it. Once it is gone, both do.
    pid = _dead_pid()
    locked = _temporary(tmp_path, "out", pid)
    unlocked = _temporary(tmp_path, "other", pid)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, os, sys, time; fd = os.open(sys.argv[1], 0);"
         " fcntl.flock(fd, fcntl.LOCK_EX); print('locked', flush=True); time.sleep(60)",
         str(locked)], stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert holder.stdout.readline() == "locked\n"
        jl.write_image(tmp_path / "out.png", np.zeros((4, 4, 3)))
        code, out, _ = run(["clean", str(tmp_path)], capsys)
        assert code == 0 and f"removed {unlocked}" in out and str(locked) not in out
        assert locked.exists() and not unlocked.exists()
    finally:
        holder.kill()
        holder.wait()
    code, out, _ = run(["clean", str(tmp_path)], capsys)
    assert code == 0 and f"removed {locked}" in out and not locked.exists()
    assert sorted(os.listdir(tmp_path)) == ["out.png"]


def test_clean_in_a_read_only_folder_says_what_it_could_not_remove(small_disk, capsys):
    disk = small_disk("1m")
    stale = _temporary(disk, "out", _dead_pid())
    if subprocess.run(["mount", "-o", "remount,ro", str(disk)]).returncode != 0:
        pytest.skip("cannot remount the tmpfs read-only here")
    try:
        code, out, err = run(["clean", str(disk)], capsys)
    finally:
        subprocess.run(["mount", "-o", "remount,rw", str(disk)])
    assert code == 2 and "removed" not in out and stale.exists()
    assert f"could not remove {stale}: Read-only file system" in err


# -- a frames folder: only what jaxlens recorded writing there is touched -------------


def test_a_frames_folder_keeps_the_users_files_and_removes_only_earlier_frames(
    tmp_path, capsys, monkeypatch
):
    import jaxlens._cli_animate as anim

    # Groups of two frames, as in test_cli_render's animation test (its program again).
    monkeypatch.setattr(anim, "GROUP_BYTES", 5000)
    frames_dir = tmp_path / "f"
    frames_dir.mkdir()
    mine = {"frame_0100.jpg": b"a photo", "notes.txt": b"notes", "frame_0004.exr": b"exr"}
    for name, data in mine.items():
        (frames_dir / name).write_bytes(data)
    base = ["animate", "--sky", "checker", "--size", "16x12", "--supersample", "1",
            "--start", "30", "--stop", "10", "-o", str(tmp_path / "a.gif"),
            "--frames-dir", str(frames_dir)]  # fmt: skip
    assert run([*base, "--frames", "5"], capsys)[0] == 0
    pngs = [f"frame_000{i}.png" for i in range(5)]
    assert sorted(os.listdir(frames_dir)) == sorted([*mine, *pngs, ".jaxlens-frames.json"])
    # A shorter run removes the two frames the first wrote beyond its own, nothing else.
    assert run([*base, "--frames", "3"], capsys)[0] == 0
    assert sorted(os.listdir(frames_dir)) == sorted([*mine, *pngs[:3], ".jaxlens-frames.json"])
    assert all((frames_dir / n).read_bytes() == d for n, d in mine.items())


def test_a_users_file_of_a_frames_name_is_an_error_and_untouched(tmp_path, capsys):
    frames_dir = tmp_path / "f"
    frames_dir.mkdir()
    (frames_dir / "frame_0000.png").write_bytes(b"the user's own")
    args = ["animate", "--sky", "checker", "--size", "16x12", "--frames", "3", "--path", "orbit",
            "--supersample", "1", "-o", str(tmp_path / "a.gif"),
            "--frames-dir", str(frames_dir)]  # fmt: skip
    code, out, err = run(args, capsys)
    assert code == 2 and out == "" and err.count("\n") == 1
    assert "'frame_0000.png' that jaxlens did not write" in err and str(frames_dir) in err
    assert os.listdir(frames_dir) == ["frame_0000.png"] and os.listdir(tmp_path) == ["f"]
    assert (frames_dir / "frame_0000.png").read_bytes() == b"the user's own"


def test_frames_dir_help_says_what_is_replaced():
    parser = cli.build_parser()._subparsers._group_actions[0].choices["animate"]
    text = " ".join(parser.format_help().split())
    assert ".jaxlens-frames.json" in text and "never touched" in text


# -- images whose header declares more pixels than the process may hold ----------------


def _png_declaring(path: Path, width: int, height: int, pad: int = 0) -> Path:
    """A PNG whose header declares `width` x `height` RGB pixels, with a few rows of
    data only (its IDAT cut short): small on disk, huge decoded. `pad`: bytes of an
    ancillary chunk that make the file larger (OpenImageIO itself refuses a header
    claiming more than about 10^4 times the file's size, but not a 1 MB file's 2.6 GB)."""

    def chunk(kind, data):
        crc = struct.pack(">I", zlib.crc32(kind + data))
        return struct.pack(">I", len(data)) + kind + data + crc

    rows = zlib.compress(b"\0" * (1 + 3 * width) * 4)[:-4]
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    extra = chunk(b"jaXl", bytes(pad)) if pad else b""
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + extra + chunk(b"IDAT", rows))
    return path


def test_an_image_declaring_a_huge_size_is_refused_before_decoding(tmp_path):
    import time

    p = _png_declaring(tmp_path / "huge.png", 30000, 30000, pad=1 << 20)  # a 1 MB file
    t = time.perf_counter()
    with pytest.raises(ValueError, match=r"30000 x 30000 pixels x 3 channels: reading it needs"):
        jl.read_image(p)
    assert time.perf_counter() - t < 1.0  # s: nothing decoded


def test_an_image_is_refused_under_the_process_address_space_limit(tmp_path):
    # 4000 x 4000 RGB: about 1.1 GiB to read, far less than the machine has; under
    # `ulimit -v` (set in the process, 300 MB beyond what it has mapped) it is refused
    # for that limit.
    p = _png_declaring(tmp_path / "big.png", 4000, 4000)
    code = (
        "import resource, sys\n"
        "import jaxlens as jl\n"
        "import OpenImageIO\n"  # (loaded before the limit: its own mappings are large)
        "mapped = [int(l.split()[1]) * 1024 for l in open('/proc/self/status')"
        " if l.startswith('VmSize:')][0]\n"
        "resource.setrlimit(resource.RLIMIT_AS, (mapped + (300 << 20), resource.RLIM_INFINITY))\n"
        "try:\n"
        "    jl.read_image(sys.argv[1])\n"
        "except ValueError as e:\n"
        "    print(e)\n"
    )
    r = subprocess.run([sys.executable, "-c", code, str(p)], capture_output=True, text=True,
                       timeout=60)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "4000 x 4000 pixels x 3 channels: reading it needs about 1.1 GiB" in r.stdout
    assert "(address-space limit)" in r.stdout, r.stdout


# -- a truncated file: one line, jaxlens's ----------------------------------------------


def test_a_truncated_png_is_one_line_on_stderr(tmp_path, capfd):
    # libpng writes "libpng error: ..." to the file descriptor 2 itself (capfd sees it).
    good = jl.write_image(tmp_path / "good.png", _noise(64, 64))
    cut = tmp_path / "cut.png"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    for args in (["fit", str(cut)],
                 ["render", "--sky", f"panorama:{cut}", "--size", "12x8", "-o",
                  str(tmp_path / "o.png")]):  # fmt: skip
        assert cli.main(args) == 2
        out, err = capfd.readouterr()
        assert out == "" and err.count("\n") == 1, err
        assert err.startswith(f"jaxlens {args[0]}: error: ") and "not a readable image" in err


# -- values the writers refuse ----------------------------------------------------------


def test_exposures_dtypes_and_loops_out_of_range_are_refused(tmp_path):
    img = _noise(4, 6)
    frames = np.stack([img, img])
    for bad in (1e300, -1e300, 100.0, float("nan"), float("inf")):
        for write in (lambda: jl.write_image(tmp_path / "a.png", img, exposure=bad),
                      lambda: jl.write_image(tmp_path / "a.exr", img, exposure=bad),
                      lambda: jl.write_gif(tmp_path / "a.gif", frames, exposure=bad),
                      lambda: jl.write_video(tmp_path / "a.mp4", frames, exposure=bad),
                      lambda: jl.to_display(img, exposure=bad)):  # fmt: skip
            with pytest.raises(ValueError, match=r"exposure=.* expected a number of stops in "
                                                 r"\(-100, 100\)"):  # fmt: skip
                write()
    with pytest.raises(TypeError, match="exposure=1j"):
        jl.write_image(tmp_path / "a.png", img, exposure=1j)
    assert jl.to_display(img, exposure=99.0).max() == 255  # the range's edge is fine
    for dtype in (np.complex64, object):
        with pytest.raises(ValueError, match=f"image of dtype {np.dtype(dtype)} is not valid"):
            jl.write_image(tmp_path / "a.png", img.astype(dtype))
        with pytest.raises(ValueError, match=f"frames of dtype {np.dtype(dtype)} is not valid"):
            jl.write_gif(tmp_path / "a.gif", frames.astype(dtype))
    for loop in (-1, 65536, 1.5, True, "2"):
        with pytest.raises(ValueError, match=r"loop=.* expected a whole number from 0"):
            jl.write_gif(tmp_path / "a.gif", frames, loop=loop)
    assert os.listdir(tmp_path) == []
    jl.write_gif(tmp_path / "a.gif", frames, loop=65535)  # the largest count is fine


def test_clean_while_an_animation_writes_its_frames_leaves_them(tmp_path, capsys, monkeypatch):
    # The hidden folder the frames are written to is locked while the command runs: a
    # `jaxlens clean` meanwhile (another terminal) leaves it, and the frames arrive.
    frames_dir, render, cleaned = tmp_path / "f", jl.render, []

    def render_then_clean(scene, **kw):
        images = render(scene, **kw)
        if frames_dir.exists():  # (made before the first frame is saved)
            cleaned.append(cli.main(["clean", str(frames_dir)]))
        return images

    monkeypatch.setattr(jl, "render", render_then_clean)
    args = ["animate", "--sky", "checker", "--size", "16x12", "--frames", "3", "--path", "orbit",
            "--supersample", "1", "-o", str(tmp_path / "a.gif"),
            "--frames-dir", str(frames_dir)]  # fmt: skip
    code, out, err = run(args, capsys)
    assert code == 0 and cleaned == [0] and "no stale temporary files" in out, err
    assert sorted(os.listdir(frames_dir)) == [".jaxlens-frames.json"] + [
        f"frame_000{i}.png" for i in range(3)
    ]
