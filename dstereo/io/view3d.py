"""Rotatable 3D views for report.html, drawn by plotly (its plotly.js inlined: the page needs nothing outside it).

- `cloud_view(points, sigma_z)`: a reconstruction's cloud, every k-th row and column of the (h, w, 3) grid so
  that at most MAX_POINTS are drawn, coloured by depth, with a button for the depth's standard deviation;
- `surface_view(u, v, height, colour)`: a surface over a grid (recession: the face's heights in its last frame,
  coloured by its recession).
Each returns an HTML fragment (a figure and its caption) for `io.report_html.write_report_html(view3d=...)`.
What is drawn is chosen for the screen (which points, the depth range shown), not computed: every number here
was in the results before.
"""

from __future__ import annotations

import base64
import math

import numpy as np

MAX_POINTS = 50_000  # a browser turns ~50k markers smoothly (WebGL); 640 x 480 px has 307k
DEPTH_PERCENTILES = (1.0, 99.0)  # the depth range shown, widened by WIDEN of its span: far outliers flatten the rest
WIDEN = 0.1
CONFIG = {"displaylogo": False, "responsive": True, "scrollZoom": True,
          "modeBarButtonsToRemove": ["toImage", "sendDataToCloud"]}  # nothing that leaves the page


def decimation(valid: np.ndarray, limit: int = MAX_POINTS) -> int:
    """The smallest step k such that every k-th row and column of `valid` holds at most `limit` valid pixels."""
    k = max(1, math.ceil(math.sqrt(int(valid.sum()) / limit)))
    while int(valid[::k, ::k].sum()) > limit:
        k += 1
    return k


def typed(values) -> dict:
    """plotly.js's typed-array form of an array ({dtype, bdata: base64, shape}), float32: 4 bytes a value in the
    page and no JSON number formatting (a list of 50k x 3 floats took 0.9 s to encode, this ~10 ms); NaN stays NaN
    (a gap)."""
    a = np.ascontiguousarray(values, dtype=np.float32)
    spec = {"dtype": "f4", "bdata": base64.b64encode(a.tobytes()).decode("ascii")}
    return spec | ({"shape": ", ".join(map(str, a.shape))} if a.ndim > 1 else {})


def _to_html(figure: dict, div_id: str) -> str:
    import plotly.io

    return plotly.io.to_html(figure, config=CONFIG, include_plotlyjs=True, full_html=False, validate=False,
                             div_id=div_id, default_height="640px")


def _colorbar(title: str) -> dict:
    return {"title": {"text": title, "side": "right"}, "thickness": 14}


def cloud_view(points: np.ndarray, sigma_z: np.ndarray | None = None, units: str = "mm") -> str:
    """The cloud of an (h, w, 3) grid of points (NaN: no point) as an HTML fragment (module docstring)."""
    points = np.asarray(points)
    valid = np.all(np.isfinite(points), axis=-1)
    total = int(valid.sum())
    if total == 0:
        return "<p>No point has a depth: nothing to show in 3D.</p>"
    z_all = points[..., 2][valid]
    lo, hi = np.percentile(z_all, DEPTH_PERCENTILES)
    lo, hi = lo - WIDEN * (hi - lo), hi + WIDEN * (hi - lo)
    shown_range = valid & (points[..., 2] >= lo) & (points[..., 2] <= hi)
    k = decimation(shown_range)
    keep = shown_range[::k, ::k]
    p = points[::k, ::k][keep].astype(np.float32)
    marker = {"size": 3, "color": typed(p[:, 2]), "colorscale": "Viridis", "colorbar": _colorbar(f"depth ({units})")}
    trace = {"type": "scatter3d", "mode": "markers", "x": typed(p[:, 0]), "y": typed(p[:, 1]), "z": typed(p[:, 2]),
             "marker": marker,
             "hovertemplate": "x %{x:.4g}<br>y %{y:.4g}<br>z %{z:.5g}<extra></extra>"}
    layout = _scene_layout(units, camera_view=True)
    if sigma_z is not None:
        s = np.asarray(sigma_z)[::k, ::k][keep].astype(np.float32)
        finite = s[np.isfinite(s)]
        low, top = (float(x) for x in np.percentile(finite, (1, 99))) if finite.size else (0.0, 1.0)
        layout["updatemenus"] = [{
            "type": "buttons", "direction": "right", "x": 0.0, "y": 1.07, "xanchor": "left", "showactive": True,
            "buttons": [
                {"label": "colour: depth", "method": "restyle",
                 "args": [{"marker.color": [typed(p[:, 2])], "marker.colorscale": "Viridis", "marker.cmin": float(lo),
                           "marker.cmax": float(hi), "marker.colorbar.title.text": f"depth ({units})"}]},
                {"label": "colour: depth std sigma_z", "method": "restyle",
                 "args": [{"marker.color": [typed(s)], "marker.colorscale": "Hot", "marker.cmin": low,
                           "marker.cmax": top, "marker.colorbar.title.text": f"sigma_z ({units})"}]}]}]
    view = _to_html({"data": [trace], "layout": layout}, "cloud3d")
    left_out = int((valid & ~shown_range).sum())
    words = (f"The cloud in the left camera's frame ({units}), seen from the cameras: {len(p)} of the {total} points "
             f"with a depth (every {k}{_nth(k)} row and column of the image)"
             + (f"; {left_out} points with a depth outside {lo:.5g} .. {hi:.5g} {units} (the 1-99 % range, widened "
                "by 10 %) are left out of the view" if left_out else "")
             + ". Drag to rotate, scroll to zoom; the buttons colour the points by depth or by its standard "
               "deviation. All points are in points.ply.")
    return f'<figure class="view3d">{view}<figcaption>{words}</figcaption></figure>'


