"""The report as a list of blocks, rendered to Markdown and to one self-contained HTML page.

Blocks: a paragraph (str, with `code` and **bold**), Bullets, a sub-heading (Sub), a Table (a DataFrame of
text and numbers), a Figure (a PNG under the folder, embedded as base64 in HTML) and Details (blocks
collapsed under a summary line: <details> in HTML and in GitHub's Markdown).
"""

from __future__ import annotations

import base64
import html
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from jsve.report._format import html_table, inline_html, markdown_table


@dataclass(frozen=True)
class Bullets:
    items: tuple[str, ...]


@dataclass(frozen=True)
class Sub:
    heading: str


@dataclass(frozen=True)
class Table:
    frame: pd.DataFrame


@dataclass(frozen=True)
class Figure:
    path: Path
    alt: str


@dataclass(frozen=True)
class Details:
    summary: str
    blocks: tuple = ()


@dataclass
class Section:
    heading: str
    blocks: list = field(default_factory=list)


STYLE = (
    "body{font-family:sans-serif;max-width:72em;margin:2em auto;padding:0 1em;line-height:1.4}"
    "table{border-collapse:collapse;margin:0.6em 0 1em;font-size:90%}"
    "td,th{border:1px solid #ccc;padding:2px 6px;vertical-align:top}th{background:#f4f4f4}"
    "td.n{white-space:nowrap}td.n,th.n{text-align:right}td.w,th.w,td.t{text-align:left}td.w{white-space:nowrap}"
    "img{max-width:100%}details{margin:0.5em 0 1em}summary{cursor:pointer;font-weight:bold}"
    "code{background:#f4f4f4;padding:0 3px}"
)


def _markdown(blocks, root: Path) -> list[str]:
    lines: list[str] = []
    for block in blocks:
        if isinstance(block, str):
            lines += [block, ""]
        elif isinstance(block, Bullets):
            lines += [f"- {item}" for item in block.items] + [""]
        elif isinstance(block, Sub):
            lines += [f"### {block.heading}", ""]
        elif isinstance(block, Table):
            lines += [markdown_table(block.frame), ""]
        elif isinstance(block, Figure):
            lines += [f"![{block.alt}]({block.path.relative_to(root).as_posix()})", ""]
        elif isinstance(block, Details):
            lines += ["<details>", f"<summary>{html.escape(block.summary)}</summary>", ""]
            lines += _markdown(block.blocks, root)
            lines += ["</details>", ""]
        else:
            raise TypeError(f"not a report block: {type(block).__name__}")
    return lines


def _html(blocks) -> list[str]:
    out: list[str] = []
    for block in blocks:
        if isinstance(block, str):
            out.append(f"<p>{inline_html(block)}</p>")
        elif isinstance(block, Bullets):
            out.append("<ul>" + "".join(f"<li>{inline_html(i)}</li>" for i in block.items) + "</ul>")
        elif isinstance(block, Sub):
            out.append(f"<h3>{html.escape(block.heading)}</h3>")
        elif isinstance(block, Table):
            out.append(html_table(block.frame))
        elif isinstance(block, Figure):
            data = base64.b64encode(block.path.read_bytes()).decode("ascii")
            out.append(f'<img alt="{html.escape(block.alt)}" src="data:image/png;base64,{data}">')
        elif isinstance(block, Details):
            out.append(f"<details><summary>{inline_html(block.summary)}</summary>")
            out += _html(block.blocks)
            out.append("</details>")
        else:
            raise TypeError(f"not a report block: {type(block).__name__}")
    return out


FOOTER = "Every number above comes from the folder's tables (Parquet and CSV); docs/report.md describes them."


def render(title: str, sections: list[Section], root: Path) -> tuple[str, str]:
    """(Markdown, HTML) of the report; figure paths are relative to `root` in Markdown."""
    md = [f"# {title}", ""]
    body = []
    for section in sections:
        md += [f"## {section.heading}", ""] + _markdown(section.blocks, root)
        body.append(f"<h2>{html.escape(section.heading)}</h2>")
        body += _html(section.blocks)
    md.append(FOOTER)
    page = (
        f'<!DOCTYPE html>\n<html><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
        f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>\n"
        + "\n".join(body)
        + f"\n<p>{html.escape(FOOTER)}</p></body></html>\n"
    )
    return "\n".join(md) + "\n", page
