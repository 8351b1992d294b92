"""Figures of the reports: matplotlib figures without a display (no pyplot state), turned
into PNG bytes. matplotlib is imported only when a figure is drawn."""
from __future__ import annotations

import io

__all__ = ["new_figure", "png_bytes", "wrap_lines"]


def new_figure(w: float, h: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(w, h), dpi=100, layout="constrained")


def png_bytes(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def wrap_lines(s: str, width: int) -> list[str]:
    import textwrap

    return textwrap.wrap(s, width) or [s]
