"""What every HTML report shares: the page style, escaping, embedded PNG images, and the
atomic writing of the page with its plots. A report is one self-contained file."""
from __future__ import annotations

import base64
import html
from pathlib import Path

from ..files import atomic_write, write_text_atomic

__all__ = ["CSS", "escape", "img_tag", "write_html_and_plots"]


CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;max-width:1150px;margin:1.5em auto;
padding:0 1em;color:#212529;line-height:1.45}
h1{font-size:1.5em;margin-bottom:.2em}h2{font-size:1.2em;margin-top:1.8em;border-bottom:1px solid #dee2e6}
.headline{font-size:1.15em;background:#f1f3f5;border-left:5px solid #e8590c;padding:.7em 1em;margin:1em 0}
.headline.none{border-left-color:#2b8a3e}.headline p{margin:.3em 0}.headline p:first-child{font-weight:600}
table{border-collapse:collapse;margin:.5em 0;font-size:.9em}
th,td{border:1px solid #dee2e6;padding:.3em .55em;text-align:left;vertical-align:top}
th{background:#f8f9fa}td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
tr.verdict td{background:#fff4e6}tr.failed td{color:#868e96}td.err{color:#c92a2a;font-family:monospace;font-size:.9em}
.small{font-size:.85em;color:#495057}.explain{font-size:.9em;color:#495057;margin:.3em 0 1em}
img{max-width:100%;height:auto;display:block;margin:.6em 0}
.yes{color:#2b8a3e;font-weight:700}.no{color:#adb5bd}
code{background:#f1f3f5;padding:0 .2em}
"""


def escape(s) -> str:
    return html.escape(str(s))


def img_tag(png: bytes, alt: str) -> str:
    return f'<img alt="{escape(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode("ascii")}">'


def write_html_and_plots(path, html_text: str, plots: dict[str, bytes], png_dir=None) -> None:
    """A report's HTML file (atomically) and, with `png_dir`, its plots as NAME.png there."""
    if png_dir is not None:
        png_dir = Path(png_dir)
        png_dir.mkdir(parents=True, exist_ok=True)
        for name, data in plots.items():
            atomic_write(png_dir / f"{name}.png", data)
    write_text_atomic(path, html_text)
