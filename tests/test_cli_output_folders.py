"""The `jaxlens` command creates the folder of an output it is asked to write, and its
parents (`-o out/ring.png` makes `out/`, as image tools do), only once every argument is
checked: a refused command creates no folder, an existing folder and the files in it
are left as they were, and a folder that cannot be made is one error line naming it."""

import os

import pytest
from helpers import run
from PIL import Image

SMALL = ["--size", "8x6", "--supersample", "1", "--sky", "checker"]


@pytest.fixture(autouse=True)
def _no_persistent_cache(monkeypatch):
    monkeypatch.setenv("JAXLENS_CACHE_DIR", "")


def _tree(root):
    """Every path under `root` (relative) and the bytes of each file."""
    out = {}
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            p = os.path.join(folder, name)
            out[os.path.relpath(p, root)] = open(p, "rb").read() if name in files else None
    return out


def test_render_creates_the_output_folder_and_its_parents(tmp_path, capsys):
    out = tmp_path / "out" / "deeper" / "ring.png"
    code, stdout, err = run(["render", *SMALL, "-o", str(out)], capsys)
    assert code == 0, err
    assert f"wrote {out}" in stdout
    with Image.open(out) as im:
        assert im.size == (8, 6)
    assert sorted(os.listdir(out.parent)) == ["ring.png"]  # nothing else in the new folder

    # Into a folder that exists: the folder and the user's files in it are left as they were.
    (out.parent / "mine.txt").write_bytes(b"a user's file")
    before = _tree(tmp_path)
    code, _, err = run(["render", *SMALL, "-o", str(out.parent / "two.png")], capsys)
    assert code == 0, err
    after = _tree(tmp_path)
    assert after.pop(os.path.join("out", "deeper", "two.png")) and after == before


def test_animate_creates_the_output_and_frames_folders(tmp_path, capsys):
    out, frames = tmp_path / "anim" / "a.gif", tmp_path / "f" / "g" / "frames"
    code, stdout, err = run(["animate", *SMALL, "--frames", "2", "--path", "orbit", "-o",
                             str(out), "--frames-dir", str(frames)], capsys)  # fmt: skip
    assert code == 0, err
    with Image.open(out) as im:
        assert im.n_frames == 2
    assert sorted(os.listdir(frames)) == [".jaxlens-frames.json", "frame_0000.png",
                                          "frame_0001.png"]  # fmt: skip


# A refused command, then the same command with its fault removed, into a new folder.
REFUSED = [
    (["render", "--distance", "0.5", "-o", "new/a.png"], [0, 1]),  # inside the horizon
    (["render", "--size", "0x6", "-o", "new/a.png"], [0, 1]),
    (["render", "-o", "new/a.gif"], ["-o", "new/a.png"]),  # an animation: `jaxlens animate`
    (["render", "-o", "new/a.bmp"], ["-o", "new/a.png"]),  # an extension not written
    (["animate", "--fps", "0", "-o", "new/a.gif"], [0, 1]),
    (["animate", "-o", "new/a.png"], ["-o", "new/a.gif"]),  # not an animation
    (["animate", "--path", "zoom", "--start", "200", "-o", "new/a.gif",  # FOV over 180
      "--frames-dir", "new2/frames"], [2, 3]),
]  # fmt: skip


@pytest.mark.parametrize("refused,fix", REFUSED, ids=[" ".join(r) for r, _ in REFUSED])
def test_a_refused_command_creates_no_folder(tmp_path, capsys, refused, fix):
    """`fix`: the indices of the faulty words to drop, or words replacing `-o NAME`."""
    refused = [str(tmp_path / w) if w.startswith("new") else w for w in refused]
    extra = [*SMALL] + (["--frames", "2"] if refused[0] == "animate" else [])
    code, _, err = run([refused[0], *extra, *refused[1:]], capsys)  # the faults come last
    assert code == 2 and err.count("\n") == 1, err
    assert os.listdir(tmp_path) == []  # no folder made, not even the first of them

    if isinstance(fix[0], int):
        fixed = [w for i, w in enumerate(refused[1:]) if i not in fix]
    else:
        at = refused.index("-o")
        fixed = refused[1:at] + [fix[0], str(tmp_path / fix[1])] + refused[at + 2 :]
    code, _, err = run([refused[0], *extra, *fixed], capsys)
    assert code == 0, err
    assert "new" in os.listdir(tmp_path)  # the fault was all that kept it from being made


def test_a_folder_that_cannot_be_made_is_one_line_naming_it(tmp_path, capsys):
    (tmp_path / "file").write_bytes(b"a user's file")
    out = tmp_path / "file" / "sub" / "ring.png"
    code, _, err = run(["render", *SMALL, "-o", str(out)], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert f"output folder '{tmp_path / 'file' / 'sub'}'" in err and "cannot be created" in err
    assert _tree(tmp_path) == {"file": b"a user's file"}
