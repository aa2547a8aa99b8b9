"""The documentation site builds from the repository with no warning (mkdocs --strict:
every Markdown link and anchor resolves); every link and image of the built pages points
at a file of the site (not a folder: the site is browsed from disk, file://, where a
folder opens as a listing); the API reference gives every public name a heading
`jaxlens.NAME` and its signature, its "**Arguments:**" as lists; formulas are MathML,
with no TeX left. The site is built once for the module (about 10 s). The notebooks are
included unexecuted here (their run is tests of their own); `make docs` executes them."""

import ast
import html
import inspect
import os
import re
import subprocess
import sys
from pathlib import Path
from urllib.parse import unquote

import equinox as eqx
import pytest

import jaxlens as jl

pytest.importorskip("mkdocs", reason="the docs build needs mkdocs (test extras)")
pytest.importorskip("mkdocs_jupyter", reason="the docs build needs mkdocs-jupyter (test extras)")
pytest.importorskip("mkdocstrings", reason="the docs build needs mkdocstrings (test extras)")
pytest.importorskip("latex2mathml", reason="the docs build needs latex2mathml (test extras)")

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("docs")
    site = tmp / "site"
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1", JAXLENS_DOCS_EXECUTE="false")
    run = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
         "-d", str(site)],
        cwd=tmp, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0 and "WARNING" not in run.stderr, run.stderr[-4000:]
    return site


def broken_links(site: Path) -> list[str]:
    """Every href and src of every page that does not name a file of the site, relative
    to the page. A folder is broken (opened from disk it is a listing, not its
    index.html); a path from the root ("/...") too, except on 404.html, which only a
    server shows (at any depth, so its links start at the root)."""
    broken = []
    for page in site.rglob("*.html"):
        for url in re.findall(r'(?:href|src)="([^"]*)"', page.read_text()):
            if re.match(r"([a-z]+:|//|#)", url) or not url:
                continue  # other sites (not fetched here), in-page anchors
            path = unquote(url.split("#")[0].split("?")[0])
            if path.startswith("/") and page.name != "404.html":
                broken.append(f"{page.relative_to(site)}: {url} (from the root)")
                continue
            base = site if path.startswith("/") else page.parent
            if not (base / path.lstrip("/")).resolve().is_file():
                broken.append(f"{page.relative_to(site)}: {url}")
    return broken


def test_docs_build_strict_and_every_link_resolves_to_a_file(site):
    pages = list(site.rglob("*.html"))
    broken = broken_links(site)
    assert len(pages) > 20 and not broken, broken[:20]
    # The search works from disk: its index is inlined into a script, and the worker's
    # shim ships with the site (no CDN).
    assert (site / "search" / "search_index.js").is_file()
    assert (site / "assets" / "javascripts" / "iframe-worker-shim.js").is_file()
    assert "unpkg.com" not in (site / "index.html").read_text()


def _constructed(obj) -> bool:
    """Whether the API page owes `obj` a signature: functions, and classes one builds
    (not abstract bases, enumerations or exceptions: none is built by a user)."""
    if not inspect.isclass(obj):
        return callable(obj)
    return not (
        obj.__name__.startswith("Abstract")
        or inspect.isabstract(obj)
        or issubclass(obj, (eqx.Enumeration, BaseException))
    )


def api_entries(site: Path) -> dict[str, tuple[str, str | None]]:
    """Each `<h3 id="jaxlens.NAME">` of the API page: the heading's text, and the text
    of the signature block that follows it (None if there is none)."""
    page = (site / "api.html").read_text()
    entries = {}
    for part in re.split(r'(?=<h3 id="jaxlens\.)', page)[1:]:
        name = re.match(r'<h3 id="jaxlens\.([^"]+)"', part).group(1)
        heading = part[: part.index("</h3>")]
        head = part[: part.index("doc-contents")]
        sig = re.search(r'<div class="doc-signature.*?</code>', head, re.S)
        heading = " ".join(html.unescape(re.sub(r"<[^>]+>", " ", heading)).split())
        if sig is not None:  # the code's tokens are spans: join them as written
            sig = " ".join(html.unescape(re.sub(r"<[^>]+>", "", sig.group(0))).split())
        entries[name] = (heading, sig)
    return entries


