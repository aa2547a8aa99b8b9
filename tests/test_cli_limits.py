"""The command line's limits: every bad value, however large, odd or endless, is one
readable line on stderr naming the option (or scene key) and the value, exit code 2,
before anything is rendered."""

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
