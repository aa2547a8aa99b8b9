"""The command line's limits: every bad value, however large, odd or endless, is one
readable line on stderr naming the option (or scene key) and the value, exit code 2,
before anything is rendered."""

import math
import os
import time

import pytest

import jaxlens as jl
from jaxlens import cli


@pytest.fixture(autouse=True)
def _no_persistent_cache(monkeypatch):
    monkeypatch.setenv("JAXLENS_CACHE_DIR", "")


def run(args, capsys):
    """`jaxlens ARGS` in this process: (exit code, stdout, stderr); argparse's own
    errors end in SystemExit."""
    try:
        code = cli.main(args)
    except SystemExit as e:
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err


def one_error_line(err: str, command: str = "render") -> str:
    assert err.count("\n") == 1 and err.startswith(f"jaxlens {command}: error: "), err[:2000]
    return err


# -------------------------------------------------------------- scene file size


@pytest.mark.parametrize("which", ["/dev/zero", "2 MB file"])
def test_an_endless_or_huge_scene_file_is_refused_at_once(tmp_path, capsys, which):
    if which == "/dev/zero":
        if not os.path.exists("/dev/zero"):
            pytest.skip("no /dev/zero here")
        scene = "/dev/zero"
    else:
        scene = tmp_path / "big.toml"
        scene.write_text("# " + "x" * 2_000_000 + "\n")  # valid TOML: a comment
    t = time.perf_counter()
    code, out, err = run(["render", str(scene), "-o", str(tmp_path / "o.png")], capsys)
    # Bounded read of 1 MiB: milliseconds (the whole file read took seconds, or all memory).
    assert time.perf_counter() - t < 5.0
    assert code == 2 and out == ""
    assert "is larger than 1 MiB, the most a scene file may hold" in one_error_line(err)
    assert not (tmp_path / "o.png").exists()


