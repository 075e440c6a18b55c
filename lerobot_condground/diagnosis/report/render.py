"""The document rendered through Jinja2 templates: HTML with every PNG inlined as a data URI, so the file
can be mailed or archived alone, and Markdown with the PNGs written to `NAME_files/` beside it."""

from __future__ import annotations

import base64
import hashlib
import html
import json
import re
import urllib.parse
from pathlib import Path

from jinja2 import Environment, PackageLoader, StrictUndefined
from markupsafe import Markup

from .sections import Document, Table


def _escape_html(value) -> Markup:
    """Autoescaping with the standard library's entities: markupsafe would write ' as &#39;, and the
    report has always written &#x27;, which readers and tests search for."""
    if hasattr(value, "__html__"):
        return Markup(value.__html__())
    return Markup(html.escape(str(value)))


def _code_spans(text: str) -> Markup:
    """Markdown's `code` spans, in HTML."""
    return Markup(re.sub(r"`([^`]+)`", r"<code>\1</code>", _escape_html(text)))


# Outside code spans, what Markdown would read as markup anywhere in a line: emphasis (an underscore only at a
# word's edge: inside a word it is text), strikethrough, table pipes, escapes, a stray backtick, and a closing
# bracket that a link's destination or label follows (with definitions kept off line starts below, a
# bracket alone, as in an interval, links nothing). Inside a code span every character is literal already.
_MARKDOWN_PUNCTUATION = re.compile(r"([\\`*~|]|\](?=[(\[])|(?<![A-Za-z0-9])_|_(?![A-Za-z0-9]))")
# At a line's start: headings, list items, setext heading underlines and link reference definitions (block
# quotes are escaped HTML).
_LINE_START = re.compile(r"^(\s*)([-+=#\[])|^(\s*\d+)([.)])(?=\s|$)", re.MULTILINE)
_CODE_SPAN = re.compile(r"(`[^`\n]+`)")


def _escape_markdown(value) -> Markup:
    """Text from the inputs (labels, paths, notes) stays inert text in Markdown: HTML is escaped as in the
    HTML report, and every character Markdown reads as markup is backslash-escaped, so a value can make no
    link, image, heading, list or table cell. The report's own `code` spans stay code spans."""
    if hasattr(value, "__html__"):
        return Markup(value.__html__())
    parts = _CODE_SPAN.split(html.escape(str(value), quote=False))
    text = "".join(
        part if i % 2 else _MARKDOWN_PUNCTUATION.sub(r"\\\1", part) for i, part in enumerate(parts)
    )
    return Markup(_LINE_START.sub(lambda m: f"{m[1] or m[3] or ''}\\{m[2] or m[4]}", text))


def _md_row(cells) -> Markup:
    """A Markdown table row's cells (a pipe is escaped, so it cannot end a cell); a line break would end the
    row, so lines are joined with <br>."""
    return Markup(" | ").join(
        Markup("<br>").join(_escape_markdown(line) for line in str(cell).splitlines()) for cell in cells
    )


def _md_columns(table: Table) -> list[str]:
    """Markdown has no spanning headers: the group goes into each column's name."""
    columns = list(table.columns)
    i = 0
    for text, span in table.groups or []:
        for j in range(i, i + span):
            columns[j] = f"{text}: {columns[j]}" if text else columns[j]
        i += span
    return columns


