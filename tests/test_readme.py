"""The README's snippets, run as a new user would run them, in order, in an empty
folder: the Python blocks in one namespace, the `jaxlens` command lines through the
command's `main` (same arguments, same outputs; in this process, so the programs the
other tests compiled are reused). The image the README's Python renders is then fitted
to within 1 % or flagged, by `fit_ring` and by `jaxlens fit --json`.

Not run: `make demo` / `make test` (the set-up itself, which runs this suite) and
`pip install` (this checkout is installed).
"""

import contextlib
import io
import json
import math
import re
import shlex
from pathlib import Path

import pytest

from jaxlens import cli

ROOT = Path(__file__).resolve().parents[1]


def _blocks(path: Path) -> list[tuple[str, str]]:
    """(language, code) of each fenced block of a Markdown file."""
    return re.findall(r"^```(\w*)\n(.*?)^```", path.read_text(), flags=re.M | re.S)


def _commands(code: str) -> list[list[str]]:
    """The `jaxlens` command lines of a shell block, as argument lists."""
    out = []
    for line in code.replace("\\\n", " ").splitlines():
        argv = shlex.split(line, comments=True)
        if argv and argv[0].endswith("jaxlens"):
            out.append(argv[1:])
    return out


def _run_cli(argv) -> str:
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = cli.main(argv)
    assert code == 0, (argv, code)
    return stdout.getvalue()


def _within_1_percent_or_flagged(distance, fov_deg, valid, message):
    close = abs(distance / 20.0 - 1) < 0.01 and abs(fov_deg / 60.0 - 1) < 0.01
    assert close or (not valid and message), (distance, fov_deg, valid, message)
    return close


def test_readme_snippets(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("JAXLENS_CACHE_DIR", "")  # no persistent cache from a test
    (tmp_path / "out").mkdir()

    blocks = _blocks(ROOT / "README.md")
    namespace, ran, outputs = {}, [], []
    for lang, code in blocks:
        if "make demo" in code or lang not in ("python", "bash"):
            continue
        if lang == "python":
            exec(compile(code, "README.md", "exec"), namespace)
        else:
            for argv in _commands(code):
                outputs.append(_run_cli(argv))
        ran.append(lang)
    assert ran.count("python") >= 2 and len(outputs) >= 3  # render, fit; three commands

    for name in ("out/ring.png", "out/approach.gif", "ring.png"):
        assert (tmp_path / name).stat().st_size > 0, name
    # Nothing but the outputs (no stray temporaries, no frame folder unasked for).
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["approach.gif", "ring.png"]

    # The Python render: the image it wrote, of the camera's size.
    assert namespace["image"].shape == (360, 480, 3)
    # The fit of the README's own render: 1 % or flagged, in Python and on the CLI.
    fit = namespace["fit"]
    _within_1_percent_or_flagged(fit.distance, fit.fov_deg, fit.valid, fit.message)
    d_m, _ = fit.distance_m(4.3e6)
    assert d_m == pytest.approx(fit.distance * 4.3e6 * 2953.25, rel=1e-6)
    out = json.loads(outputs[-1].strip().splitlines()[-1])
    _within_1_percent_or_flagged(out["distance"], out["fov_deg"], out["valid"], out["message"])
    assert out["distance"] == pytest.approx(fit.distance, rel=1e-6)
    assert out["distance_m"] == pytest.approx(out["distance"] * 4.3e6 * 2953.25, rel=1e-6)
    assert math.isfinite(out["distance_err"]) and out["transfer"] == "srgb"