def test_api_reference_names_every_public_name_with_its_signature(site):
    entries = api_entries(site)
    assert sorted(entries) == sorted(jl.__all__), (
        f"docs/api.md lacks {sorted(set(jl.__all__) - set(entries))}, "
        f"has beside the public names {sorted(set(entries) - set(jl.__all__))}"
    )
    wrong = []
    for name, (heading, sig) in entries.items():
        obj = getattr(jl, name)
        if heading.split()[0] != f"jaxlens.{name}":
            wrong.append(f"{name}: heading {heading!r}")
        elif _constructed(obj) and not (sig or "").startswith(f"{name}("):
            wrong.append(f"{name}: signature {sig!r}")
        elif _constructed(obj) and inspect.isclass(obj):
            # The constructor's own arguments, by name (equinox writes them from the
            # fields; docs/hooks/griffe_equinox.py tells the API page).
            params = [p for p in inspect.signature(obj).parameters]
            args = ast.parse(f"def f{sig.removeprefix(name)}: pass").body[0].args
            shown = [a.arg for a in args.posonlyargs + args.args + args.kwonlyargs]
            if shown != params:
                wrong.append(f"{name}: signature {sig!r}, constructor {params}")
    assert not wrong, wrong


def test_api_reference_argument_lists_render_as_lists(site):
    """The docstrings' "**Arguments:**" followed by "- `x`: ..." lines, with no blank line
    between: a list, not one paragraph with the items run together."""
    page = (site / "api.html").read_text()
    run_together = re.findall(r"<p>((?:(?!</p>).)*\n- (?:(?!</p>).)*)</p>", page, re.S)
    assert not run_together, run_together[:3]
    alone = page.count("<p><strong>Arguments:</strong></p>")  # the others are sentences
    assert alone >= 15 and page.count("<p><strong>Arguments:</strong></p>\n<ul>") == alone


def raw_tex(page: Path) -> list[str]:
    """TeX left in a page's text (outside code, scripts and MathML): the delimiters
    \\( \\) \\[ \\] and dollars."""
    text = re.sub(r"<(code|pre|script|style|math)\b.*?</\1>", "", page.read_text(), flags=re.S)
    text = html.unescape(re.sub(r"<[^>]+>", " ", text))
    return re.findall(r".{0,40}(?:\\[()[\]]|\$).{0,40}", text)


def test_formulas_are_mathml_with_no_tex_left(site):
    pages = list(site.rglob("*.html"))
    left = {str(p.relative_to(site)): raw_tex(p) for p in pages}
    left = {page: found for page, found in left.items() if found}
    assert not left, left
    for page, least in [("index.html", 1), ("effects.html", 50), ("api.html", 300),
                        ("tutorials/05_sources_at_a_distance.html", 50)]:  # fmt: skip
        assert (site / page).read_text().count("<math ") >= least, page


def test_a_formula_that_does_not_convert_fails_the_build():
    """The hook raises (mkdocs stops) on TeX that latex2mathml rejects or leaves
    unconverted, and on a notebook formula left open, rather than print raw TeX."""
    import importlib.util

    from mkdocs.exceptions import PluginError

    spec = importlib.util.spec_from_file_location("site_hooks", ROOT / "docs/hooks/site.py")
    hooks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hooks)
    assert "<msup>" in hooks.mathml("c^2", False, "page.md")
    for tex in ["x^", r"\left( x", r"\notacommand x"]:
        with pytest.raises(PluginError, match="page.md"):
            hooks.mathml(tex, False, "page.md")
    assert "<math" in hooks._dollars("<p>a $x^2$ b</p>", "nb.ipynb")
    with pytest.raises(PluginError, match="not closed"):
        hooks._dollars("<p>a $x^2 b</p>", "nb.ipynb")