def _environment(autoescape: bool) -> Environment:
    env = Environment(
        loader=PackageLoader(__package__, "templates"),
        autoescape=autoescape,
        finalize=_escape_html if autoescape else None,
        undefined=StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters.update(splitlines=lambda text: str(text).splitlines())
    return env


_HTML = _environment(autoescape=True)
_HTML.filters.update(code_spans=_code_spans, base64=lambda png: base64.b64encode(png).decode("ascii"))
_MARKDOWN = _environment(autoescape=False)
# A link destination is percent-encoded, not backslash-escaped: parentheses and spaces cannot end it.
_MARKDOWN.filters.update(
    md=_escape_markdown,
    md_row=_md_row,
    md_columns=_md_columns,
    url=lambda text: urllib.parse.quote(str(text)),
)


def render_html(doc: Document) -> str:
    return _HTML.get_template("report.html.j2").render(doc=doc)


def render_markdown(doc: Document, files_dir: str) -> tuple[str, dict[str, bytes]]:
    """Markdown text and the PNG files it links, by file name under `files_dir`."""
    text = _MARKDOWN.get_template("report.md.j2").render(doc=doc, files_dir=files_dir)
    return text, {f"{figure.name}.png": figure.png for figure in doc.figures}


# In NAME_files/: the figures the last run wrote with their sha256, the only files a rerun replaces or removes.
MANIFEST = "condground-report.json"


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _written_before(manifest_path: Path) -> dict[str, str | None] | None:
    """The figures an earlier report wrote, by name, with their sha256 (None: no earlier report; a hash of
    None: a manifest of before the hashes). The manifest is a file on disk like any input: a name that is
    not a plain PNG file name is refused, and a figure is removed only if its content is the one listed."""
    if not manifest_path.is_file():
        return None
    try:
        figures = json.loads(manifest_path.read_text())["figures"]
        figures = figures if isinstance(figures, dict) else dict.fromkeys(figures)
        if not all(isinstance(n, str) and re.fullmatch(r"[\w.-]+\.png", n) and n[0] != "." for n in figures):
            raise ValueError("a figure name is not a plain PNG file name")
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{manifest_path} is damaged ({err}); choose another --output") from None
    return figures


def write_report(doc: Document, html_path: Path) -> tuple[Path, Path]:
    """Writes the HTML to `html_path` and the Markdown beside it (same name, .md, figures in NAME_files/).
    Overwrites and removes only files an earlier report wrote there; anything else is an error."""
    if html_path.suffix.lower() not in (".html", ".htm"):
        raise ValueError(
            f"--output={html_path} is not allowed; allowed: a file name ending in .html "
            f"(the Markdown goes beside it as {html_path.stem}.md)"
        )
    md_path = html_path.with_suffix(".md")
    files_dir = html_path.parent / f"{html_path.stem}_files"
    manifest_path = files_dir / MANIFEST
    before = _written_before(manifest_path)
    text, files = render_markdown(doc, files_dir.name)
    ours = set() if before is None else {html_path, md_path, *(files_dir / n for n in before)}
    foreign = [
        p for p in (html_path, md_path, *(files_dir / n for n in files)) if p.exists() and p not in ours
    ]
    if foreign:
        raise FileExistsError(
            f"--output={html_path} would overwrite {foreign[0]}, which condground report did not write; "
            "choose another --output or move that file away"
        )
    if files_dir.exists() and not files_dir.is_dir():
        raise FileExistsError(
            f"--output={html_path}: {files_dir} is a file; the report's figures go in that folder"
        )
    # Writing through a link would overwrite whatever it points at.
    links = [
        p
        for p in (html_path, md_path, files_dir, manifest_path, *(files_dir / n for n in files))
        if p.is_symlink()
    ]
    if links:
        raise PermissionError(
            f"--output={html_path} would write through the link {links[0]}; remove it or choose another --output"
        )
    html = render_html(doc)
    files_dir.mkdir(parents=True, exist_ok=True)
    # The manifest claims every file before any is written: a run that dies half way leaves files its
    # rerun knows as its own, not files that block it.
    written = {name: _sha(png) for name, png in files.items()}
    manifest_path.write_text(json.dumps({"figures": {**(before or {}), **written}}, indent=1, sort_keys=True))
    html_path.write_text(html, encoding="utf-8")
    for name, sha in (before or {}).items():  # a rerun with fewer figures must not leave old ones behind
        stale = files_dir / name
        if name not in files and sha is not None and stale.is_file() and _sha(stale.read_bytes()) == sha:
            stale.unlink()
    for name, png in files.items():
        (files_dir / name).write_bytes(png)
    md_path.write_text(text, encoding="utf-8")
    manifest_path.write_text(json.dumps({"figures": written}, indent=1, sort_keys=True))
    return html_path, md_path
