"""report.html: a results folder's finished report.md as one page a browser opens from disk.

`write_report_html(folder, headline, view3d)` reads `folder/report.md` and writes `folder/report.html` beside it:
- one self-contained file: every figure report.md shows (`![caption](plots/x.png)`) embedded as a data URI, the
  style and the small scripts inline, and a Content-Security-Policy that lets the page load nothing from outside
  itself (a link to another file of the folder still opens when clicked);
- at the top, the summary: the title, what was measured with its +- and the verdicts of the self-checks
  (`Headline`, formatted by the writer from its finished summary, `io.report_headlines`), every warning with a
  link to the section it concerns, and the sections' contents;
- the report itself, converted from the markdown subset the writers use (`markdown_blocks`); a warning of the
  report's "Warnings" section whose subject (the text before its first ":") names a section is shown in that
  section, and listed at the top;
- every figure with its caption (`CAPTIONS`, else the markdown's alt text); a table of more than
  SORTABLE_ROWS rows sorts by a column when its header is clicked;
- `view3d`: an HTML fragment (a rotatable 3D view, `io.view3d`) shown after the summary.
Nothing here computes a result: it renders finished text and figures. The figures must all be in the folder when
it is called (a figure drawn by the figure workers is there once its writer waited for them): a missing one is a
programming error, raised.
"""

from __future__ import annotations

import base64
import html
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

SORTABLE_ROWS = 8  # a table with more body rows than this sorts by a clicked column
MIME = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".svg": "image/svg+xml",
        ".gif": "image/gif"}

# Captions of the figures the writers draw, by file name (a regular expression on the path's name); the markdown's
# alt text where none matches.
CAPTIONS = (
    (r"coverage\.png", "Where the board's corners fell in the image, and the share of corners in each quadrant and "
                       "image corner (thesis section 5.2.1.2): distortion is only determined where corners were."),
    (r"per_image_rms\.png", "RMS reprojection error of each image in the full-set solve: an image far above the "
                            "others holds a detection error or a moved board."),
    (r"residuals\.png", "Reprojection residual vectors over the image (magnified): a pattern in them is error the "
                        "lens model does not describe."),
    (r"projection_uncertainty\.png", "Standard deviation of each pixel's projection (worst direction) from the "
                                     "calibration's covariance, at the range stated in the text."),
    (r"cross_validation\.png", "Cross-validation: the two halves' projection difference, the difference the "
                               "halves' +- predict, and their Mahalanobis distance."),
    (r"re\.png", "Reprojection error (RMS) of each subset: histogram with its kernel density, and box plots of the "
                 "initial and the surviving subsets (thesis Figure 5.9)."),
    (r"rig\.png", "The rig in the reference camera's frame, with every frame's board."),
    (r"rig_consistency\.png", "Each frame's share of the rig-consistency statistic: a frame far above the others "
                              "is one the rig cannot explain."),
    (r"T(_.+)?\.png", "The translation T of the pair over the frame subsets, before and after the stereo steps "
                      "(thesis Figure 5.15)."),
    (r"RV(_.+)?\.png", "The rotation vector RV of the pair over the frame subsets, before and after the stereo "
                       "steps (thesis Figure 5.16)."),
    (r"recession_vs_time\.png", "Recession at the stagnation point against time, with the fitted line."),
    (r"recession_maps\.png", "Recession over the face, frame by frame."),
    (r"rate_map\.png", "Recession rate over the face, cell by cell."),
    (r"radial_profiles\.png", "Recession against the distance from the stagnation point."),
    (r"disparity\.png", "Disparity in rectified pixels (black: no match)."),
    (r"sigma_z\.png", "Standard deviation of each point's depth (calibration and disparity noise)."),
    (r"epipolar\.png", "The rectified pair side by side with horizontal lines: a feature lies on the same line in "
                       "both images when the rectification is right."),
    (r"rectified_left\.png", "The rectified left image."),
    (r"rectified_right\.png", "The rectified right image."),
    (r"dof_vs_focal_length\.png", "Total depth of field against the lens focal length at the chosen f-number "
                                  "(thesis Figure 5.1)."),
    (r"dof_vs_f_number\.png", "Total depth of field against the f-number at the chosen focal length (thesis "
                              "Figure 5.2)."),
    (r"dof_contour\.png", "Total depth of field over focal length and f-number (thesis Figure 5.3)."),
)
PARAMETER_CAPTION = ("{name} over the image subsets: histogram with its kernel density, and box plots of the initial "
                     "and the surviving subsets (thesis Figure 5.9).")


