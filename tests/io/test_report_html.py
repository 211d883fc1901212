"""report.html (`dstereo.io.report_html`): the markdown subset the writers use, the page's parts (figures embedded,
long tables sortable, warnings beside their section, the summary), and the page in a real browser, with controls
that show each browser check can fail (an outside request, a script error, a 3D view with nothing drawn)."""

import base64
import re

import numpy as np
import pytest

from conftest import DRAWN_SHARE, assert_reports_render, open_reports
from dstereo.io.report_html import Check, Headline, inline, markdown_blocks, render, write_report_html
from dstereo.io.view3d import cloud_view, decimation


def _png(path, w=40, h=30):
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.zeros((h, w, 3), np.uint8)
    img[:, : w // 2] = (0, 0, 255)
    cv2.imwrite(str(path), img)


REPORT = """# Camera calibration: `images`

- board: 9 x 6
- images: 12 usable

## Result

| parameter | value | +- |
|---|---|---|
{rows}

**Model:** fine.

## Projection uncertainty

Std of the projected pixel.

![projection uncertainty](plots/projection_uncertainty.png)
![fx](plots/fx.png)

## Coverage

- warning: upper-right image corner holds only 0.5% of the corners
- plain item
  continued here

## Warnings

- projection uncertainty: 3 grid pixels masked
- camera left: something else
"""


def _folder(tmp_path, name="report"):
    folder = tmp_path / name
    rows = "\n".join(f"| p{i} | {10 - i}.5 | 0.{i} |" for i in range(12))
    folder.mkdir()
    (folder / "report.md").write_text(REPORT.format(rows=rows))
    _png(folder / "plots" / "projection_uncertainty.png")
    _png(folder / "plots" / "fx.png")
    return folder


def test_blocks_of_the_subset():
    blocks = markdown_blocks("# T\n\npara one\nline two\n- a\n- b\n  more\n\n| x | y \\| z |\n|---|---|\n| 1 | 2 |\n"
                             "![cap](f.png)\n```\ncode <b>\n```\n")
    kinds = [b.kind for b in blocks]
    assert kinds == ["heading", "paragraph", "list", "table", "figure", "code"]
    assert blocks[1].text == "para one line two"
    assert blocks[2].items == ["a", "b more"]
    assert blocks[3].items == [["x", "y | z"], ["1", "2"]]  # an escaped pipe stays in its cell
    assert (blocks[4].text, blocks[4].items) == ("f.png", ["cap"])
    assert blocks[5].text == "code <b>"


def test_inline_escapes_and_marks():
    assert inline("a < b & **c** `x<y` [f](d/e.txt)") == ('a &lt; b &amp; <strong>c</strong> <code>x&lt;y</code> '
                                                           '<a href="d/e.txt">f</a>')
    assert inline("2 * 3 * 4") == "2 * 3 * 4"  # no emphasis on lone stars


def test_page_embeds_figures_sorts_long_tables_and_places_warnings(tmp_path):
    folder = _folder(tmp_path)
    (folder / "left").mkdir()
    (folder / "left" / "report.html").write_text("")  # a rig's camera: its warnings link its own report
    (folder / "report.md").write_text((folder / "report.md").read_text() + "- camera left: too few views\n")
    headline = Headline([("fx", "1000.0 +- 1.2 px")], [Check("identifiability", True, "fine"),
                                                        Check("residual pattern", False, "too simple")])
    page = write_report_html(folder, headline).read_text()
    assert "<script src" not in page and "<link" not in page and 'src="plots/' not in page
    uris = re.findall(r'<img src="data:image/png;base64,([^"]+)"', page)
    assert len(uris) == 2 and base64.b64decode(uris[0]) == (folder / "plots/projection_uncertainty.png").read_bytes()
    assert page.count('class="sortable"') == 1  # the 12-row table; not the 1-row summary
    assert "Standard deviation of each pixel's projection" in page  # the figure's caption
    assert "fx over the image subsets" in page  # a parameter's figure
    # the warning whose subject names a section is shown there; the other stays under Warnings; both at the top
    section = page[page.index('id="projection-uncertainty"'):page.index('id="coverage"')]
    assert "3 grid pixels masked" in section
    rest = page[page.index('id="warnings"'):]
    assert "camera left: something else" in rest and "3 grid pixels masked" not in rest
    top = page[page.index('class="summary"'):page.index("<nav>")]
    assert "Warnings (4)" in top and "1000.0 +- 1.2 px" in top and "too simple" in top
    assert 'too few views <a href="left/report.html">(its report)</a>' in top
    assert '<li class="fail">' in top and '<li class="ok">' in top
    text = re.sub(r"<script>.*?</script>|<style>.*?</style>|data:[^\"]+", "", page, flags=re.S)
    assert "|---" not in text and "**" not in text and "![" not in text  # no markdown left over


def test_a_figure_missing_from_the_folder_is_an_error(tmp_path):
    folder = _folder(tmp_path)
    (folder / "plots" / "fx.png").unlink()
    with pytest.raises(ValueError, match="plots/fx.png"):
        write_report_html(folder)
    assert not (folder / "report.html").exists()


def test_a_large_figure_is_embedded_downscaled(tmp_path):
    import cv2

    folder = tmp_path / "big"
    folder.mkdir()
    noise = np.random.default_rng(0).integers(0, 255, (1200, 2400, 3), np.uint8)  # incompressible: ~8 MB of PNG
    cv2.imwrite(str(folder / "epipolar.png"), noise)
    page = render("# big\n\n## Pair\n\n![epipolar](epipolar.png)\n", folder)
    data = base64.b64decode(re.search(r'data:image/jpeg;base64,([^"]+)"', page).group(1))
    assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR).shape == (800, 1600, 3)
    assert "epipolar.png, shown downscaled" in page


