"""Several processes for real: `jax.distributed` on localhost, two processes with two
CPU devices each (collectives through gloo), against one process with one device.
A ray batch split over the four devices, in chunks that end in padding, must come back
bit for bit the same, on every process."""

import os
import subprocess
import sys
import textwrap

import numpy as np
from helpers import children as _children

WORKER = textwrap.dedent(
    """
    import sys
    import numpy as np
    import jax

    pid, nproc, port, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
    jax.config.update("jax_enable_x64", True)
    if nproc > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(f"127.0.0.1:{port}", num_processes=nproc, process_id=pid,
                                   initialization_timeout=120)
    import jaxlens as jl

    alpha = np.linspace(0.0, np.pi, 100_003)  # crosses the critical angle; odd count
    r = jl.trace_sharded(alpha, 20.0, chunk=40_000, method="exact", progress=False)
    np.savez(out, phi=r.phi, status=r.status, r_min=r.r_min,
             devices=jax.device_count(), processes=jax.process_count())
    """
)


def _env(devices: int) -> dict:
    return dict(os.environ, JAXLENS_CACHE_DIR="",
                XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")  # fmt: skip


def test_a_ray_batch_over_two_processes_is_bitwise_one_process(tmp_path, free_port):
    port = str(free_port)
    procs = [
        subprocess.Popen([sys.executable, "-c", WORKER, str(i), "2", port, str(tmp_path / f"p{i}")],
                         env=_env(2), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for i in range(2)
    ]  # fmt: skip
    try:
        logs = [p.communicate(timeout=300)[0] for p in procs]
    finally:
        for p in procs:
            p.kill()
    for p, log in zip(procs, logs, strict=True):
        assert p.returncode == 0, log[-3000:]
    one = subprocess.run([sys.executable, "-c", WORKER, "0", "1", "0", str(tmp_path / "one")],
                         env=_env(1), capture_output=True, text=True, timeout=300)  # fmt: skip
    assert one.returncode == 0, one.stderr[-3000:]

    ref = np.load(tmp_path / "one.npz")
    assert (int(ref["devices"]), int(ref["processes"])) == (1, 1)
    for i in range(2):
        got = np.load(tmp_path / f"p{i}.npz")
        assert (int(got["devices"]), int(got["processes"])) == (4, 2)
        for key in ("phi", "status", "r_min"):
            np.testing.assert_array_equal(got[key], ref[key], err_msg=f"process {i}: {key}")
    assert np.unique(ref["status"]).size == 2  # escaped and captured rays both present


# ------------------------------------------------------- commands over processes


def _jaxlens(args, env, timeout=600):
    return subprocess.run([sys.executable, "-m", "jaxlens", *args], env=env, capture_output=True,
                          text=True, timeout=timeout)  # fmt: skip


def _command_env(cache) -> dict:
    # Two CPU devices a process; one persistent cache for the runs of a test, so the
    # processes load the programs the first run compiled (the same programs: the
    # comparison is of how the work is split, not of two compiles).
    return dict(_env(2), JAXLENS_CACHE_DIR=str(cache))


def _files(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


def test_an_animation_over_two_processes_is_bitwise_one_process(tmp_path):
    import signal
    import time

    from PIL import Image

    # A panorama sky: B for the reference, A for a run that is killed, then B again in
    # the same file, of the same size, inode and time (PNGs of 32 x 16 random pixels).
    rng = np.random.default_rng(0)
    pictures = {}
    for name in ("A", "B"):
        Image.fromarray(rng.integers(0, 256, (16, 32, 3), np.uint8)).save(tmp_path / "p.png")
        pictures[name] = (tmp_path / "p.png").read_bytes()
    assert len(pictures["A"]) == len(pictures["B"]) and pictures["A"] != pictures["B"]
    sky = tmp_path / "sky.png"
    sky.write_bytes(pictures["B"])
    env = _command_env(tmp_path / "cache")
    anim = ["animate", "--size", "64x36", "--frames", "6", "--path", "orbit", "--sky",
            f"panorama:{sky}"]  # fmt: skip
    for name in ("one", "two", "three"):
        (tmp_path / name).mkdir()
    one = _jaxlens([*anim, "-o", str(tmp_path / "one" / "a.gif"), "--frames-dir",
                    str(tmp_path / "one" / "f")], env)  # fmt: skip
    assert one.returncode == 0, one.stderr[-3000:]
    two = _jaxlens([*anim, "-o", str(tmp_path / "two" / "a.gif"), "--frames-dir",
                    str(tmp_path / "two" / "f"), "--processes", "2"], env)  # fmt: skip
    assert two.returncode == 0, two.stderr[-3000:]
    assert "2 processes" in two.stdout and "[Gloo]" not in two.stdout
    ref = _files(tmp_path / "one")
    shown = sorted(k for k in ref if "/." not in k)  # (a hidden record of the frames too)
    assert shown == ["a.gif"] + [f"f/frame_{i:04d}.png" for i in range(6)]
    assert _files(tmp_path / "two") == ref  # nothing else either: no staging folder left

    # Sky A. Process 1 held once it has joined, and killed once process 0 has finished
    # its share: a clear error, no output file; the 3 frames process 0 finished are kept.
    with open(sky, "r+b") as f:
        f.write(pictures["A"])
    stat = sky.stat()
    out = tmp_path / "three" / "a.gif"
    p = subprocess.Popen([sys.executable, "-m", "jaxlens", *anim, "-o", str(out), "--processes",
                          "2"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while not list(out.parent.glob(".a.gif.frames-*")) and time.monotonic() < deadline:
            time.sleep(0.01)  # made by the processes once they have joined
        children = _children(p.pid)
        os.kill(children[1], signal.SIGSTOP)  # seconds before it could render a frame
        while len(list(out.parent.glob(".a.gif.frames-*/0*.npy"))) < 3:
            assert time.monotonic() < deadline and p.poll() is None
            time.sleep(0.01)
        os.kill(children[1], signal.SIGKILL)
        err = p.communicate(timeout=120)[1]
    finally:
        p.kill()
    assert p.returncode == 1, err
    line = err.replace("\r", "\n").strip().splitlines()[-1]
    assert line.startswith("jaxlens animate: error: process 1 of 2 was killed by SIGKILL"), err
    assert "nothing was written to" in line
    (stage,) = out.parent.iterdir()  # nothing but the finished frames
    assert stage.name.startswith(".a.gif.frames-")
    assert line.endswith(f"; 3 of 6 frames finished are kept in {stage}: rerun the same command "
                         "to continue")  # fmt: skip
    assert sorted(f.name for f in stage.glob("*.npy")) == ["00000.npy", "00001.npy", "00002.npy"]

    # Sky B again, in the same file with the same size and time: the rerun starts afresh
    # (frames of sky A are not reused) and makes the animation of sky B, bit for bit.
    with open(sky, "r+b") as f:
        f.write(pictures["B"])
    os.utime(sky, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert (sky.stat().st_size, sky.stat().st_ino, sky.stat().st_mtime_ns) == (
        stat.st_size, stat.st_ino, stat.st_mtime_ns)  # fmt: skip
    again = _jaxlens([*anim, "-o", str(out), "--processes", "2"], env)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "from an earlier run" not in again.stdout, again.stdout
    assert _files(out.parent) == {"a.gif": ref["a.gif"]}  # the stale frames removed too


def test_fits_over_two_processes_are_bitwise_one_process(tmp_path):
    import json

    import OpenImageIO as oiio

    import jaxlens as jl

    paths = []
    # Process 0 fits the ring, process 1 meets the blank image (an error line, which
    # reaches process 0 through the job's store as a result does). (Process 1's device
    # is another than a single process's: XLA's CPU cache would miss and compile the
    # fit's programs a second time.)
    for i, (d, fov_deg) in enumerate([(14.0, 75.0), (0.0, 0.0)]):
        if d:
            img = np.asarray(jl.ring_image(d, np.radians(fov_deg), 96, 72, sigma=np.radians(1.5),
                                           brightness=0.8, floor=0.05))  # fmt: skip
            img = img + 0.01 * np.random.default_rng(i).standard_normal(img.shape)
        else:
            img = np.full((72, 96), 0.25)  # blank: an error line, the others go on
        paths.append(str(tmp_path / f"i{i}.exr"))
        out = oiio.ImageOutput.create(paths[-1])
        assert out.open(paths[-1], oiio.ImageSpec(96, 72, 1, oiio.FLOAT))
        assert out.write_image(np.ascontiguousarray(img[..., None], np.float32)) and out.close()
    env = _command_env(tmp_path / "cache")
    argv = ["fit", *paths, "--star-sigma-deg", "1.5", "--json"]
    one = _jaxlens(argv, env)
    two = _jaxlens([*argv, "--processes", "2"], env)
    for run in (one, two):
        assert run.returncode == 2, run.stderr[-3000:]  # the blank image
        assert run.stderr.strip().endswith("1 of 2 images could not be fitted (see their lines)")
    lines = [[json.loads(s) for s in run.stdout.splitlines()] for run in (one, two)]
    for a in lines:
        for row in a:
            row.pop("seconds", None)  # the only value that differs: the time taken
    assert lines[0] == lines[1]
    assert [row["image"] for row in lines[0]] == paths
    assert "blank" in lines[0][1]["error"] and lines[0][0]["converged"]
    assert abs(lines[0][0]["distance"] / 14.0 - 1) < 0.01


def test_a_large_render_over_two_processes_is_bitwise_one_process(tmp_path):
    # 1024 x 768 at 2 x 2 samples a pixel: 3.1e6 samples, two blocks of the default size.
    env = _command_env(tmp_path / "cache")
    argv = ["render", "--size", "1024x768", "--yaw-deg", "10"]
    one = _jaxlens([*argv, "-o", str(tmp_path / "one.exr")], env)
    assert one.returncode == 0, one.stderr[-3000:]
    (tmp_path / "two").mkdir()
    two = _jaxlens([*argv, "-o", str(tmp_path / "two" / "two.exr"), "--processes", "2"], env)
    assert two.returncode == 0, two.stderr[-3000:]
    assert "2 processes" in two.stdout
    assert [p.name for p in (tmp_path / "two").iterdir()] == ["two.exr"]  # no blocks left
    a, b = (jl_read(tmp_path / name) for name in ("one.exr", "two/two.exr"))
    assert a.shape == (768, 1024, 3) and np.array_equal(a, b)


def jl_read(path):
    import jaxlens as jl

    return np.asarray(jl.read_image(str(path)))


def test_the_processes_command_line():
    from jaxlens._multi import worker_argv

    assert worker_argv(["fit", "a.png", "--processes", "2", "--json"], "fit") == [
        "fit", "--distributed", "a.png", "--json"]  # fmt: skip
    assert worker_argv(["render", "--proc=4", "-o", "x.png"], "render") == [
        "render", "--distributed", "-o", "x.png"]  # fmt: skip
    # After `--` everything is an argument, an image named like the option too.
    assert worker_argv(["fit", "--pro", "2", "--", "--processes"], "fit") == [
        "fit", "--distributed", "--", "--processes"]  # fmt: skip