def test_a_scene_file_of_just_under_the_limit_is_read(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text("# " + "x" * ((1 << 20) - 40) + "\n[camera]\ndistance = 7.5\n")
    assert os.path.getsize(scene) <= 1 << 20
    assert jl.load_scene(scene).camera.distance == 7.5


# -------------------------------------------------------------- long values cut


def test_a_list_of_a_million_numbers_is_named_by_its_start_and_length():
    with pytest.raises(ValueError) as e:
        jl.Scene.from_dict({"camera": {"width": [7] * 1_000_000}})
    message = str(e.value)
    assert "[camera] width = [7, 7, 7, ... 1000000 items] is not valid" in message
    assert len(message) < 300


def test_a_long_list_in_a_scene_file_gives_a_short_line(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    # 300,000 items: 900 KB, under the size limit.
    scene.write_text('[[sky]]\ntype = "checker"\nn_lon = [' + "12," * 300_000 + "]\n")
    code, _, err = run(["render", str(scene), "-o", str(tmp_path / "o.png")], capsys)
    assert code == 2
    assert "n_lon = [12, 12, 12, ... 300000 items] is not valid" in one_error_line(err)
    assert len(err) < 400


def test_the_bad_item_of_a_long_list_is_named_alone(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    lon = "[" + "1.5," * 9_999 + "inf]"
    scene.write_text(f'[[sky]]\ntype = "stars"\nlon_deg = {lon}\nlat_deg = {lon}\n')
    code, _, err = run(["render", str(scene), "-o", str(tmp_path / "o.png")], capsys)
    assert code == 2 and len(err) < 400
    assert "(stars) lon_deg[9999] = inf is not valid: expected a list of finite" in one_error_line(
        err
    )


LONG = "a" * 10_000_000  # a 10 MB argument (in this process: no limit on argv)


@pytest.mark.parametrize(
    "where", ["-o", "scene", "--size", "--distance", "--sky", "animate -o", "fit image"]
)
def test_a_10_mb_argument_gives_a_line_of_bounded_length(tmp_path, capsys, where):
    command = where.split()[0] if " " in where else "render"
    out = str(tmp_path / "o.png")
    args = {
        "-o": ["render", "-o", f"{tmp_path}/{LONG}.png"],
        "scene": ["render", f"{tmp_path}/{LONG}.toml", "-o", out],
        "--size": ["render", "--size", LONG, "-o", out],
        "--distance": ["render", "--distance", LONG, "-o", out],
        "--sky": ["render", "--sky", LONG, "-o", out],
        "animate -o": ["animate", "-o", f"{tmp_path}/{LONG}.gif"],
        "fit image": ["fit", f"{tmp_path}/{LONG}.png"],
    }[where]
    code, _, err = run(args, capsys)
    assert code == 2
    one_error_line(err, command)
    assert len(err) <= 1100  # the line's limit: 1000 characters and the command's name
    assert "aaaaaaaaaaaaaaaaaaaa" in err and "10000" in err  # its start, and its length
    assert os.listdir(tmp_path) == []


def test_one_line_cuts_long_words_and_long_lines():
    line = cli.one_line("value " + "x" * 5000 + "\nis\tbad")
    assert line.startswith("value " + "x" * 200 + "... (5000 characters) is bad")
    line = cli.one_line(" ".join(str(i) for i in range(100_000)))
    assert len(line) <= 1000 and line.startswith("0 1 2 3") and line.endswith("99998 99999")


# -------------------------------------------------------------- values named


def no_render(monkeypatch):
    """`jl.render` that fails the test: the value must be refused before rendering."""

    def render(*args, **kwargs):
        raise AssertionError("rendered")

    monkeypatch.setattr(jl, "render", render)


@pytest.mark.parametrize(
    "extra,message",
    [
        # Values that start with "-": argparse took them for options ("expected one argument").
        (["--distance", "-inf"], "--distance -inf is not valid: expected a finite number > 1 "
         "(units of R_S)"),
        (["--size", "-5x10"], "--size '-5x10': width and height must be >= 1 pixel"),
        (["--exposure", "-1e300"], "--exposure -1e+300 is not valid: expected a number in "
         "(-100, 100) (stops)"),
        (["--yaw-deg", "-nan"], "--yaw-deg nan is not valid: expected a finite number (degrees)"),
        (["--fov-deg", "-Infinity"], "--fov-deg -inf is not valid"),
        (["--star-brightness", "-1E300"], "--star-brightness -1e+300 is not valid"),
        # Enough digits to show the value is outside the range.
        (["--fov-deg", "180.0000000001"], "--fov-deg 180.0000000001 is not valid: expected a "
         "number in (0, 180) (degrees)"),
        (["--size", "2000000x10"], "--size '2000000x10': width 2000000 is not valid: expected a "
         "whole number from 1 to 1048575 (pixels)"),
        (["--supersample", str(10**30)], f"--supersample {10**30} is not valid: expected a "
         "whole number from 1 to 64"),
    ],
)  # fmt: skip
def test_every_bad_option_value_is_named(tmp_path, capsys, monkeypatch, extra, message):
    no_render(monkeypatch)
    code, _, err = run(["render", *extra, "-o", str(tmp_path / "o.png")], capsys)
    assert code == 2 and message in one_error_line(err)


@pytest.mark.parametrize(
    "sky,message",
    [
        ("type = 'stars'\nseed = -1", "[[sky]] #1 (stars) seed = -1 is not valid: expected a "
         "whole number >= 0"),
        ("type = 'checker'\nn_lon = 1000000", "[[sky]] #1 (checker) n_lon = 1000000 is not "
         "valid: expected a whole number from 1 to 100000"),
        ("type = 'star'\nsigma_deg = 180.00000000001", "[[sky]] #1 (star) sigma_deg = "
         "180.00000000001 is not valid: expected a number in (0, 180) (degrees)"),
    ],
)  # fmt: skip
def test_every_bad_scene_key_is_named_with_its_real_range(tmp_path, capsys, monkeypatch, sky,
                                                          message):  # fmt: skip
    no_render(monkeypatch)
    (tmp_path / "s.toml").write_text(f"[[sky]]\n{sky}\n")
    code, _, err = run(["render", str(tmp_path / "s.toml"), "-o", str(tmp_path / "o.png")],
                       capsys)  # fmt: skip
    assert code == 2 and message in one_error_line(err)


def test_scene_keys_give_the_range_that_is_checked(capsys):
    with pytest.raises(SystemExit):
        cli.main(["render", "--scene-keys"])
    out = capsys.readouterr().out
    assert "  n_lon = 24    # a whole number from 1 to 100000\n" in out
    assert "  seed = 0    # a whole number >= 0\n" in out
    assert "  width = 960    # a whole number from 1 to 1048575 (pixels)\n" in out


def test_a_fov_that_float32_rounds_to_180_renders_in_float64(tmp_path, capsys, monkeypatch):
    # 179.99999999 degrees is in (0, 180) but is pi in float32: the camera refused it
    # as "fov=180.0". The pixels are computed in float64 instead, as for a distance
    # float32 cannot tell from 1.
    import numpy as np

    seen = []

    def render(scene, **kwargs):
        seen.append(scene.camera.fov.dtype)
        return np.zeros((scene.camera.height, scene.camera.width, 3), np.float32)

    monkeypatch.setattr(jl, "render", render)
    args = ["render", "--size", "16x12", "--fov-deg", "179.99999999", "-o", str(tmp_path / "o.exr")]
    code, out, err = run(args, capsys)
    assert code == 0, err
    assert seen == [np.float64] and "FOV = 179.99999999 deg" in out


@pytest.mark.parametrize(
    "extra,message",
    [
        (["--path", "pan", "--start", "1e300"], "--start 1e+300 is not valid: expected a finite "
         "number (degrees), at most 1e+30 in magnitude"),
        (["--path", "orbit", "--stop", "-1e300"], "--stop -1e+300 is not valid"),
        (["--path", "approach", "--start", "1e300"], "--start 1e+300 is not valid: expected a "
         "finite number > 1 (units of R_S), at most 1e+30 in magnitude"),
        (["--path", "approach", "--stop", "-inf"], "--stop -inf is not valid: expected a finite "
         "number > 1 (units of R_S)"),
        (["--path", "zoom", "--start", "180"], "--start 180.0 is not valid: expected a number "
         "in (0, 180) (degrees)"),
        (["--frames", "-1"], "--frames -1 is not valid: expected a whole number from 1 to 10000"),
        (["--fps", "-inf"], "--fps -inf is not valid: expected a number in (0, 1000)"),
        (["{scene}"], "s.toml: [animation] (approach) start = 0.5 is not valid: expected a "
         "finite number > 1 (units of R_S)"),
    ],
)  # fmt: skip
def test_animation_paths_are_checked_before_rendering(tmp_path, capsys, monkeypatch, extra,
                                                      message):  # fmt: skip
    import warnings

    no_render(monkeypatch)
    (tmp_path / "s.toml").write_text("[animation]\nstart = 0.5\n")
    extra = [e.format(scene=tmp_path / "s.toml") for e in extra]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning of an overflow on the way
        code, _, err = run(["animate", "--size", "16x12", *extra, "-o", f"{tmp_path}/a.gif"],
                           capsys)  # fmt: skip
    assert code == 2 and message in one_error_line(err, "animate")
    assert os.listdir(tmp_path) == ["s.toml"]


# -------------------------------------------------------------- the sweep
# Every numeric option of render, animate and fit, and every number of a scene file,
# with values at and beyond every edge: each is refused with one line naming the option
# (or key) and the value, before anything is rendered, or is valid and gives finite
# values. (A valid render is replaced by a stand-in: the sweep checks the inputs.)

EDGES = ["-inf", "inf", "nan", "1e300", "-1e300", "0", "-1", "1e-300", "1.5", str(10**30)]

RENDER = ["--distance", "--fov-deg", "--star-sigma-deg", "--star-brightness", "--floor",
          "--supersample", "--exposure", "--yaw-deg", "--pitch-deg", "--roll-deg",
          "--accuracy"]  # fmt: skip
FIT = ["--psf-sigma-px", "--noise", "--gain", "--star-sigma-deg", "--mass-msun",
       "--distance-m"]  # fmt: skip
FIXED = ["distance", "fov_deg", "yaw_deg", "source_lat_deg", "sigma_deg", "brightness",
         "floor", "psf_sigma"]  # fmt: skip


def _sweep():
    """(command, its arguments, the option the message names, the value typed)."""
    for v in EDGES:
        for flag in RENDER:
            yield "render", [flag, v], flag, v
        yield "render", ["--size", f"{v}x12"], "--size", v
        yield "render", ["--size", f"16x{v}"], "--size", v
        for path in ("approach", "orbit", "pan", "zoom"):
            for flag in ("--start", "--stop"):
                yield "animate", ["--path", path, flag, v], flag, v
        for flag in ("--frames", "--fps"):
            yield "animate", [flag, v], flag, v
        for flag in FIT:
            yield "fit", [flag, v], flag, v
        for name in FIXED:
            yield "fit", ["--fix", f"{name}={v}"], f"--fix {name}=", v


SWEEP = list(_sweep())
# Checked by the renderer (before it compiles): a field of view or a star narrower than
# the float resolution of the pixels' directions depends on the image size and dtype.
AT_RENDER = {"--fov-deg 1e-300": "field of view", "--star-sigma-deg 1e-300": "sigma",
             "--path zoom --start 1e-300": "field of view",
             "--path zoom --stop 1e-300": "field of view"}  # fmt: skip


def _shown(text: str) -> set[str]:
    """The ways a message may show the number typed as `text`."""
    out = {text}
    for kind in (float, int):
        try:
            out.add(repr(kind(text)))
        except (ValueError, OverflowError):
            pass
    return out


@pytest.mark.parametrize("command,extra,flag,value", SWEEP,
                         ids=[f"{c} {' '.join(e)}" for c, e, _, _ in SWEEP])  # fmt: skip
def test_every_number_of_the_command_line_at_its_edges(tmp_path, capsys, monkeypatch, command,
                                                       extra, flag, value):  # fmt: skip
    import jax
    import numpy as np

    at_render = AT_RENDER.get(" ".join(extra))
    rendered, real = [], jl.render

    def render(scene, **kwargs):  # a stand-in: the inputs are what the sweep checks
        rendered.append(scene)
        if at_render:
            return real(scene, **kwargs)  # (its checks come before it compiles)
        for leaf in jax.tree_util.tree_leaves(scene):
            if np.issubdtype(getattr(leaf, "dtype", np.int8), np.inexact):
                assert np.all(np.isfinite(np.asarray(leaf))), (extra, scene)
        cam = scene.camera
        return np.zeros((*cam.batch_shape, cam.height, cam.width, 3), np.float32)

    monkeypatch.setattr(jl, "render", render)
    if command == "fit":  # an image that is not there: valid options end at it
        args = ["fit", str(tmp_path / "none.png"), *extra]
    else:
        out = tmp_path / ("o.exr" if command == "render" else "o.gif")
        frames = ["--frames", "2"] if command == "animate" and "--frames" not in extra else []
        args = [command, "--size", "16x12", "--supersample", "1", *frames, *extra, "-o", str(out)]
    code, stdout, err = run(args, capsys)
    if code == 0:  # valid: rendered (by the stand-in) from finite values
        assert command != "fit" and rendered and "wrote" in stdout
        return
    line = one_error_line(err, command)
    assert code == 2
    if command == "fit" and "none.png' does not exist" in line:
        return  # the options were valid
    if at_render:
        assert at_render in line
        return
    assert not rendered  # refused before rendering
    # (the GIF's own limits on --fps are said by its writer as "fps=...")
    assert flag.lstrip("-") in line and any(s in line for s in _shown(value)), line


EDGE_VALUES = [-math.inf, math.inf, math.nan, 1e300, -1e300, 0, -1, 1e-300, 1.5, 10**30]


def _scene_keys():
    """(the scene dict around a value, the key's name): every number of a scene file."""
    from jaxlens import _scene

    yield from ((lambda v, n=n: {n: v}, n) for n in _scene.TOP_KEYS)
    for table in ("camera", "output", "animation"):
        for name, key in getattr(_scene, f"{table.upper()}_KEYS").items():
            if key.kind not in ("str", "bool"):
                yield (lambda v, t=table, n=name: {t: {n: v}}), name
    for kind in jl.scene_table_types("sky"):
        keys = jl.scene_table_keys("sky", kind)
        for name, key in keys.items():
            if key.kind in ("str", "bool"):
                continue
            # What the key needs beside it: an image, a star list's partner.
            extra = {"path": "p.png"} if "path" in keys else {}
            if name in ("lon_deg", "lat_deg", "size", "plane_distance"):
                extra = {{"lon_deg": "lat_deg", "lat_deg": "lon_deg", "size": "plane_distance",
                          "plane_distance": "size"}[name]: 1.0, **extra}  # fmt: skip
            yield (lambda v, k=kind, n=name, e=extra: {"sky": [{"type": k, n: v, **e}]}), name
    for section in ("motion", "redshift", "disk"):
        for kind in jl.scene_table_types(section):
            for name, key in jl.scene_table_keys(section, kind).items():
                if key.kind not in ("str", "bool"):
                    yield (lambda v, s=section, k=kind, n=name:
                           {"effects": {s: {"type": k, n: v}}}), f"{kind} {name}"  # fmt: skip


SCENE_KEYS = [(make, name, v) for make, name in _scene_keys() for v in EDGE_VALUES]


@pytest.mark.parametrize("make,name,value", SCENE_KEYS)
def test_every_number_of_a_scene_file_at_its_edges(tmp_path, monkeypatch, make, name, value):
    import jax
    import numpy as np

    if "p.png" in str(make(value)):  # an image sky's image, here
        monkeypatch.chdir(tmp_path)
        jl.write_image("p.png", np.full((4, 8, 3), 0.5, np.float32))
    name = name.rpartition(" ")[2]
    try:
        scene = jl.Scene.from_dict(make(value))
    except ValueError as e:
        message = str(e)
        assert name in message and len(message) < 400, message
        shown = {repr(value), repr(float(value)) if abs(value) < 1e300 else repr(value),
                 str(value).lower()}  # fmt: skip
        assert any(s in message for s in shown), message
        return
    for leaf in jax.tree_util.tree_leaves(scene):
        if np.issubdtype(getattr(leaf, "dtype", np.int8), np.inexact):
            assert np.all(np.isfinite(np.asarray(leaf))), (name, value, scene)
