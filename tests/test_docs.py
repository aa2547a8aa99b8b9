"""The documentation site builds from the repository with no warning (mkdocs --strict:
every Markdown link and anchor resolves), every link and image of the built pages points
at a file of the site, and the API reference documents every public name. The notebooks
are included unexecuted here (their run is tests of their own); `make docs` executes
them."""

import os
import re
import subprocess
import sys
from pathlib import Path
from urllib.parse import unquote

import pytest

import jaxlens as jl

pytest.importorskip("mkdocs", reason="the docs build needs mkdocs (test extras)")
pytest.importorskip("mkdocs_jupyter", reason="the docs build needs mkdocs-jupyter (test extras)")
pytest.importorskip("mkdocstrings", reason="the docs build needs mkdocstrings (test extras)")

ROOT = Path(__file__).resolve().parents[1]


def test_docs_build_strict_and_every_link_resolves(tmp_path):
    site = tmp_path / "site"
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1", JAXLENS_DOCS_EXECUTE="false")
    run = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
         "-d", str(site)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0 and "WARNING" not in run.stderr, run.stderr[-4000:]

    broken = []
    pages = list(site.rglob("*.html"))
    for page in pages:
        for url in re.findall(r'(?:href|src)="([^"]*)"', page.read_text()):
            if re.match(r"([a-z]+:|//|#)", url) or not url:
                continue  # other sites (not fetched here), in-page anchors
            path = unquote(url.split("#")[0].split("?")[0])
            base = site if path.startswith("/") else page.parent  # 404.html: from the root
            target = (base / path.lstrip("/")).resolve()
            if target.is_dir():
                target /= "index.html"
            if not target.is_file():
                broken.append(f"{page.relative_to(site)}: {url}")
    assert len(pages) > 20 and not broken, broken

    api = (site / "api" / "index.html").read_text()
    missing = [n for n in jl.__all__ if f'id="jaxlens.{jl._WHERE[n]}.{n}"' not in api]
    assert not missing, f"docs/api.md lacks {missing}"
