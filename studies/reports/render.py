"""Markdown to one self-contained HTML page, with markdown-it-py.

The parser is CommonMark with the GFM table extension and **raw HTML disabled**:
any ``<script>``, ``<iframe>`` or other markup in the Markdown (a study's
``table.md``, a text from a results file that escaped :func:`studies.reports.text.md_escape`)
is shown as text, never passed through.  On top of the parser, one core rule and a
few render rules give the page what a report needs:

* headings get GitHub-style ``id`` anchors (:func:`slug`; repeats get ``-1``, ``-2``, ...),
  the same :func:`heading_anchors` returns for a table of contents;
* a paragraph that starts with an image is a ``<figure>``: the image inlined as a base64
  ``data:image/png`` URI (from the ``images`` given; a missing one is replaced by its alt
  text), the rest of the paragraph (or the alt text) its ``<figcaption>``;
* table alignment becomes classes (``right``, ``center``) and every table is wrapped in a
  horizontally scrolling ``<div>``;
* a link that is not an in-page ``#anchor`` is shown as its text (no ``href``): the page
  links nowhere outside itself.

The page has an inline style sheet, no JavaScript, and a Content-Security-Policy that
forbids loading anything but ``data:`` images and the inline style.
"""
from __future__ import annotations

import base64
import html
import re
import struct
from typing import Mapping
from urllib.parse import unquote

from markdown_it import MarkdownIt
from markdown_it.token import Token

__all__ = ["markdown_to_html", "heading_anchors", "slug", "inline_plain", "CSP"]

CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; base-uri 'none'; form-action 'none'"


def slug(text: str, seen: dict[str, int]) -> str:
    """GitHub's heading anchor: lower case, punctuation dropped, spaces to hyphens; repeats get -1, -2, ..."""
    base = re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")
    n = seen.get(base, 0)
    seen[base] = n + 1
    return base if n == 0 else f"{base}-{n}"


def _plain(children) -> str:
    """The text inline tokens show (markup stripped), as for an image's alt text."""
    out = []
    for t in children or ():
        if t.type in ("text", "code_inline"):
            out.append(t.content)
        elif t.type == "image":
            out.append(_plain(t.children))
        elif t.type in ("softbreak", "hardbreak"):
            out.append(" ")
    return "".join(out)


def _png_size(data: bytes) -> tuple[int, int] | None:
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) >= 24:
        return struct.unpack(">II", data[16:24])
    return None


def _html_token(content: str) -> Token:
    return Token("html_inline", "", 0, content=content)


def _rewrite(state) -> None:
    """Core rule: heading anchors, figures, table-cell classes, outside links shown as text."""
    tokens = state.tokens
    seen: dict[str, int] = {}
    for i, tok in enumerate(tokens):
        if tok.type == "heading_open":
            tok.attrSet("id", slug(_plain(tokens[i + 1].children), seen))
        elif tok.type in ("th_open", "td_open"):
            style = str(tok.attrs.pop("style", ""))
            m = re.fullmatch(r"text-align:(left|right|center)", style)
            if m and m.group(1) != "left":
                tok.attrSet("class", m.group(1))
        elif tok.type == "inline" and tok.children:
            _links(tok.children)
            if (tok.children[0].type == "image" and i > 0 and tokens[i - 1].type == "paragraph_open"
                    and tokens[i + 1].type == "paragraph_close"):
                _figure(tokens[i - 1], tok, tokens[i + 1])


def _links(children: list[Token]) -> None:
    """In-page links keep their anchor (unescaped, as the heading ids are); any other link becomes its text."""
    stack = []
    for t in children:
        if t.type == "link_open":
            href = str(t.attrGet("href") or "")
            outside = not href.startswith("#")
            stack.append(outside)
            if outside:
                t.tag, t.attrs = "span", {"class": "link"}
            else:
                t.attrSet("href", unquote(href))
        elif t.type == "link_close" and stack and stack.pop():
            t.tag = "span"


def _figure(p_open: Token, inline: Token, p_close: Token) -> None:
    p_open.tag = p_close.tag = "figure"
    image, rest = inline.children[0], inline.children[1:]
    while rest and rest[0].type in ("softbreak", "hardbreak"):
        rest = rest[1:]
    caption = rest or [Token("text", "", 0, content=_plain(image.children))]
    inline.children = [image, _html_token("<figcaption>"), *caption, _html_token("</figcaption>")]


def _render_image(self, tokens, idx, options, env) -> str:
    tok = tokens[idx]
    name = unquote(str(tok.attrGet("src") or ""))
    alt = _plain(tok.children)
    data = (env or {}).get("images", {}).get(name)
    if data is None:
        return (f'<span class="missing">{html.escape(alt)} (figure {html.escape(name)} not found)</span>')
    size = _png_size(data)
    dims = f' width="{size[0]}" height="{size[1]}"' if size else ""
    src = "data:image/png;base64," + base64.b64encode(data).decode("ascii")
    return (f'<img src="{src}" alt="{html.escape(alt)}" title="{html.escape(name)}" '
            f'data-file="{html.escape(name)}"{dims}>')


