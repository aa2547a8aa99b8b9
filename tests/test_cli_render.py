"""`jaxlens render` and `jaxlens animate`: outputs, overrides, and every bad input as one
line on stderr with exit code 2 and no file left behind."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from helpers import run
from PIL import Image

import jaxlens as jl
from jaxlens import cli, read_image, write_image


@pytest.fixture(autouse=True)
def _no_persistent_cache(monkeypatch):
    monkeypatch.setenv("JAXLENS_CACHE_DIR", "")


def test_options_in_degrees_are_named_so_and_the_old_names_stay(tmp_path, capsys):
    base = ["render", "--sky", "star", "--size", "12x8", "--supersample", "1"]
    files = []
    for names in (["--fov-deg", "--yaw-deg", "--roll-deg"], ["--fov", "--yaw", "--roll"]):
        files.append(tmp_path / f"{len(files)}.exr")
        args = [names[0], "70", names[1], "3", names[2], "10", "-o", str(files[-1])]
        assert run([*base, *args], capsys)[0] == 0
    np.testing.assert_array_equal(read_image(files[0]), read_image(files[1]))
    help_text = cli.build_parser()._subparsers._group_actions[0].choices["render"].format_help()
    assert "--fov-deg DEG, --fov DEG" in help_text and "--pitch-deg DEG" in help_text


def test_the_collector_skips_the_objects_loaded_while_a_command_runs(tmp_path, capsys,
                                                                       monkeypatch):  # fmt: skip
    import gc

    seen, render = [], jl.render

    def counted(*args, **kwargs):
        seen.append(gc.get_freeze_count())
        return render(*args, **kwargs)

    monkeypatch.setattr(jl, "render", counted)
    args = ["render", "--sky", "star", "--size", "12x8", "-o", str(tmp_path / "x.png")]
    assert run(args, capsys)[0] == 0
    assert seen[0] > 0  # frozen while the command ran ...
    assert gc.get_freeze_count() == 0  # ... and given back to the collector after it


def test_native_modules_load_where_a_signal_ends_the_command_at_once(tmp_path, capsys,
                                                                       monkeypatch):  # fmt: skip
    # A Ctrl-C in OpenImageIO's set-up (its first import, maybe while a render compiles)
    # aborted the process: "Critical nanobind error".
    import contextlib
    import signal

    from jaxlens import _io

    seen, render = [], jl.render

    def spied(*args, **kwargs):
        with _io.native_import():
            seen.append(signal.getsignal(signal.SIGINT))
        seen.append(signal.getsignal(signal.SIGINT))
        return render(*args, **kwargs)

    monkeypatch.setattr(jl, "render", spied)
    # Run from a background job, the suite inherits SIGINT ignored, which the command
    # rightly keeps ignored: the test starts from Python's own handler.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        args = ["render", "--sky", "star", "--size", "12x8", "-o", str(tmp_path / "x.png")]
        assert run(args, capsys)[0] == 0
    finally:
        signal.signal(signal.SIGINT, previous)
    assert seen[0].func is cli._exit_at_once and seen[1] is not seen[0]
    assert _io.native_import is contextlib.nullcontext  # outside the command: as it was


def test_render_star_exr(tmp_path, capsys):
    out = tmp_path / "x.exr"
    args = ["--sky", "star", "--size", "48x32", "--supersample", "2", "--distance", "10"]
    code, stdout, err = run(["render", *args, "--fov", "90", "-o", str(out)], capsys)
    assert code == 0 and "wrote" in stdout and err == ""
    img = read_image(out)
    assert img.shape == (32, 48, 3)
    # Linear floats, no exposure: the ring of a peak-1 star stays below 1 and close
    # to it; the shadow at the centre is black.
    assert 0.5 < img.max() <= 1.0 + 1e-6
    assert img[16, 24].max() == 0.0
    assert os.listdir(tmp_path) == ["x.exr"]


EFFECTS_SCENE = """
accuracy = 1e-8
[camera]
distance = 15.0
fov_deg = 80.0
width = 24
height = 16
supersample = 1
[[sky]]
type = "uniform"
level = 0.2
[effects.motion]
type = "orbit"
[effects.redshift]
mode = "spectral"
[effects.disk]
r_out = 10.0
inclination_deg = 75.0
crossings = 2
steps = 16
"""


def test_render_a_scene_file_with_effects_and_a_disk(tmp_path, capsys):
    # The scene file's [effects] tables reach `jaxlens render`: the image is the one
    # jl.render makes of jl.load_scene of the same file, float32 output round-off only.
    scene_file = tmp_path / "effects.toml"
    scene_file.write_text(EFFECTS_SCENE)
    out = tmp_path / "fx.exr"
    code, stdout, err = run(["render", str(scene_file), "-o", str(out)], capsys)
    assert code == 0 and "wrote" in stdout and err == ""
    scene = jl.load_scene(scene_file)
    assert isinstance(scene.motion, jl.CircularOrbit) and scene.disk is not None
    want = jl.render(scene, dtype=np.float32)
    np.testing.assert_allclose(read_image(out), want, rtol=0, atol=1e-6)
    # the disk is in the image (brighter than the 0.2 sky, which the shift changes)
    assert read_image(out).max() > 1.0
    bad = tmp_path / "bad.toml"
    bad.write_text(EFFECTS_SCENE.replace('type = "orbit"', 'type = "spin"'))
    code, _, err = run(["render", str(bad), "-o", str(tmp_path / "b.exr")], capsys)
    assert code == 2 and "expected one of orbit, infall" in err and err.count("\n") == 1
    assert not (tmp_path / "b.exr").exists()


def test_options_override_the_scene_file(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(
        '[camera]\ndistance = 30.0\nwidth = 16\nheight = 8\n[[sky]]\ntype = "checker"\n'
    )
    code, stdout, _ = run(["render", str(scene), "--distance", "10", "-o",
                           str(tmp_path / "a.png")], capsys)  # fmt: skip
    assert code == 0 and "16x8, D = 10 R_S" in stdout
    code, stdout, _ = run(["render", str(scene), "-o", str(tmp_path / "b.png")], capsys)
    assert code == 0 and "D = 30 R_S" in stdout


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
@pytest.mark.parametrize("ext", [".png", ".exr"])
def test_panorama_files_of_any_channel_count(tmp_path, capsys, channels, ext):
    pano = tmp_path / f"p{ext}"
    write_image(pano, np.random.default_rng(0).random((16, 32, channels)) * 0.5)
    out = tmp_path / "o.png"
    code, _, err = run(["render", "--sky", f"panorama:{pano}", "--size", "16x8",
                        "--supersample", "1", "-o", str(out)], capsys)  # fmt: skip
    assert code == 0, err
    assert Image.open(out).size == (16, 8)


def test_a_single_sky_table_takes_paths_relative_to_its_file(tmp_path, capsys, monkeypatch):
    # `[sky]` (one table) as well as `[[sky]]` (a list): the image path is the file's.
    (tmp_path / "scenes").mkdir()
    write_image(tmp_path / "scenes" / "p.exr", np.full((16, 32, 3), 0.25, np.float32))
    scene = tmp_path / "scenes" / "one.toml"
    scene.write_text('[camera]\nwidth = 16\nheight = 8\nsupersample = 1\n'
                     '[sky]\ntype = "panorama"\npath = "p.exr"\n')  # fmt: skip
    monkeypatch.chdir(tmp_path)
    code, _, err = run(["render", "scenes/one.toml", "-o", "o.exr"], capsys)
    assert code == 0, err
    assert read_image(tmp_path / "o.exr").max() == pytest.approx(0.25, rel=1e-6)


def _bad_files(tmp_path):
    (tmp_path / "text.png").write_text("hello")
    good = write_image(tmp_path / "good.exr", np.ones((32, 64, 3), np.float32))
    (tmp_path / "cut.exr").write_bytes(good.read_bytes()[:200])
    (tmp_path / "bad.toml").write_text("[camera]\nfov = 60\n")
    (tmp_path / "wide.toml").write_text('camera = "wide"\n')
    (tmp_path / "five.toml").write_text("camera = 5\n")
    (tmp_path / "output.toml").write_text("output = 5\n")
    (tmp_path / "base.toml").write_text('[[sky]]\ntype = "star"\n_base = "/etc"\n')
    (tmp_path / "deep.toml").write_text("a = " + "[" * 1000 + "]" * 1000 + "\n")


BAD = [
    (["--distance", "0.5"], "--distance 0.5"),
    (["--distance", "1"], "--distance 1.0"),
    (["--distance", "-3"], "--distance -3.0"),
    (["--distance", "nan"], "--distance nan"),
    (["--distance", "inf"], "--distance inf"),
    (["--fov", "0"], "--fov-deg 0.0"),
    (["--fov", "180"], "--fov-deg 180.0"),
    (["--fov", "-10"], "--fov-deg -10.0"),
    (["--size", "0x10"], "--size '0x10'"),
    (["--size=-4x4"], "--size '-4x4'"),
    (["--size", "10"], "--size '10'"),
    (["--supersample", "0"], "--supersample 0"),
    (["--star-sigma-deg", "0"], "--star-sigma-deg 0.0"),
    (["--sky", "nebula"], "--sky 'nebula'"),
    (["--sky", "panorama:{tmp}/none.png"], "none.png' does not exist"),
    (["--sky", "panorama:{tmp}/text.png"], "text.png' is not a readable image"),
    (["--sky", "panorama:{tmp}/cut.exr"], "cut.exr' is not a readable image"),
    (["--sky", "plane:{tmp}/text.png"], "text.png' is not a readable image"),
    (["{tmp}/bad.toml"], "unknown key 'fov'"),
    (["{tmp}/none.toml"], "none.toml' does not exist"),
    (["--distance", "1e35"], "at most 1e+30 in magnitude"),
    (["--star-brightness", "1e300"], "at most 1e+30 in magnitude"),
    (["--exposure", "150"], "a number in (-100, 100) (stops)"),
    (["{tmp}/wide.toml"], '[camera] must be a table, got "wide"'),
    (["{tmp}/five.toml", "--fov", "30"], "[camera] must be a table, got 5"),
    (["{tmp}/output.toml", "--exposure", "1"], "[output] must be a table, got 5"),
    (["{tmp}/base.toml"], "[[sky]] #1 has an unknown key '_base'"),
    (["{tmp}/deep.toml"], "nests its tables too deeply"),
]


@pytest.mark.parametrize("extra,message", BAD, ids=[" ".join(e) for e, _ in BAD])
def test_bad_input_is_one_line_exit_2_and_no_file(tmp_path, capsys, extra, message):
    _bad_files(tmp_path)
    before = sorted(os.listdir(tmp_path))
    extra = [e.format(tmp=tmp_path) for e in extra]
    code, stdout, err = run(["render", "--size", "8x6", *extra, "-o", str(tmp_path / "o.png")],
                            capsys)  # fmt: skip
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("jaxlens render: error: ")
    assert message in err
    assert sorted(os.listdir(tmp_path)) == before  # nothing written, no temporary files


@pytest.mark.parametrize(
    "output,message",
    [
        ("/sys/o.png", "not writable"),
        ("{tmp}/o.bmp", "unsupported extension '.bmp'"),
        ("{tmp}/o.gif", "jaxlens animate"),
        ("{tmp}/o.mp4", "jaxlens animate"),
    ],
)
def test_bad_output_paths(tmp_path, capsys, output, message):
    if output.startswith("/sys") and os.access("/sys", os.W_OK) and os.geteuid() != 0:
        pytest.skip("/sys is not a read-only folder here")
    code, _, err = run(["render", "--size", "8x6", "-o", output.format(tmp=tmp_path)], capsys)
    assert code == 2 and err.count("\n") == 1 and message in err
    assert os.listdir(tmp_path) == []


def test_usage_errors_are_one_line(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["render", "--no-such-option", "-o", "x.png"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--no-such-option" in err


def test_outputs_larger_than_memory_are_refused_before_rendering(tmp_path, capsys, monkeypatch):
    import jaxlens._io as io_

    monkeypatch.setattr(io_, "available_memory", lambda: 64 << 20)  # 64 MiB
    for cmd in (["render", "-o", str(tmp_path / "a.png")],
                ["animate", "--frames", "3", "-o", str(tmp_path / "a.gif")]):  # fmt: skip
        code, _, err = run([*cmd, "--size", "4000x3000"], capsys)
        assert code == 2 and err.count("\n") == 1 and "4000 x 3000 pixels need about" in err
    assert os.listdir(tmp_path) == []


def test_interrupt_leaves_no_file(tmp_path, capsys, monkeypatch):
    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(jl, "render", interrupted)
    code, _, err = run(["render", "--size", "8x6", "-o", str(tmp_path / "o.png")], capsys)
    assert code == 130 and "interrupted" in err and os.listdir(tmp_path) == []


def test_an_interrupt_swallowed_by_a_gc_callback_is_sent_again():
    # Python ignores exceptions raised in garbage-collector callbacks (JAX has one): a
    # Ctrl-C landing there reached the hook only, and the render went on to exit 0.
    # The signal is sent again in a child process: sent to this one, it could land in
    # another callback of this long-lived process (JAX's weak-key caches) and be printed
    # there as an ignored KeyboardInterrupt, after the test dots.
    import types

    code = textwrap.dedent(
        """
        import signal, sys, time
        signal.signal(signal.SIGINT, signal.default_int_handler)
        from jaxlens import cli
        sys.unraisablehook = cli._redeliver  # as the command installs it

        class Dropped:
            def __del__(self):
                raise KeyboardInterrupt  # where Python ignores it: the hook sees it

        Dropped()
        try:
            time.sleep(10.0)  # the signal is sent again within 0.05 s
        except KeyboardInterrupt:
            print("interrupted")
        """
    )
    run_ = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)  # fmt: skip
    assert run_.returncode == 0 and run_.stdout == "interrupted\n", run_.stderr[-2000:]
    assert "Exception ignored" not in run_.stderr, run_.stderr

    calls = []
    cli._redeliver(types.SimpleNamespace(exc_value=RuntimeError("x")), hook=calls.append)
    assert len(calls) == 1  # other reports go on to the previous hook


@pytest.mark.parametrize("signame, code, word", [("SIGINT", 130, "interrupted"),
                                                 ("SIGTERM", 143, "terminated")])  # fmt: skip
def test_signals_while_jax_loads_or_compiles(tmp_path, signame, code, word):
    import signal
    import time

    out = tmp_path / "o.png"
    # Importing JAX (its native modules run Python code where an exception aborts the
    # process: a Ctrl-C there ended in `terminate called ...`), then compiling.
    for delay in (0.1, 0.3, 0.5, 0.8, 1.5):
        # Python's own Ctrl-C handler in the child (a background job inherits SIGINT
        # ignored), set in the child itself: a pre-exec function would fork this
        # multithreaded process.
        # The delay counts from the child's "ready" (the command's module imported, in
        # 0.1-0.3 s on a loaded machine): a signal during Python's own start-up, before
        # any of jaxlens runs, ends the process the default way.
        code_ = ("import runpy, signal, sys;"
                 " signal.signal(signal.SIGINT, signal.default_int_handler);"
                 " import jaxlens.cli; print('ready', flush=True);"
                 f" sys.argv = ['jaxlens', 'render', '-o', {str(out)!r}];"
                 " runpy.run_module('jaxlens', run_name='__main__')")  # fmt: skip
        p = subprocess.Popen([sys.executable, "-c", code_], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True,
                             env=dict(os.environ, JAXLENS_CACHE_DIR=""))  # fmt: skip
        assert p.stdout.readline() == "ready\n"
        time.sleep(delay)
        p.send_signal(getattr(signal, signame))
        err = p.communicate(timeout=120)[1]
        assert p.returncode == code and err.strip().endswith(word), (delay, err)
        assert "Traceback" not in err and os.listdir(tmp_path) == []


def test_a_status_line_on_a_terminal_from_the_first_second(tmp_path):
    # A command silent for seconds (loading JAX, compiling) shows what it does on a
    # terminal's stderr, and clears the line before its result; not into a pipe.
    import pty
    import select

    master, slave = pty.openpty()
    out = tmp_path / "o.png"
    p = subprocess.Popen(
        [sys.executable, "-m", "jaxlens", "render", "--size", "16x12", "--supersample", "1",
         "-o", str(out)],
        stderr=slave, stdout=subprocess.PIPE, text=True,
        env=dict(os.environ, JAXLENS_CACHE_DIR=""),
    )  # fmt: skip
    os.close(slave)
    seen = b""
    while True:
        if select.select([master], [], [], 0.2)[0]:
            try:
                chunk = os.read(master, 4096)
            except OSError:  # the child closed the terminal
                break
            if not chunk:
                break
            seen += chunk
        elif p.poll() is not None:
            break
    os.close(master)
    stdout = p.communicate(timeout=60)[0]
    assert p.returncode == 0 and stdout.startswith(f"wrote {out}")
    text = seen.decode()
    assert "\rjaxlens render: " in text and " s\x1b[K" in text, text
    assert text.endswith("\r\x1b[K")  # cleared before the result


def test_animate_writes_frames_and_gif(tmp_path, capsys):
    out = tmp_path / "orbit.gif"
    args = ["--sky", "checker", "--size", "16x12", "--frames", "3", "--path", "orbit"]
    code, stdout, err = run(["animate", *args, "--supersample", "1", "-o", str(out)], capsys)
    assert code == 0, err
    assert os.listdir(tmp_path) == ["orbit.gif"]  # frame files only when asked for
    with Image.open(out) as im:
        assert im.n_frames == 3 and im.size == (16, 12)
    frames_dir = tmp_path / "frames"
    code, stdout, err = run(["animate", *args, "--supersample", "1", "-o", str(out),
                             "--frames-dir", str(frames_dir)], capsys)  # fmt: skip
    assert code == 0 and f"3 frames in {frames_dir}/" in stdout, err
    frames = sorted(os.listdir(frames_dir))  # and the record of the frames written
    assert frames == [".jaxlens-frames.json", "frame_0000.png", "frame_0001.png",
                      "frame_0002.png"]  # fmt: skip
    frames = frames[1:]
    # An orbit turns the sky: the frames differ.
    a = np.asarray(Image.open(frames_dir / frames[0]))
    b = np.asarray(Image.open(frames_dir / frames[1]))
    assert np.abs(a.astype(int) - b).max() > 50


def test_animate_streams_groups_of_frames_and_replaces_or_keeps_a_frames_folder(
    tmp_path, capsys, monkeypatch
):
    import jaxlens._cli_animate as anim

    # 16 x 12 float32 RGB frames, 2304 bytes: groups of two, the last padded.
    monkeypatch.setattr(anim, "GROUP_BYTES", 5000)
    assert anim.frames_per_call(16, 12, 5) == 2 and anim.frames_per_call(16, 12, 1) == 1
    calls, real = [], jl.render

    def counting(scene, **kw):
        calls.append(np.shape(scene.camera.distance))
        return real(scene, **kw)

    monkeypatch.setattr(jl, "render", counting)
    out, frames_dir = tmp_path / "a.gif", tmp_path / "f"
    base = ["animate", "--sky", "checker", "--size", "16x12", "--supersample", "1",
            "--start", "30", "--stop", "10", "-o", str(out),
            "--frames-dir", str(frames_dir)]  # fmt: skip
    assert run([*base, "--frames", "5"], capsys)[0] == 0
    assert calls == [(2,), (2,), (2,)]
    first = {n: (frames_dir / n).read_bytes() for n in sorted(os.listdir(frames_dir))}
    assert list(first) == [".jaxlens-frames.json"] + [f"frame_000{i}.png" for i in range(5)]
    with Image.open(out) as im:
        assert im.n_frames == 5

    # Interrupted on its second group: no GIF, and the folder as it was.
    gif = out.read_bytes()

    def interrupted(scene, **kw):
        calls.append(None)
        if calls.count(None) == 2:
            raise KeyboardInterrupt
        return real(scene, **kw)

    monkeypatch.setattr(jl, "render", interrupted)
    code, _, err = run([*base, "--frames", "4", "--start", "20"], capsys)
    assert code == 130 and "interrupted" in err
    assert out.read_bytes() == gif and sorted(os.listdir(tmp_path)) == ["a.gif", "f"]
    assert {n: (frames_dir / n).read_bytes() for n in os.listdir(frames_dir)} == first

    # A rerun with fewer frames replaces them all: none of the earlier five is left.
    monkeypatch.setattr(jl, "render", real)
    assert run([*base, "--frames", "3", "--start", "20"], capsys)[0] == 0
    assert sorted(os.listdir(frames_dir)) == [".jaxlens-frames.json"] + [
        f"frame_000{i}.png" for i in range(3)
    ]
    assert (frames_dir / "frame_0000.png").read_bytes() != first["frame_0000.png"]


def test_animate_writes_frames_and_mp4(tmp_path, capsys):
    av = pytest.importorskip("av")
    out = tmp_path / "orbit.mp4"
    args = ["--sky", "default", "--size", "32x24", "--frames", "3", "--path", "orbit",
            "--start", "0", "--stop", "60", "--fps", "6", "--supersample", "1"]  # fmt: skip
    code, stdout, err = run(["animate", *args, "-o", str(out), "--frames-dir",
                             str(tmp_path / "orbit_frames")], capsys)  # fmt: skip
    assert code == 0, err
    assert f"wrote {out}" in stdout
    assert sorted(os.listdir(tmp_path)) == ["orbit.mp4", "orbit_frames"]
    names = sorted(os.listdir(tmp_path / "orbit_frames"))  # and the frames' record
    assert names == [".jaxlens-frames.json", "frame_0000.png", "frame_0001.png",
                     "frame_0002.png"]  # fmt: skip
    names = names[1:]
    pngs = [np.asarray(Image.open(tmp_path / "orbit_frames" / n)).astype(int) for n in names]
    with av.open(str(out)) as c:
        s = c.streams.video[0]
        assert s.codec_context.name == "h264" and s.average_rate == 6
        assert (s.width, s.height) == (32, 24)
        got = [f.to_ndarray(format="rgb24", src_colorspace="itu709", src_color_range="MPEG")
               for f in c.decode(s)]  # fmt: skip
    assert len(got) == 3
    # Each video frame is its PNG frame to within codec error (1 to 3 levels measured;
    # the default sky has stars and dust, sharper than the gradients of test_io), and
    # not another frame's (15 to 59): the orbit turns the sky.
    diff = np.array([[np.abs(g.astype(int) - p).mean() for p in pngs] for g in got])
    assert np.diag(diff).max() < 8, diff
    assert (diff + 100 * np.eye(3)).min(axis=1).min() > 2 * np.diag(diff).max(), diff


def test_animate_mp4_without_pyav_fails_before_rendering(tmp_path, capsys, monkeypatch):
    def not_reached(*a, **k):
        raise AssertionError("rendered although the MP4 cannot be written")

    monkeypatch.setattr(jl, "render", not_reached)
    monkeypatch.setitem(sys.modules, "av", None)  # `import av` raises ImportError
    code, _, err = run(["animate", "--size", "8x6", "-o", str(tmp_path / "a.mp4")], capsys)
    assert code == 2 and err.count("\n") == 1 and "pip install 'jaxlens-bh[video]'" in err
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize(
    "extra,message",
    [
        (["-o", "{tmp}/a.png"], "must be a .gif or .mp4"),
        (["--path", "approach", "--start", "0.5", "-o", "{tmp}/a.gif"], "--start 0.5"),
        (["--path", "zoom", "--stop", "200", "-o", "{tmp}/a.gif"], "--stop 200.0"),
        (["--frames", "0", "-o", "{tmp}/a.gif"], "--frames 0"),
        (["--fps", "0.0001", "-o", "{tmp}/a.gif"], "fps=0.0001 is not valid for a GIF"),
    ],
)
def test_animate_bad_input(tmp_path, capsys, extra, message):
    extra = [e.format(tmp=tmp_path) for e in extra]
    code, _, err = run(["animate", "--size", "8x6", *extra], capsys)
    assert code == 2 and err.count("\n") == 1 and message in err
    assert os.listdir(tmp_path) == []


def test_scene_keys_lists_the_schema_and_help_names_no_file(capsys):
    for command in ("render", "animate"):
        with pytest.raises(SystemExit) as e:
            cli.main([command, "--scene-keys"])
        assert e.value.code == 0
        out = capsys.readouterr().out
        assert "[camera]\n  distance = 20.0    # a finite number > 1 (units of R_S)" in out
        for kind in jl.scene_table_types("sky"):
            assert f'  type = "{kind}"' in out
        for section in ("motion", "redshift", "disk"):
            assert f"[effects.{section}]" in out
        with pytest.raises(SystemExit):
            cli.main([command, "--help"])
        assert "docs/" not in capsys.readouterr().out  # the wheel has no docs folder


def test_version_and_python_dash_m(capsys):
    import jaxlens

    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"jaxlens {jaxlens.__version__}"
    p = subprocess.run([sys.executable, "-m", "jaxlens", "--version"], capture_output=True,
                       text=True, timeout=60)  # fmt: skip
    assert p.returncode == 0 and p.stdout.strip() == f"jaxlens {jaxlens.__version__}"


# A command's end (`cli.finish`): the exit handlers run, the output is flushed, the
# status kept.
_FINISH = """
import atexit
from jaxlens.cli import finish

atexit.register(lambda: print("exit handler"))
print("done", end="")
finish(3)
"""


def test_a_command_ends_after_its_exit_handlers(tmp_path):
    p = subprocess.run([sys.executable, "-c", _FINISH], capture_output=True, text=True,
                       timeout=120)  # fmt: skip
    assert p.returncode == 3, p.stderr[-2000:]
    assert p.stdout == "doneexit handler\n"


def test_command_line_process_has_no_traceback(tmp_path):
    env = dict(os.environ, JAXLENS_CACHE_DIR="")
    p = subprocess.run(
        [sys.executable, "-m", "jaxlens", "render", "--distance", "0.9", "-o",
         str(tmp_path / "x.png")], capture_output=True, text=True, env=env, timeout=120,
    )  # fmt: skip
    assert p.returncode == 2
    assert p.stderr.strip().count("\n") == 0 and "Traceback" not in p.stderr
    assert "--distance 0.9" in p.stderr
    assert os.listdir(tmp_path) == []
