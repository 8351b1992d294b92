"""A real headless browser for the HTML reports' tests: Debian's chromium, driven directly.

check_page() loads a report at a given width and answers, from the page itself after it
loaded: how many images it has, how many of them failed to load, and which elements reach
beyond the window's width (horizontal overflow). screenshot() saves the whole page as PNG."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

__all__ = ["browser", "check_page", "screenshot", "NO_BROWSER"]

NO_BROWSER = "no headless browser installed (Debian: apt-get install chromium)"

_PROBE = """<script>
window.addEventListener('load', () => {
  const W = document.documentElement.clientWidth;
  const imgs = [...document.images];
  const over = [...document.querySelectorAll('body *')]
    .filter(e => e.getBoundingClientRect().right > W + 1)
    .map(e => e.tagName + (e.className ? '.' + e.className : ''));
  document.body.setAttribute('data-probe', JSON.stringify({
    images: imgs.length,
    broken: imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length,
    clientWidth: W, scrollWidth: document.documentElement.scrollWidth,
    height: document.documentElement.scrollHeight, overflow: over.slice(0, 8),
    h2: [...document.querySelectorAll('h2')].map(h => h.textContent)}));
});
</script>"""


def browser() -> str | None:
    return next((p for p in (shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")) if p), None)


def _run(args: list[str], timeout: float = 120.0) -> str:
    with tempfile.TemporaryDirectory() as profile:
        cmd = [browser(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--disable-sync", "--no-first-run", "--hide-scrollbars",
               f"--user-data-dir={profile}", *args]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=True).stdout


def check_page(html: Path, width: int = 1280) -> dict:
    """What the page says about itself once loaded at `width` px (a copy with a probe script)."""
    probe = html.with_name(html.stem + ".probe.html")
    probe.write_text(html.read_text(encoding="utf-8").replace("</body>", _PROBE + "</body>"), encoding="utf-8")
    try:
        dom = _run([f"--window-size={width},900", "--virtual-time-budget=10000", "--dump-dom", probe.as_uri()])
    finally:
        probe.unlink()
    m = re.search(r'data-probe="([^"]*)"', dom)
    assert m, "the page never finished loading"
    return json.loads(m.group(1).replace("&quot;", '"').replace("&amp;", "&"))


def screenshot(html: Path, png: Path, width: int = 1280, height: int = 900) -> Path:
    """The page at `width` x `height` px as a PNG (height: the page's, to have all of it)."""
    _run([f"--window-size={width},{height}", "--virtual-time-budget=10000", f"--screenshot={png}", html.as_uri()])
    return png
