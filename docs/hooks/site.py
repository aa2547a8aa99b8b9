"""MkDocs hooks of the documentation site (mkdocs.yml, `hooks:`).

- Formulas are converted to MathML when the site is built, so they show with no
  script and no network (a page opened from disk included): browsers render MathML
  natively. `pymdownx.arithmatex` (generic mode) marks the TeX of the Markdown pages
  and the docstrings (`$...$`, `\\(...\\)`, `$$...$$`, `\\[...\\]`) as
  `<span class="arithmatex">\\(...\\)</span>` / `<div class="arithmatex">\\[...\\]</div>`;
  the notebook pages (mkdocs-jupyter) keep `$...$` / `$$...$$` as text in their
  Markdown cells. Each formula goes through `latex2mathml`; one that does not convert
  (or leaves a TeX command unconverted) fails the build, naming the page and the TeX.
- A list that follows a paragraph line directly (the docstrings' "**Arguments:**"
  then "- `x`: ..." lines) is a list: Python-Markdown would otherwise read the items
  as the paragraph's continuation and run them together.
"""

import html
import re
import shutil
from pathlib import Path

from latex2mathml.converter import convert
from markdown import Extension
from markdown.preprocessors import Preprocessor
from mkdocs.exceptions import PluginError
from mkdocs.plugins import event_priority

# ---------------------------------------------------------------------------
# Lists after a paragraph line.

_ITEM = re.compile(r"^(\s*)([-*+]|\d{1,3}[.)])\s+\S")
_RULE = re.compile(r"^\s*([-*_])(\s*\1){2,}\s*$")
_FENCE = re.compile(r"^\s*(`{3,}|~{3,})")


class _ListAfterParagraph(Preprocessor):
    """Puts a blank line before the first item of a list that follows a paragraph line
    (outside fenced code); a list item's continuation lines and later items are left."""

    def run(self, lines: list[str]) -> list[str]:
        out: list[str] = []
        fence = None  # the marker of the open code fence
        in_list = False
        for line in lines:
            if fence is not None:
                if line.strip().startswith(fence):
                    fence = None
                out.append(line)
                continue
            if (m := _FENCE.match(line)) is not None:
                fence = m.group(1)
                in_list = False
                out.append(line)
                continue
            if not line.strip():
                out.append(line)
                continue
            item = _ITEM.match(line) is not None and _RULE.match(line) is None
            if item and not in_list and out and out[-1].strip():
                out.append("")
            if item:
                in_list = True
            elif not line[:1].isspace() and (not out or not out[-1].strip()):
                in_list = False  # a new paragraph after a blank line ends the list
            out.append(line)
        return out


class ListAfterParagraph(Extension):
    def extendMarkdown(self, md) -> None:  # noqa: N802 (Python-Markdown's name)
        md.preprocessors.register(_ListAfterParagraph(md), "jaxlens_lists", 27)


@event_priority(100)  # before mkdocstrings and mkdocs-material's offline plugin read these
def on_config(config):
    config.markdown_extensions.append(ListAfterParagraph())
    config.extra["polyfills"] = [*config.extra.get("polyfills", []), _SHIM_URL]  # see below
    return config


# ---------------------------------------------------------------------------
# Formulas.

