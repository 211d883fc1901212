"""What a report.html does in a real browser (chromium driven by playwright; `conftest.open_reports` finds the
browser or skips): its console errors, the requests it makes outside its own file (routed and refused, so a page
that tries one is caught even where the machine has no network), each image's decoded width, the share of
coloured pixels in each 3D view's WebGL canvas, and the first long table's second column after a click on its
header (sorted by the page's script)."""

from __future__ import annotations

import time
from pathlib import Path

# Counts, in one pass over the canvas's pixels read back from WebGL, those whose channels differ by more than 60
# (coloured by a colour scale; the axes, grid and background a 3D scene draws without data are grey or white).
CANVAS_PIXELS_JS = """() => Array.from(document.querySelectorAll('.view3d canvas')).map(c => {
  const g = c.getContext('webgl2') || c.getContext('webgl') || c.getContext('experimental-webgl');
  if (!g) return {width: c.width, height: c.height, webgl: false, coloured: 0, pixels: c.width * c.height};
  const px = new Uint8Array(4 * g.drawingBufferWidth * g.drawingBufferHeight);
  g.readPixels(0, 0, g.drawingBufferWidth, g.drawingBufferHeight, g.RGBA, g.UNSIGNED_BYTE, px);
  let coloured = 0;
  for (let i = 0; i < px.length; i += 4) {
    if (px[i + 3] > 0 && Math.max(px[i], px[i + 1], px[i + 2]) - Math.min(px[i], px[i + 1], px[i + 2]) > 60) coloured++;
  }
  return {width: c.width, height: c.height, webgl: true, coloured: coloured, pixels: px.length / 4};
}).filter(v => v.width > 0 && v.height > 0)"""

# Clicks the second header of the first sortable table and reads that column back (the page's sort script).
SORT_JS = """() => { const t = document.querySelector('table.sortable'); if (!t) return null;
  const th = t.querySelectorAll('thead th'); const col = th.length > 1 ? 1 : 0; th[col].click();
  return Array.from(t.tBodies[0].rows).map(r => r.cells[col] ? r.cells[col].textContent.trim() : ''); }"""

IMAGES_JS = "() => Array.from(document.images).map(i => (i.complete ? i.naturalWidth : 0))"

# A plotly figure is drawn once `Plotly.newPlot` resolves: its div gets the class js-plotly-plot and, for a 3D
# scene, a canvas inside; then a frame or two later the canvas holds the picture.
VIEWS_READY_JS = """() => Array.from(document.querySelectorAll('.view3d')).every(f =>
  f.querySelector('.js-plotly-plot') !== null && f.querySelector('canvas') !== null)"""


def browse(paths: list[Path], executable: Path, args, screenshot: Path | None = None, settle_ms: int = 400,
           viewport=(1280, 900)) -> list[dict]:
    """Open each of `paths` (files) from file:// in a browser of its own, one page each; returns per page: path,
    errors (console errors and uncaught exceptions), outside (URLs requested outside the file), images (natural
    widths), views3d (per 3D canvas: coloured pixels and their share), seconds (load to checked). A browser per
    page: chromium run as one process (`--single-process`, conftest.BROWSER_ARGS) ends with its first page closed,
    and a second page in it failed ("Target page, context or browser has been closed")."""
    from playwright.sync_api import sync_playwright

    out = []
    with sync_playwright() as p:
        for k, path in enumerate(paths):
            browser = p.chromium.launch(executable_path=str(executable), args=list(args))
            try:
                out.append(_one(browser, Path(path).resolve(), screenshot if k == 0 else None, settle_ms, viewport))
            finally:
                browser.close()
    return out


def _one(browser, path: Path, screenshot, settle_ms: int, viewport) -> dict:
    url = path.as_uri()
    page = browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
    errors, outside = [], []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(f"uncaught: {e}"))

    def route(r):
        if r.request.url == url or r.request.url.startswith("data:"):
            r.continue_()
        else:  # refused: the page must need nothing outside itself
            outside.append(r.request.url)
            r.abort()

    page.route("**/*", route)
    t0 = time.perf_counter()
    page.goto(url, wait_until="load")
    if page.query_selector(".view3d") is not None:
        page.wait_for_function(VIEWS_READY_JS, timeout=60_000)
    page.wait_for_timeout(settle_ms)
    views = page.evaluate(CANVAS_PIXELS_JS)
    for v in views:
        v["coloured_share"] = v["coloured"] / max(v["pixels"], 1)
    result = {"path": str(path), "errors": errors, "outside": outside, "images": page.evaluate(IMAGES_JS),
              "views3d": views, "has_view3d": page.query_selector(".view3d") is not None,
              "sorted_column": page.evaluate(SORT_JS), "seconds": time.perf_counter() - t0}
    if screenshot is not None:
        page.screenshot(path=str(screenshot))
    page.close()
    return result