@dataclass(frozen=True)
class Check:
    """One self-check's verdict for the summary: `ok` True (passed), False (failed: read the warning), None (a
    figure to judge, no verdict)."""

    name: str
    ok: bool | None
    text: str


@dataclass(frozen=True)
class Headline:
    """The summary at the top of report.html: what was measured (quantity, value with its +-) and the checks."""

    measured: list[tuple[str, str]] = field(default_factory=list)
    checks: list[Check] = field(default_factory=list)
    note: str = ""  # one sentence under the measured table (where the +- comes from)


# --- the markdown subset --------------------------------------------------------------------------------------


@dataclass
class Block:
    """One block of report.md: kind 'heading' (level, text), 'paragraph' (text), 'list' (items), 'table' (rows,
    the first the header), 'figure' (src, alt) or 'code' (text)."""

    kind: str
    text: str = ""
    level: int = 0
    items: list = field(default_factory=list)


_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
_ITEM = re.compile(r"^[-*]\s+(.*)$")
_FIGURE = re.compile(r"^!\[([^\]]*)\]\(([^)\s]+)\)\s*$")
_DELIMITER = re.compile(r"^\s*\|?\s*:?-{3,}:?\s*(\|\s*:?-{3,}:?\s*)*\|?\s*$")


def _cells(line: str) -> list[str]:
    """A table row's cells: split on the pipes not escaped as `\\|`, the outer ones dropped."""
    line = line.strip()
    if line.startswith("|"):
        line = line[1:]
    if line.endswith("|") and not line.endswith("\\|"):
        line = line[:-1]
    return [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line)]


def markdown_blocks(text: str) -> list[Block]:
    """The blocks of `text` in the subset of markdown the writers use: ATX headings, paragraphs, `-` lists (an
    indented line continues the item), pipe tables (a header row and a `|---|` row), a figure alone on its line,
    and fenced code."""
    lines, blocks, i = text.splitlines(), [], 0
    paragraph: list[str] = []

    def flush():
        if paragraph:
            blocks.append(Block("paragraph", " ".join(s.strip() for s in paragraph)))
            paragraph.clear()

    while i < len(lines):
        line = lines[i]
        if not line.strip():
            flush()
            i += 1
        elif line.lstrip().startswith("```"):
            flush()
            j = i + 1
            while j < len(lines) and not lines[j].lstrip().startswith("```"):
                j += 1
            blocks.append(Block("code", "\n".join(lines[i + 1:j])))
            i = j + 1
        elif (m := _HEADING.match(line)) is not None:
            flush()
            blocks.append(Block("heading", m.group(2), level=len(m.group(1))))
            i += 1
        elif (m := _FIGURE.match(line.strip())) is not None:
            flush()
            blocks.append(Block("figure", m.group(2), items=[m.group(1)]))
            i += 1
        elif line.lstrip().startswith("|") and i + 1 < len(lines) and _DELIMITER.match(lines[i + 1]):
            flush()
            rows = [_cells(line)]
            i += 2
            while i < len(lines) and lines[i].lstrip().startswith("|"):
                rows.append(_cells(lines[i]))
                i += 1
            blocks.append(Block("table", items=rows))
        elif _ITEM.match(line):
            flush()
            items = []
            while i < len(lines) and (_ITEM.match(lines[i]) or (items and lines[i][:1].isspace()
                                                                 and lines[i].strip())):
                m = _ITEM.match(lines[i])
                if m:
                    items.append(m.group(1).strip())
                else:  # an indented line continues the item
                    items[-1] += " " + lines[i].strip()
                i += 1
            blocks.append(Block("list", items=items))
        else:
            paragraph.append(line)
            i += 1
    flush()
    return blocks