def _parser() -> MarkdownIt:
    md = MarkdownIt("commonmark", {"html": False, "linkify": False, "typographer": False, "xhtmlOut": False})
    md.enable("table")
    md.core.ruler.push("cfdesign_report", _rewrite)
    md.add_render_rule("image", _render_image)
    md.add_render_rule("table_open", lambda self, t, i, o, e: '<div class="table-wrap"><table>\n')
    md.add_render_rule("table_close", lambda self, t, i, o, e: "</table></div>\n")
    return md


_MD = _parser()


def heading_anchors(markdown: str) -> list[tuple[int, str, str]]:
    """(level, text, id) of every heading of ``markdown``, with the ids the HTML page gives them."""
    tokens = _MD.parse(markdown)
    return [(int(t.tag[1]), _plain(tokens[i + 1].children), str(t.attrGet("id")))
            for i, t in enumerate(tokens) if t.type == "heading_open"]


def inline_plain(markdown: str) -> str:
    """The text an inline Markdown string shows."""
    return "".join(_plain(t.children) for t in _MD.parseInline(markdown) if t.type == "inline")


_CSS = """
:root { color-scheme: light; }
body { font: 16px/1.55 system-ui, -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif;
       color: #1d232a; background: #fff; margin: 0; }
main { max-width: 72rem; margin: 0 auto; padding: 1.5rem 2rem 4rem; }
h1 { font-size: 1.9rem; margin: 0.5rem 0 0.75rem; border-bottom: 3px solid #2b6cb0; padding-bottom: 0.3rem; }
h2 { font-size: 1.45rem; margin-top: 2.4rem; border-bottom: 1px solid #cbd5e0; padding-bottom: 0.2rem; }
h3 { font-size: 1.2rem; margin-top: 1.8rem; }
h4, h5, h6 { font-size: 1.02rem; margin-top: 1.4rem; }
p, li { max-width: 60rem; }
li { margin: 0.2rem 0; }
code { font-family: ui-monospace, SFMono-Regular, Menlo, Consolas, monospace; font-size: 0.88em;
       background: #f1f4f8; padding: 0.05em 0.3em; border-radius: 3px; }
pre { background: #f1f4f8; padding: 0.6rem 0.8rem; overflow-x: auto; }
pre code { background: none; padding: 0; }
.table-wrap { overflow-x: auto; margin: 0.8rem 0 1.2rem; }
table { border-collapse: collapse; font-size: 0.9rem; }
th, td { border: 1px solid #d5dce4; padding: 0.3rem 0.6rem; vertical-align: top; }
th { background: #edf2f7; text-align: left; }
tbody tr:nth-child(even) { background: #f8fafc; }
td.right, th.right { text-align: right; font-variant-numeric: tabular-nums; }
td.right { white-space: nowrap; }
tbody td:first-child { min-width: 8rem; }
td.center, th.center { text-align: center; }
figure { margin: 1.2rem 0 2rem; }
figure img { display: block; max-width: 100%; height: auto; border: 1px solid #e2e8f0; }
figcaption { font-size: 0.92rem; color: #4a5568; margin-top: 0.4rem; }
a { color: #2b6cb0; }
.missing { color: #9b2c2c; }
@media print { main { max-width: none; } h2 { page-break-after: avoid; } figure { page-break-inside: avoid; } }
"""


def markdown_to_html(markdown: str, images: Mapping[str, bytes] | None = None, title: str = "Report") -> str:
    """A complete, self-contained HTML page from ``markdown`` (see the module docstring).

    Parameters
    ----------
    markdown : str
        CommonMark with GFM tables; raw HTML in it is shown as text.
    images : mapping of str to bytes, optional
        PNG bytes by file name (as the Markdown's ``![alt](file)`` names it); an image
        whose file is not here is replaced by its alt text.
    title : str
        The page title (plain text).

    Returns
    -------
    str
        HTML5 with inline CSS, images as ``data:`` URIs and a Content-Security-Policy that
        forbids loading anything else.
    """
    body = _MD.render(markdown, {"images": dict(images or {})})
    return ("<!DOCTYPE html>\n"
            '<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f'<meta http-equiv="Content-Security-Policy" content="{CSP}">\n'
            '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
            '<meta name="generator" content="cfdesign studies.reports (markdown-it-py)">\n'
            f"<title>{html.escape(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n<main>\n"
            + body + "</main>\n</body>\n</html>\n")
