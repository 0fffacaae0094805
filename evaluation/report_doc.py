"""The report's page: HTML and Markdown written side by side (`ReportDoc`), and the page's style."""

from __future__ import annotations

import base64
import html
import shutil
from pathlib import Path

from evaluation.report_text import html_text, md_text, url

__all__ = ["ReportDoc", "CSS"]


class ReportDoc:
    """Builds the HTML and Markdown side by side so they always hold the same content; text goes
    into both escaped (evaluation/report_text.py: html_text, md_text, url)."""

    def __init__(self, img_dir: Path):
        self.html: list[str] = []
        self.md: list[str] = []
        self.img_dir = img_dir

    def h(self, level: int, text: str, anchor: str | None = None) -> None:
        a = f' id="{anchor}"' if anchor else ""
        self.html.append(f"<h{level}{a}>{html_text(text)}</h{level}>")
        self.md.append(f"\n{'#' * level} {md_text(text)}\n")

    def p(self, text: str, cls: str = "") -> None:
        c = f' class="{cls}"' if cls else ""
        self.html.append(f"<p{c}>{html_text(text)}</p>")
        self.md.append(f"{'> ' if cls == 'warn' else ''}{md_text(text, paragraph_start=True)}\n")

    def table(self, header: list[str], rows: list[list[str]]) -> None:
        th = "".join(f"<th>{html_text(h)}</th>" for h in header)
        trs = "".join("<tr>" + "".join(f"<td>{html_text(c)}</td>" for c in r) + "</tr>" for r in rows)
        self.html.append(f"<table><thead><tr>{th}</tr></thead><tbody>{trs}</tbody></table>")
        self.md.append("| " + " | ".join(md_text(h) for h in header) + " |")
        self.md.append("|" + "---|" * len(header))
        for r in rows:
            self.md.append("| " + " | ".join(md_text(c) for c in r) + " |")
        self.md.append("")

    def details(self, summary: str, header: list[str], rows: list[list[str]]) -> None:
        """A table folded away under a one-line summary (<details>; GitHub's Markdown renders it too)."""
        self.html.append(f"<details><summary>{html_text(summary)}</summary>")
        self.md.append(f"<details><summary>{html_text(summary)}</summary>\n")
        self.table(header, rows)
        self.html.append("</details>")
        self.md.append("</details>\n")

    def links(self, items: list[tuple[str, str]]) -> None:
        """A bullet list of (relative href, text) links to files of the run."""
        lis = "".join(f'<li><a href="{html.escape(url(href))}">{html_text(text)}</a></li>' for href, text in items)
        self.html.append(f"<ul>{lis}</ul>")
        for href, text in items:
            self.md.append(f"- [{md_text(text)}]({url(href)})")
        self.md.append("")

    def _embed(self, src: Path, name_prefix: str) -> tuple[str, str]:
        """Copy `src` into img/ (unless it is there already); its base64 and its name in img/."""
        # gt/, renders/, errors/ and depth/ hold files of the same name: keep the folder in it
        dst_name = src.name if src.name.startswith(name_prefix) else f"{name_prefix}-{src.parent.name}-{src.stem}.png"
        dst = self.img_dir / dst_name
        if src.resolve() != dst.resolve():
            shutil.copyfile(src, dst)
        return base64.b64encode(dst.read_bytes()).decode("ascii"), dst_name

    def images(self, items: list[tuple], name_prefix: str) -> None:
        """A row of images with captions: embedded in the HTML, copied beside the Markdown.

        An item is (path, caption) or (path, caption, (colour bar path, units label)): a false-colour
        map then shows its colour bar, with the units, right under it."""
        figs, mds = [], []
        for item in items:
            src, caption = item[0], item[1]
            cbar = item[2] if len(item) > 2 else None
            b64, dst_name = self._embed(src, name_prefix)
            extra, md_extra = "", ""
            if cbar is not None:
                cb64, cb_name = self._embed(cbar[0], name_prefix)
                alt = f"colour bar: {cbar[1]}"
                extra = f'<img class="cbar" alt="{html_text(alt)}" src="data:image/png;base64,{cb64}">'
                md_extra = f"<br>![{md_text(alt)}]({url(f'{self.img_dir.name}/{cb_name}')})"
            figs.append(
                f'<figure><img alt="{html_text(caption)}" src="data:image/png;base64,{b64}">{extra}'
                f"<figcaption>{html_text(caption)}</figcaption></figure>"
            )
            mds.append(f"![{md_text(caption)}]({url(f'{self.img_dir.name}/{dst_name}')}){md_extra}")
        cls = "row single" if len(figs) == 1 else "row"
        self.html.append(f'<div class="{cls}">' + "".join(figs) + "</div>")
        if any(len(i) > 2 and i[2] is not None for i in items):
            # maps with colour bars: one table cell each, so a bar stays under its map
            self.md.append("| " + " | ".join(md_text(i[1]) for i in items) + " |")
            self.md.append("|" + "---|" * len(items))
            self.md.append("| " + " | ".join(mds) + " |\n")
        else:
            self.md.append(" ".join(mds) + "\n")


CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,sans-serif;margin:2em auto;max-width:1200px;color:#222;padding:0 1em}
h1{border-bottom:2px solid #444}h2{border-bottom:1px solid #ccc;margin-top:2em}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:4px 10px;text-align:right}
th{background:#f0f0f0}td:first-child,th:first-child{text-align:left}
.row{display:flex;flex-wrap:wrap;gap:8px}figure{margin:0;flex:1 1 260px;max-width:100%}
figure img{width:100%;image-rendering:pixelated;border:1px solid #ddd}
figure img.cbar{image-rendering:auto;border:none}figcaption{font-size:.8em;color:#555}
.row:not(.single) figure{max-width:calc(25% - 6px)}
.single figure{flex:0 1 760px}
.warn{background:#fff4d6;border-left:4px solid #e0a800;padding:.5em}.note{color:#666}
details{margin:1em 0}details summary{cursor:pointer;color:#245}
"""