def _nth(k: int) -> str:
    return {1: "st", 2: "nd", 3: "rd"}.get(k if k < 20 else k % 10, "th")


def _scene_layout(units: str, camera_view: bool) -> dict:
    scene = {"aspectmode": "data", "xaxis": {"title": {"text": f"x ({units})"}},
             "yaxis": {"title": {"text": f"y ({units})"}}, "zaxis": {"title": {"text": f"z ({units})"}}}
    if camera_view:  # the left camera's frame: x right, y down, z forward; look along +z with y down
        scene["camera"] = {"eye": {"x": 0.6, "y": -0.5, "z": -2.2}, "up": {"x": 0.0, "y": -1.0, "z": 0.0}}
    return {"scene": scene, "margin": {"l": 0, "r": 0, "t": 30, "b": 0}, "height": 620}


def surface_view(u: np.ndarray, v: np.ndarray, height: np.ndarray, colour: np.ndarray, colour_label: str,
                 caption: str) -> str:
    """A surface height(v, u) on a grid ((ny, nx), NaN: no value) coloured by `colour` (same shape)."""
    height, colour = np.asarray(height, float), np.asarray(colour, float)
    if not np.isfinite(height).any():
        return "<p>No grid cell has a height: nothing to show in 3D.</p>"
    trace = {"type": "surface", "x": typed(u), "y": typed(v), "z": typed(height), "surfacecolor": typed(colour),
             "colorscale": "Viridis", "colorbar": _colorbar(colour_label),
             "hovertemplate": "u %{x:.4g}<br>v %{y:.4g}<br>height %{z:.4g}<extra></extra>"}
    layout = _scene_layout("mm", camera_view=False)
    layout["scene"]["xaxis"]["title"]["text"] = "u (mm)"
    layout["scene"]["yaxis"]["title"]["text"] = "v (mm)"
    # heights grow along the axis, away from the cameras: reversed, the face is seen as the cameras see it
    layout["scene"]["zaxis"].update({"title": {"text": "height along the axis (mm)"}, "autorange": "reversed"})
    layout["scene"]["camera"] = {"eye": {"x": 0.9, "y": -1.1, "z": 0.8}}
    layout["scene"]["aspectmode"] = "manual"  # the face is wide and shallow: its relief would not show at 1:1:1
    layout["scene"]["aspectratio"] = {"x": 1.0, "y": float(np.ptp(v) / max(np.ptp(u), 1e-12)), "z": 0.4}
    view = _to_html({"data": [trace], "layout": layout}, "surface3d")
    return f'<figure class="view3d">{view}<figcaption>{caption}</figcaption></figure>'