_CODE = re.compile(r"`([^`]+)`")
_IMAGE_INLINE = re.compile(r"!\[([^\]]*)\]\(([^)\s]+)\)")
_LINK = re.compile(r"\[([^\]]+)\]\(([^)\s]+)\)")
_BOLD = re.compile(r"\*\*(.+?)\*\*")


def inline(text: str) -> str:
    """HTML of one line of markdown text: `code`, [links](target), **bold**; everything else escaped."""
    codes: list[str] = []

    def keep(m):
        codes.append(f"<code>{html.escape(m.group(1))}</code>")
        return f"\x00{len(codes) - 1}\x00"

    text = _CODE.sub(keep, text)
    text = html.escape(text, quote=False)
    text = _IMAGE_INLINE.sub(lambda m: f"[{m.group(1)}]", text)  # an image inside a sentence: its alt text
    text = _LINK.sub(lambda m: f'<a href="{html.escape(m.group(2))}">{m.group(1)}</a>', text)
    text = _BOLD.sub(r"<strong>\1</strong>", text)
    return re.sub("\x00(\\d+)\x00", lambda m: codes[int(m.group(1))], text)


# --- the page -------------------------------------------------------------------------------------------------


def slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "section"


def caption(src: str, alt: str) -> str:
    name = Path(src).name
    for pattern, text in CAPTIONS:
        if re.fullmatch(pattern, name):
            return text
    if src.startswith("plots/") and alt and alt == Path(src).stem:  # a parameter's figure (plots/fx.png)
        return PARAMETER_CAPTION.format(name=alt)
    return alt or name


EMBED_BYTES = 1_500_000  # an image file larger than this is embedded downscaled (the file keeps its full size)
EMBED_WIDTH = 1600  # px: the downscaled copy's width at most (a laptop screen's)


def data_uri(path: Path) -> tuple[str, bool]:
    """(the data URI of the image at `path`, whether it was downscaled to fit the page: a file over EMBED_BYTES is
    embedded as a JPEG at most EMBED_WIDTH px wide)."""
    mime = MIME.get(path.suffix.lower())
    if mime is None:
        raise ValueError(f"report.html: {path} is not an image it can embed ({', '.join(MIME)})")
    data = path.read_bytes()
    if len(data) > EMBED_BYTES and mime in ("image/png", "image/jpeg"):
        import cv2
        import numpy as np

        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if image is not None:
            scale = min(1.0, EMBED_WIDTH / image.shape[1])
            if scale < 1.0:
                image = cv2.resize(image, (round(image.shape[1] * scale), round(image.shape[0] * scale)),
                                   interpolation=cv2.INTER_AREA)
            ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 85])
            if ok:
                return f"data:image/jpeg;base64,{base64.b64encode(jpeg.tobytes()).decode('ascii')}", True
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}", False


def _figure(folder: Path, block: Block) -> str:
    src, alt = block.text, block.items[0]
    path = folder / src
    if not path.is_file():
        raise ValueError(f"report.html: {folder}/report.md shows {src}, which is not in the folder (write "
                         "report.html after every figure is drawn)")
    text = caption(src, alt)
    uri, smaller = data_uri(path)
    where = f"{src}, shown downscaled" if smaller else src
    return (f'<figure><img src="{uri}" alt="{html.escape(alt or src)}" title="click to enlarge">'
            f"<figcaption>{inline(text)} <span class=\"file\">{html.escape(where)}</span></figcaption></figure>")