def test_value_with_its_std_to_two_significant_digits():
    from dstereo.io.report_headlines import pm

    assert pm(4787.3812, 9.338, "px") == "4787.4 +- 9.3 px"
    assert pm(100.00412, 0.00914, "mm") == "100.0041 +- 0.0091 mm"
    assert pm(4787.3812, 123.4) == "4787 +- 123"
    assert pm(0.5, None) == "0.5" and pm(float("nan"), 1.0) == "-"


def test_decimation_keeps_at_most_the_limit():
    valid = np.ones((480, 640), bool)
    k = decimation(valid, 50_000)
    assert valid[::k, ::k].sum() <= 50_000 < valid[:: k - 1, :: k - 1].sum()
    assert decimation(np.zeros((10, 10), bool)) == 1


def _sphere_points(h=120, w=160):
    v, u = np.mgrid[0:h, 0:w]
    x, y = (u - w / 2) / 4.0, (v - h / 2) / 4.0
    z = 600.0 - np.sqrt(np.maximum(30.0 ** 2 - x ** 2 - y ** 2, 0))
    pts = np.stack([x, y, z], -1)
    pts[x ** 2 + y ** 2 > 25.0 ** 2] = np.nan
    return pts, 0.1 + 0.001 * (x ** 2 + y ** 2)


@pytest.mark.slow
def test_reports_in_a_browser_and_controls_that_fail(tmp_path):
    """A report with a cloud passes every check; a page that asks for an outside image
    (refused by the page's own policy: a console error; without the policy: the request, caught and refused), one
    that throws, and one whose 3D scene has no data fail the check meant for them."""
    import plotly.io

    from conftest import require_browser

    require_browser()  # before any page is built
    good = _folder(tmp_path, "good")
    pts, sigma = _sphere_points()
    write_report_html(good, Headline([("x", "1")]), cloud_view(pts, sigma))
    page = render("# Outside\n\n## A\n\ntext\n", tmp_path).replace("<main>",
                                                                    '<main><img src="http://192.0.2.1/x.png">')
    blocked, outside = tmp_path / "blocked", tmp_path / "outside"
    for folder in (blocked, outside):
        folder.mkdir()
    (blocked / "report.html").write_text(page)  # the page's own policy refuses the request: a console error
    (outside / "report.html").write_text(re.sub(r'<meta http-equiv="Content-Security-Policy"[^>]*>', "", page))
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "report.html").write_text(render("# Broken\n", broken).replace("<main>",
                                                                             "<main><script>nosuch();</script>"))
    empty = tmp_path / "empty"
    empty.mkdir()
    div = plotly.io.to_html({"data": [{"type": "scatter3d", "x": [], "y": [], "z": [], "mode": "markers"}]},
                            include_plotlyjs=True, full_html=False, validate=False)
    (empty / "report.md").write_text("# Empty\n")
    write_report_html(empty, None, f'<figure class="view3d">{div}</figure>')

    pages = assert_reports_render([good])  # surface_view's page: tests/jobs/test_frame_tasks.py (recession)
    values = [float(v) for v in pages[0]["sorted_column"]]  # written 10.5, 9.5, ... -1.5: sorted by the click
    assert values == sorted(values) and len(values) == 12
    seen = {p["path"].split("/")[-2]: p for p in open_reports([outside, blocked, broken, empty])}
    assert seen["outside"]["outside"] == ["http://192.0.2.1/x.png"] and 0 in seen["outside"]["images"]
    assert any("Content Security Policy" in e for e in seen["blocked"]["errors"]), seen["blocked"]
    assert any("nosuch" in e for e in seen["broken"]["errors"])
    assert seen["empty"]["views3d"] and seen["empty"]["views3d"][0]["coloured_share"] <= DRAWN_SHARE / 10