_ARITHMATEX = re.compile(
    r'<(span|div) class="arithmatex">\s*(\\\(|\\\[)(.*?)(\\\)|\\\])\s*</\1>', re.S
)
_CELL = re.compile(
    r'(<div class="jp-RenderedHTMLCommon jp-RenderedMarkdown[^"]*"[^>]*>)(.*?)(</div>)', re.S
)
_SKIP = re.compile(r"(<(code|pre|script|style|math)\b.*?</\2>)", re.S)
# TeX between dollars, not across an HTML tag (nbconvert escapes the formula's "<").
_DOLLARS = re.compile(
    r"(?<![\\$])\$\$([^$<>]+?)\$\$|(?<![\\$])\$(?!\s)([^$<>]+?)(?<![\s\\])\$", re.S
)
_DOLLAR = re.compile(r"(?<!\\)\$")
# A paragraph with an open formula, then a one-item list that closes it: nbconvert's
# Markdown parser reads a formula's line break before "- x" as a list, where
# JupyterLab (which takes the formulas out first) reads a minus sign.
_SPLIT = re.compile(r"(<p>(?:(?!</p>).)*)</p>\s*<ul>\s*<li>((?:(?!</li>).)*)</li>\s*</ul>", re.S)
_LEFTOVER = re.compile(r"<m[a-z]+[^>]*>[^<]*\\[A-Za-z]")


def mathml(tex: str, display: bool, where: str) -> str:
    """MathML of one TeX formula; raises `PluginError` naming `where` and the TeX if
    latex2mathml fails or leaves a command unconverted."""
    try:
        out = convert(tex.strip(), display="block" if display else "inline")
    except Exception as e:  # latex2mathml raises its own exception types and others
        raise PluginError(f"{where}: the formula {tex!r} does not convert: {e!r}") from e
    if _LEFTOVER.search(out):
        raise PluginError(f"{where}: the formula {tex!r} leaves TeX in its MathML: {out}")
    return out


def _rejoin(m: re.Match) -> str:
    para, item = m.group(1), m.group(2)
    if len(_DOLLAR.findall(para)) % 2 and len(_DOLLAR.findall(item)) % 2:
        return f"{para}\n- {item}</p>"
    return m.group(0)


def _dollars(text: str, where: str) -> str:
    """Converts `$$...$$` and `$...$` in HTML text, outside code and existing math; a
    dollar left over (a formula not closed) raises `PluginError`."""
    text = _SPLIT.sub(_rejoin, text)
    parts = _SKIP.split(text)
    out = []
    i = 0
    while i < len(parts):
        chunk = parts[i]
        out.append(
            _DOLLARS.sub(
                lambda m: mathml(
                    html.unescape(m.group(1) if m.group(1) is not None else m.group(2)),
                    m.group(1) is not None,
                    where,
                ),
                chunk,
            )
        )
        if i + 1 < len(parts):
            out.append(parts[i + 1])  # a skipped element, whole
        i += 3  # the split yields text, element, tag name, text, ...
    for chunk in out[::2]:
        if (m := _DOLLAR.search(chunk)) is not None:
            context = re.sub(r"<[^>]+>", "", chunk[max(m.start() - 80, 0) : m.end() + 80])
            raise PluginError(f"{where}: a formula is not closed: ...{context}...")
    return "".join(out)


def on_page_content(html_text: str, page, config, files) -> str:
    where = page.file.src_uri
    html_text = _ARITHMATEX.sub(
        lambda m: mathml(html.unescape(m.group(3)), m.group(2) == "\\[", where), html_text
    )
    if where.endswith(".ipynb"):
        html_text = _CELL.sub(
            lambda m: m.group(1) + _dollars(m.group(2), where) + m.group(3), html_text
        )
        _toc_titles(page.toc, where)  # the headings' titles in the table of contents
    return html_text


def _toc_titles(items, where: str) -> None:
    for item in items:
        item.title = _dollars(item.title, where)
        _toc_titles(item.children, where)


# ---------------------------------------------------------------------------
# Search from disk. The `offline` plugin of mkdocs-material inlines the search index
# into search/search_index.js and turns directory URLs off (every link names a file);
# its search worker then runs through the iframe-worker shim, which the plugin would
# load from a CDN. The shim ships here instead (docs/hooks/iframe-worker-shim.js).

_SHIM = Path(__file__).with_name("iframe-worker-shim.js")
_SHIM_URL = "assets/javascripts/iframe-worker-shim.js"


def on_post_build(config):
    target = Path(config.site_dir) / _SHIM_URL
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(_SHIM, target)