def _table(rows: list[list[str]]) -> str:
    head, body = rows[0], rows[1:]
    sortable = len(body) > SORTABLE_ROWS
    cls = ' class="sortable"' if sortable else ""
    hint = ' title="click to sort"' if sortable else ""
    out = [f"<div class=\"table\"><table{cls}><thead><tr>"
           + "".join(f"<th{hint}>{inline(c)}</th>" for c in head) + "</tr></thead><tbody>"]
    for row in body:
        out.append("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in row) + "</tr>")
    return "".join(out) + "</tbody></table></div>"


def _warning_item(text: str) -> str:
    return f'<div class="warning" role="note"><strong>warning</strong> {inline(text)}</div>'


def _is_warning(item: str) -> bool:
    return item.lower().startswith("warning:")


def _block_html(folder: Path, block: Block) -> str:
    if block.kind == "paragraph":
        return f"<p>{inline(block.text)}</p>"
    if block.kind == "code":
        return f"<pre><code>{html.escape(block.text)}</code></pre>"
    if block.kind == "table":
        return _table(block.items)
    if block.kind == "figure":
        return _figure(folder, block)
    if block.kind == "list":
        parts, plain = [], []
        for item in block.items:
            if _is_warning(item):
                if plain:
                    parts.append("<ul>" + "".join(f"<li>{inline(x)}</li>" for x in plain) + "</ul>")
                    plain = []
                parts.append(_warning_item(item.split(":", 1)[1].strip()))
            else:
                plain.append(item)
        if plain:
            parts.append("<ul>" + "".join(f"<li>{inline(x)}</li>" for x in plain) + "</ul>")
        return "".join(parts)
    raise ValueError(f"report.html: unknown block {block.kind}")


@dataclass
class Section:
    title: str
    anchor: str
    blocks: list[Block] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)  # moved here from the report's Warnings section


WARNINGS_TITLES = ("warnings",)


def sections(blocks: list[Block]) -> tuple[str, list[Block], list[Section]]:
    """(the title, the blocks before the first section, the sections at heading level 2)."""
    title, preamble, out, used = "", [], [], set()
    for block in blocks:
        if block.kind == "heading" and block.level == 1 and not title:
            title = block.text
        elif block.kind == "heading" and block.level == 2:
            anchor = slug(block.text)
            while anchor in used:
                anchor += "-x"
            used.add(anchor)
            out.append(Section(block.text, anchor))
        elif out:
            out[-1].blocks.append(block)
        else:
            preamble.append(block)
    return title, preamble, out


def subject(warning: str) -> str:
    """What a warning is about: its text before the first ': ' ("projection uncertainty: ..."), lower case."""
    return warning.split(": ", 1)[0].strip().lower() if ": " in warning else ""


def place_warnings(parts: list[Section]) -> list[tuple[str, str]]:
    """Move each item of the Warnings section to the section its subject names (the subject starts the section's
    title or the title starts the subject); returns every warning as (text, anchor of where it is shown)."""
    found: list[tuple[str, str]] = []
    for part in parts:
        for block in part.blocks:
            if block.kind == "list":
                found += [(item.split(":", 1)[1].strip(), part.anchor) for item in block.items if _is_warning(item)]
    for part in [p for p in parts if p.title.strip().lower() in WARNINGS_TITLES]:
        keep = []
        for block in part.blocks:
            if block.kind != "list":
                keep.append(block)
                continue
            rest = []
            for item in block.items:
                about = subject(item)
                target = next((p for p in parts if p is not part and about and len(about) >= 4 and (
                    p.title.lower().startswith(about) or about.startswith(p.title.lower()))), None)
                if target is not None:
                    target.warnings.append(item)
                    found.append((item, target.anchor))
                else:
                    rest.append(item)
                    found.append((item, part.anchor))
            if rest:
                keep.append(Block("list", items=rest))
        part.blocks = keep
    return found


def _own_report(folder: Path, warning: str) -> str | None:
    """A rig's warning about one camera ("camera left: ..."): that camera's own report in its folder, if written."""
    about = warning.split(": ", 1)[0].strip() if ": " in warning else ""
    name = about[len("camera "):] if about.startswith("camera ") else ""
    return f"{name}/report.html" if name and (folder / name / "report.html").is_file() else None


