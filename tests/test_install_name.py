"""The name users are told to install is this project's distribution name: `jaxlens` on
PyPI is another project, so every `pip install` line in the README, the docs, the
notebooks and the library's own messages must name the distribution of
`pyproject.toml` (`import jaxlens` is unchanged)."""

import importlib.metadata
import re
import tomllib
from pathlib import Path

import jaxlens as jl

ROOT = Path(__file__).resolve().parents[1]
DIST = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["name"]

# A requirement after `pip install` (options skipped) naming this project: jaxlens,
# jaxlens-bh, "jaxlens-bh[video]", 'jaxlens[fits]', ... The name is what precedes
# the extras.
_INSTALL = re.compile(r"pip install\s+(?:-\S+\s+)*[\"'`]?(jaxlens[\w.-]*)")


def _texts():
    for pattern in ("README.md", "docs/**/*.md", "notebooks/*.ipynb", "jaxlens/**/*.py",
                    "CONTRIBUTING.md"):  # fmt: skip
        for path in ROOT.glob(pattern):
            yield path.relative_to(ROOT), path.read_text()


def test_every_install_line_names_the_distribution():
    seen, wrong = 0, []
    for path, text in _texts():
        for name in _INSTALL.findall(text):
            seen += 1
            if name != DIST:
                wrong.append(f"{path}: pip install {name}")
    assert seen >= 8 and not wrong, (DIST, wrong)  # README, docs index, extras' messages


def test_the_readme_and_docs_home_install_it_first():
    for page in ("README.md", "docs/index.md"):
        first = _INSTALL.search((ROOT / page).read_text())
        assert first and first.group(1) == DIST, page


def test_the_installed_distribution_is_this_package():
    assert DIST != "jaxlens"  # taken on PyPI by an unrelated project
    assert importlib.metadata.version(DIST) == jl.__version__
    files = importlib.metadata.files(DIST) or []
    top = {f.parts[0] for f in files}
    assert "jaxlens" in top or any(str(f).endswith(".pth") for f in files), top