def _headline_html(headline: Headline | None, warnings: list[tuple[str, str]]) -> str:
    out = []
    if headline is not None and headline.measured:
        out.append('<h2 id="summary">Summary</h2><table class="measured"><tbody>'
                   + "".join(f"<tr><th>{inline(k)}</th><td>{inline(v)}</td></tr>" for k, v in headline.measured)
                   + "</tbody></table>")
        if headline.note:
            out.append(f'<p class="note">{inline(headline.note)}</p>')
    if headline is not None and headline.checks:
        mark = {True: ("ok", "&#10004;", "passed"), False: ("fail", "&#10008;", "failed"),
                None: ("info", "&#8226;", "figure")}
        rows = []
        for c in headline.checks:
            cls, sign, word = mark[c.ok]
            rows.append(f'<li class="{cls}"><span class="sign" title="{word}">{sign}</span> '
                        f"<strong>{inline(c.name)}</strong>: {inline(c.text)}</li>")
        out.append('<h3>Self-checks</h3><ul class="checks">' + "".join(rows) + "</ul>")
    if warnings:
        out.append(f'<h3>Warnings ({len(warnings)})</h3><ul class="warnings">'
                   + "".join(f'<li>{inline(w)} <a href="{a}">({"its report" if a.endswith(".html") else "section"})'
                             f"</a></li>" for w, a in warnings) + "</ul>")
    else:
        out.append('<p class="ok">No warnings.</p>')
    return "".join(out)


def render(text: str, folder: Path, headline: Headline | None = None, view3d: str | None = None) -> str:
    """The page of report.md's `text`, its figures read from `folder`."""
    title, preamble, parts = sections(markdown_blocks(text))
    warnings = [(w, _own_report(folder, w) or f"#{a}") for w, a in place_warnings(parts)]
    if preamble:  # what report.md says before its first section: shown after the summary, as its own section
        parts.insert(0, Section("Overview", "overview", preamble))
    body = [f"<h1>{inline(title or 'dstereo report')}</h1>",
            f'<section class="summary">{_headline_html(headline, warnings)}</section>']
    nav = [(p.title, p.anchor) for p in parts if p.blocks or p.warnings]
    if view3d:
        nav.insert(0, ("3D view", "view3d"))
    if nav:
        body.append('<nav><strong>Contents:</strong> '
                    + " &middot; ".join(f'<a href="#{a}">{inline(t)}</a>' for t, a in nav) + "</nav>")
    if view3d:
        body.append(f'<section id="view3d"><h2>3D view</h2>{view3d}</section>')
    for part in parts:
        if not part.blocks and not part.warnings:
            continue
        inner = [_warning_item(w) for w in part.warnings]
        run: list[str] = []  # consecutive figures share a grid
        for block in part.blocks:
            if block.kind == "figure":
                run.append(_block_html(folder, block))
                continue
            if run:
                inner.append('<div class="figures">' + "".join(run) + "</div>")
                run = []
            inner.append(_block_html(folder, block))
        if run:
            inner.append('<div class="figures">' + "".join(run) + "</div>")
        body.append(f'<section id="{part.anchor}"><h2>{inline(part.title)}</h2>{"".join(inner)}</section>')
    page_title = html.escape(re.sub(r"[`*]", "", title or "dstereo report"))
    return PAGE.format(title=page_title, style=STYLE, body="\n".join(body), script=SCRIPT)


def write_report_html(folder: str | Path, headline: Headline | None = None, view3d: str | None = None,
                      source: str = "report.md") -> Path:
    """report.html of `folder`'s report.md (or the `source` markdown file; module docstring); returns its path."""
    folder = Path(folder)
    page = render((folder / source).read_text(), folder, headline, view3d)
    path, partial = folder / "report.html", folder / ".report.html.partial"
    partial.write_text(page, encoding="utf-8")
    os.replace(partial, path)  # never half-written where it is read (optics --plots writes into a plain folder)
    return path


# Nothing outside the file: scripts and styles inline, images as data URIs ('unsafe-eval': plotly's WebGL code
# compiles its shaders' wrappers with new Function).
CSP = ("default-src 'none'; img-src data: blob:; style-src 'unsafe-inline'; script-src 'unsafe-inline' "
       "'unsafe-eval'; font-src data:; worker-src blob:")

PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="%s">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title><style>{style}</style></head>
<body><main>
{body}
<footer>Written by dstereo from report.md in this folder; the figures are embedded, the other files are beside it.
</footer></main><script>{script}</script></body></html>
""" % CSP

STYLE = """
body{margin:0;font:15px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;color:#1d232a;background:#f4f5f7}
main{max-width:1200px;margin:0 auto;padding:16px 24px 48px;background:#fff}
h1{font-size:1.5em;margin:.4em 0 .6em;word-break:break-word}
h2{font-size:1.2em;margin:1.6em 0 .5em;padding-bottom:.2em;border-bottom:1px solid #d8dce1}
h3{font-size:1em;margin:1em 0 .3em}
section.summary{background:#f7f9fb;border:1px solid #d8dce1;border-radius:6px;padding:4px 16px 10px;margin:12px 0}
section.summary h2{border:none;margin-top:.6em}
table{border-collapse:collapse;margin:.5em 0;font-size:.92em}
th,td{border:1px solid #d8dce1;padding:3px 8px;text-align:left;vertical-align:top}
thead th{background:#eef1f4}
table.sortable thead th{cursor:pointer;user-select:none}
table.sortable thead th[data-order="asc"]::after{content:" \\25B2"}
table.sortable thead th[data-order="desc"]::after{content:" \\25BC"}
table.measured th{background:#eef1f4;font-weight:600}
.table{overflow-x:auto}
ul.checks{list-style:none;padding-left:0}
ul.checks li{margin:.2em 0}
.sign{display:inline-block;width:1.3em;text-align:center;font-weight:bold}
li.ok .sign,p.ok{color:#1a7f37} li.fail .sign{color:#cf222e} li.info .sign{color:#57606a}
ul.warnings li{margin:.2em 0}
.warning{background:#fff8e1;border-left:4px solid #d4a72c;padding:6px 10px;margin:.5em 0}
.warning strong{color:#9a6700;text-transform:uppercase;font-size:.8em;margin-right:.4em}
nav{margin:10px 0;font-size:.95em}
.figures{display:grid;grid-template-columns:repeat(auto-fill,minmax(440px,1fr));gap:14px;align-items:start}
figure{margin:.6em 0}
figure img{max-width:100%;height:auto;border:1px solid #e3e6ea;cursor:zoom-in;background:#fff}
figure.big{grid-column:1/-1} figure.big img{cursor:zoom-out}
figcaption{font-size:.9em;color:#444;margin-top:.2em}
figcaption .file{color:#888;font-family:monospace;font-size:.9em}
code{font-family:ui-monospace,Menlo,Consolas,monospace;font-size:.92em;background:#f0f2f4;padding:0 3px}
pre{background:#f0f2f4;padding:8px;overflow-x:auto}
p.note{color:#57606a;font-size:.9em}
footer{margin-top:3em;color:#777;font-size:.85em}
@media print{body{background:#fff} main{max-width:none} nav{display:none}}
"""

# Sort a long table by a clicked header (numbers as numbers, the rest as text; a second click reverses), and
# enlarge a clicked figure to the page's width.
SCRIPT = """
(function(){
function key(td){var t=td.textContent.trim(),n=parseFloat(t.replace(/[^0-9eE+\\-.]/g,''));
 return (/^[-+]?[0-9.]/.test(t)&&!isNaN(n))?[0,n]:[1,t.toLowerCase()];}
document.querySelectorAll('table.sortable').forEach(function(table){
 table.querySelectorAll('thead th').forEach(function(th,col){th.addEventListener('click',function(){
  var asc=th.getAttribute('data-order')!=='asc';
  table.querySelectorAll('thead th').forEach(function(h){h.removeAttribute('data-order');});
  th.setAttribute('data-order',asc?'asc':'desc');
  var body=table.tBodies[0],rows=Array.prototype.slice.call(body.rows);
  rows.sort(function(a,b){var x=key(a.cells[col]||a),y=key(b.cells[col]||b);
   var c=x[0]-y[0]||(x[1]<y[1]?-1:x[1]>y[1]?1:0);return asc?c:-c;});
  rows.forEach(function(r){body.appendChild(r);});});});});
document.querySelectorAll('figure img').forEach(function(img){img.addEventListener('click',function(){
 img.parentNode.classList.toggle('big');});});
})();
"""
