"""Pictures and the HTML report of ``lidar-obstacles evaluate``.

Every ``*_png`` function draws one figure with matplotlib's object-oriented API on its Agg
canvas (``matplotlib.figure.Figure``, never ``pyplot``: no global backend switch, no GUI,
safe in a node's thread) and writes it atomically (temporary file + ``os.replace``), so a
crash never leaves half a PNG. matplotlib is imported lazily, only when a picture is drawn.

Conventions: map views are north-up with equal x/y scale and coordinates in metres shown
relative to a round offset named in the axis label; grids follow the DEM convention (row 0
south, cell (r, c) centred at origin + ((c + 0.5) res, (r + 0.5) res)); class colours
follow the usual ASPRS viewer scheme (:data:`CLASS_STYLE`): ground brown, vegetation
greens, building orange-red, wire cyan, tower magenta, noise grey.
"""
from __future__ import annotations

import base64
import html
import json
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from lidar_obstacles.core.arrays import points_xyz
from lidar_obstacles.core.classes import CLASS_HEX
from lidar_obstacles.core.metrics import jsonable, latency_stats
from lidar_obstacles.errors import CloudFormatError, LidarObstaclesError
from lidar_obstacles.io.atomic import HTML, JSON, PNG, atomic_write, atomic_write_text

DPI = 150
"""Resolution of every PNG; a figure of W x H inches is (W * DPI) x (H * DPI) pixels."""

CLASS_STYLE: dict[int, tuple[str, str]] = {
    0: ("object / never classified", "#7d6b8c"),
    1: ("unclassified", CLASS_HEX[1]),
    2: ("ground", CLASS_HEX[2]),
    3: ("low vegetation", CLASS_HEX[3]),
    4: ("medium vegetation", CLASS_HEX[4]),
    5: ("high vegetation", CLASS_HEX[5]),
    6: ("building", CLASS_HEX[6]),
    7: ("noise", CLASS_HEX[7]),
    8: ("model key-point", "#c8966a"),
    9: ("water", "#3b6fd1"),
    11: ("road surface", "#6e4a32"),
    14: ("wire conductor", CLASS_HEX[14]),
    15: ("transmission tower", CLASS_HEX[15]),
    26: ("crane (user 26)", "#ffa000"),
}
"""ASPRS code -> (name, colour) used in every class picture; other codes are dark grey."""

_OTHER_COLOUR = "#303030"
_EMPHASISED = (14, 15)  # thin obstacles a UAV must not hit: always drawn, on top, larger

ERROR_STYLE: tuple[tuple[str, str], ...] = (
    ("correct", "#cfcfcf"),
    ("Type I: ground rejected", "#d62728"),
    ("Type II: object taken as ground", "#1f5fd6"),
    ("other: wrong object class", "#ff9f1c"),
)
"""Categories of :func:`error_views_png`, in drawing order."""


# --------------------------------------------------------------------------- plumbing


def _figure(width_in: float, height_in: float):
    """A new constrained-layout Figure on the Agg canvas (lazy matplotlib import)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: str | Path) -> Path:
    """Write the figure as PNG at :data:`DPI`, atomically; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=DPI), kind=PNG)


def _offset(values: np.ndarray) -> float:
    """A round number below the data so tick labels stay short (e.g. 228800 for UTM)."""
    lo = float(np.nanmin(values))
    step = 10 ** max(0, int(np.floor(np.log10(max(abs(lo), 1.0)))) - 2)
    return float(np.floor(lo / step) * step) if abs(lo) >= 1000 else 0.0


def _thousands(value: float) -> str:
    """12 345 678: thin groups as in surveying reports, never a comma (a decimal mark)."""
    return f"{value:,.0f}".replace(",", " ")


def _coord_label(axis: str, offset: float) -> str:
    return f"{axis} − {_thousands(offset)} (m)" if offset else f"{axis} (m)"


def _subsample(keep: np.ndarray, max_points: int, seed: int) -> np.ndarray:
    """Sorted indices: every ``keep`` point plus a uniform, seeded draw of the rest."""
    forced = np.flatnonzero(keep)
    rest = np.flatnonzero(~keep)
    budget = max(max_points - forced.size, 0)
    if rest.size > budget:
        rest = np.random.default_rng(seed).choice(rest, size=budget, replace=False)
    return np.sort(np.concatenate([forced, rest]))


def _principal_axis(xy: np.ndarray) -> np.ndarray:
    """Unit horizontal direction of largest spread (a corridor's axis), pointing east-ish."""
    cov = np.cov((xy - xy.mean(axis=0)).T)
    u = np.linalg.eigh(cov)[1][:, -1]
    return -u if (u[0] < 0 or (u[0] == 0 and u[1] < 0)) else u


def _exaggeration(length: float, height: float, target: float = 0.22) -> int:
    """Smallest 'nice' vertical exaggeration making height/length at least ``target``."""
    need = target * length / max(height, 1e-6)
    for e in (1, 2, 3, 5, 10, 20, 50, 100):
        if e >= need:
            return e
    return 100


def _map_views(
    xyz: np.ndarray,
    colours: np.ndarray,
    emphasised: np.ndarray,
    order_top: np.ndarray,
    order_side: np.ndarray,
    title: str,
    *,
    emph_scale: float,
):
    """Top view (north-up, equal scale) above a side view along the main axis.

    Marker size follows the drawn point spacing so that sparse clouds do not dissolve
    into moiré and dense ones do not turn into blots; ``emphasised`` points get
    ``emph_scale`` times the area. Returns (fig, ax_top, ax_side); points are drawn in
    the given orders.
    """
    xy = xyz[:, :2]
    ox, oy = _offset(xyz[:, 0]), _offset(xyz[:, 1])
    dx = max(np.ptp(xyz[:, 0]), 1e-6)
    dy = max(np.ptp(xyz[:, 1]), 1e-6)
    u = _principal_axis(xy)
    along = (xy - xy.mean(axis=0)) @ u
    along -= along.min()
    length = max(float(along.max()), 1e-6)
    height = max(float(np.ptp(xyz[:, 2])), 1e-6)
    exag = _exaggeration(length, height)
    width = 11.0
    top_h = float(np.clip(dy / dx, 0.35, 1.2)) * 7.5
    side_h = float(np.clip(height * exag / length, 0.12, 0.5)) * 9.5 + 0.9
    # mean point spacing over the occupied area (not the bounding box: corridors are
    # diagonal strips), and the top view's scale in points per metre
    cells = 128
    cx = np.minimum(((xyz[:, 0] - xyz[:, 0].min()) / dx * cells).astype(np.int64), cells - 1)
    cy = np.minimum(((xyz[:, 1] - xyz[:, 1].min()) / dy * cells).astype(np.int64), cells - 1)
    area = np.unique(cy * cells + cx).size * (dx / cells) * (dy / cells)
    spacing = np.sqrt(area / xyz.shape[0])
    map_w_in = min(width - 3.2, 0.92 * top_h * dx / dy)
    diameter_pt = float(np.clip(0.75 * spacing * map_w_in * 72.0 / dx, 0.6, 6.0))
    sizes = np.where(emphasised, emph_scale, 1.0) * diameter_pt**2
    fig = _figure(width, top_h + side_h + 0.8)
    gs = fig.add_gridspec(2, 1, height_ratios=[top_h, side_h])
    ax_top = fig.add_subplot(gs[0])
    ax_side = fig.add_subplot(gs[1])
    # the side view stacks every point of a profile on the same pixels: smaller markers
    for ax, order, xs, ys, scale in (
        (ax_top, order_top, xyz[:, 0] - ox, xyz[:, 1] - oy, 1.0),
        (ax_side, order_side, along, xyz[:, 2], 0.4),
    ):
        ax.scatter(xs[order], ys[order], c=colours[order], s=scale * sizes[order], marker="o",
                   linewidths=0, rasterized=True)
        ax.set_facecolor("white")
        ax.grid(True, color="#e6e6e6", linewidth=0.5, zorder=0)
        ax.set_axisbelow(True)
    ax_top.set_aspect("equal", adjustable="box")
    ax_top.set_anchor("NW")  # a tall map leaves room on its right for the legend
    ax_top.set_xlabel(_coord_label("easting x", ox))
    ax_top.set_ylabel(_coord_label("northing y", oy))
    ax_top.set_title(f"{title} — top view", fontsize=11)
    ax_side.set_aspect(exag, adjustable="box")
    bearing = float(np.degrees(np.arctan2(u[0], u[1])) % 180.0)
    ax_side.set_xlabel(f"distance along the main axis, bearing {bearing:.0f}° (m)")
    ax_side.set_ylabel("height z (m)")
    ex = f", vertical exaggeration ×{exag}" if exag > 1 else ""
    ax_side.set_title(f"side view{ex}", fontsize=10)
    # the top view is drawn at a scale the box adjusts to, so show the data extent in text
    ax_top.text(0.01, 0.01, f"{dx:.0f} m × {dy:.0f} m", transform=ax_top.transAxes,
                fontsize=8, color="#444444", va="bottom", ha="left",
                bbox=dict(facecolor="white", alpha=0.7, edgecolor="none", pad=1.5))
    return fig, ax_top, ax_side


def _map_figure(width_m: float, height_m: float, *, colorbar: bool = True):
    """Figure sized to a map's shape (equal scale) so it carries little white space.

    The map area fits in 7.5 x 8.5 inches; room is added for labels, title and colour bar.
    """
    aspect = float(np.clip(height_m / max(width_m, 1e-9), 0.25, 4.0))
    map_w, map_h = 7.5, 7.5 * aspect
    if map_h > 8.5:
        map_w, map_h = 8.5 / aspect, 8.5
    fig = _figure(map_w + (2.2 if colorbar else 1.0), map_h + 1.4)
    return fig, fig.add_subplot()


def _legend(ax, entries: Iterable[tuple[str, str]], title: str | None = None) -> None:
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], marker="s", linestyle="none", markersize=8, color=colour,
                      label=label) for label, colour in entries]
    ax.legend(handles=handles, title=title, loc="upper left", bbox_to_anchor=(1.01, 1.0),
              fontsize=8, title_fontsize=8, frameon=False, borderaxespad=0.0)


def _code_colours(codes: np.ndarray) -> np.ndarray:
    """(N, 4) RGBA per ASPRS code."""
    from matplotlib.colors import to_rgba

    table = np.tile(np.array(to_rgba(_OTHER_COLOUR)), (256, 1))
    for code, (_, colour) in CLASS_STYLE.items():
        table[code] = to_rgba(colour)
    return table[codes]


def _codes(classes: Any, n: int, name: str) -> np.ndarray:
    arr = np.asarray(classes)
    if arr.shape != (n,):
        raise CloudFormatError(f"{name} must have shape ({n},), got {arr.shape}")
    codes = arr.astype(np.int64)
    if n and (codes.min() < 0 or codes.max() > 255):
        raise CloudFormatError(f"{name}: codes must lie in 0..255")
    return codes


# --------------------------------------------------------------------------- clouds


def cloud_views_png(
    xyz: Any,
    classes: Any,
    path: str | Path,
    *,
    title: str = "classes",
    max_points: int = 200_000,
    seed: int = 0,
) -> Path:
    """Top and side view of a cloud coloured by ASPRS class.

    xyz: (N, 3) float64, metres. classes: (N,) integer ASPRS codes.
    At most ``max_points`` are drawn: every wire (14) and tower (15) point plus a seeded
    uniform sample of the rest, so the picture is deterministic and thin obstacles never
    vanish. The top view draws higher points over lower ones; the side view looks along
    the horizontal axis of largest spread (a corridor's axis), near points over far ones.
    The legend lists the classes present with their full point counts.
    Returns the path of the PNG (11 in = 1650 px wide; height follows the data's shape).
    """
    pts = points_xyz(xyz, "cloud_views_png: xyz", min_points=1)
    codes = _codes(classes, pts.shape[0], "classes")
    emph = np.isin(codes, _EMPHASISED)
    idx = _subsample(emph, max_points, seed)
    sub, sub_codes, sub_emph = pts[idx], codes[idx], emph[idx]
    colours = _code_colours(sub_codes)
    # emphasised classes last in both views; otherwise by height (top) or depth (side)
    order_top = np.lexsort((sub[:, 2], sub_emph))
    u = _principal_axis(sub[:, :2])
    depth = (sub[:, :2] - sub[:, :2].mean(axis=0)) @ np.array([-u[1], u[0]])
    order_side = np.lexsort((-depth, sub_emph))
    fig, ax_top, _ = _map_views(sub, colours, sub_emph, order_top, order_side, title,
                                emph_scale=4.0)
    present, counts = np.unique(codes, return_counts=True)
    entries = [
        (f"{c:d} {CLASS_STYLE.get(int(c), (f'class {c}', ''))[0]} ({_thousands(n)})",
         CLASS_STYLE.get(int(c), ("", _OTHER_COLOUR))[1])
        for c, n in zip(present, counts)
    ]
    _legend(ax_top, entries, title="ASPRS class (points)")
    if idx.size < codes.size:
        fig.suptitle(f"{_thousands(idx.size)} of {_thousands(codes.size)} points drawn",
                     fontsize=8, x=0.99, ha="right", color="#666666")
    return _save(fig, path)


def error_categories(reference: Any, predicted: Any) -> np.ndarray:
    """Per point: 0 correct, 1 Type I, 2 Type II, 3 other error (see :data:`ERROR_STYLE`).

    reference, predicted: (N,) ASPRS codes, compared by evaluation group
    (:func:`lidar_obstacles.core.metrics.compared_groups`). Type I: reference ground
    predicted as object; Type II: reference object predicted as ground; other: an object
    given the wrong object group (never one the reference does not class).
    Returns (N,) int8.
    """
    from lidar_obstacles.core.metrics import GROUP_GROUND, compared_groups

    if np.shape(reference) != np.shape(predicted):
        raise CloudFormatError(f"reference {np.shape(reference)} and prediction "
                               f"{np.shape(predicted)} differ")
    ref, pred, _ = compared_groups(reference, predicted)
    cat = np.zeros(ref.size, dtype=np.int8)
    wrong = ref != pred
    cat[wrong & (ref == GROUP_GROUND)] = 1
    cat[wrong & (pred == GROUP_GROUND)] = 2
    cat[wrong & (ref != GROUP_GROUND) & (pred != GROUP_GROUND)] = 3
    return cat


def error_views_png(
    xyz: Any,
    reference: Any,
    predicted: Any,
    path: str | Path,
    *,
    title: str = "errors",
    max_points: int = 200_000,
    seed: int = 0,
) -> Path:
    """Top and side view coloured by correct / Type I / Type II / other error.

    xyz: (N, 3) float64, metres; reference, predicted: (N,) ASPRS codes.
    Errors are drawn over the correct points, larger; every error point is kept (up to
    ``max_points``), the correct ones are sampled with ``seed``. The legend gives the
    share of each category among all N points.
    """
    pts = points_xyz(xyz, "error_views_png: xyz", min_points=1)
    ref = _codes(reference, pts.shape[0], "reference")
    pred = _codes(predicted, pts.shape[0], "predicted")
    cat = error_categories(ref, pred)
    wrong = cat > 0
    if wrong.sum() > max_points:
        # more errors than the budget: sample errors too, still every category in play
        idx = _subsample(np.zeros(cat.size, bool), max_points, seed)
    else:
        idx = _subsample(wrong, max_points, seed)
    sub, sub_cat = pts[idx], cat[idx]
    from matplotlib.colors import to_rgba

    palette = np.array([to_rgba(c) for _, c in ERROR_STYLE])
    colours = palette[sub_cat]
    order_top = np.lexsort((sub[:, 2], sub_cat > 0))
    u = _principal_axis(sub[:, :2])
    depth = (sub[:, :2] - sub[:, :2].mean(axis=0)) @ np.array([-u[1], u[0]])
    order_side = np.lexsort((-depth, sub_cat > 0))
    fig, ax_top, _ = _map_views(sub, colours, sub_cat > 0, order_top, order_side, title,
                                emph_scale=2.0)
    shares = np.bincount(cat, minlength=len(ERROR_STYLE)) / cat.size
    _legend(ax_top, [(f"{name} ({100 * s:.2f} %)", colour)
                     for (name, colour), s in zip(ERROR_STYLE, shares)],
            title="point (share of all)")
    return _save(fig, path)


# --------------------------------------------------------------------------- matrices


def confusion_png(
    matrix: Any,
    labels: Iterable[str],
    path: str | Path,
    *,
    drop_empty: bool = True,
    title: str = "confusion matrix",
) -> Path:
    """Heat map of a confusion matrix with counts and percentages.

    matrix: (K, K) counts, rows = predicted, columns = reference (the convention of
    :mod:`lidar_obstacles.core.metrics`). labels: K class names.
    Colour and percentage are the share of each reference class (column-normalised, so a
    rare class such as wires is as readable as ground; square-root colour scale so small
    confusions show); the diagonal is then the producer's accuracy. Classes absent from both
    sides are left out when ``drop_empty``.
    """
    m = np.asarray(matrix, dtype=np.int64)
    names = list(labels)
    if m.ndim != 2 or m.shape[0] != m.shape[1] or m.shape[0] != len(names):
        raise CloudFormatError(f"matrix must be (K, K) with K = {len(names)} labels, got {m.shape}")
    if drop_empty:
        keep = (m.sum(axis=0) + m.sum(axis=1)) > 0
        if keep.any():
            m = m[np.ix_(keep, keep)]
            names = [n for n, k in zip(names, keep) if k]
    k = m.shape[0]
    cols = m.sum(axis=0)
    share = np.divide(m, cols, out=np.zeros(m.shape), where=cols > 0)
    side = 2.2 + 0.95 * k
    fig = _figure(side + 1.4, side)
    ax = fig.add_subplot()
    from matplotlib.colors import PowerNorm

    # square-root colour scale: a 1 % confusion still shows, 97 % vs 99 % stays apart
    im = ax.imshow(share * 100.0, cmap="Blues", norm=PowerNorm(0.5, vmin=0.0, vmax=100.0))
    for i in range(k):
        for j in range(k):
            dark = share[i, j] > 0.35
            ax.text(j, i, f"{_thousands(m[i, j])}\n{100 * share[i, j]:.1f} %",
                    ha="center", va="center", fontsize=8 if k <= 5 else 7,
                    color="white" if dark else "#1a1a1a",
                    fontweight="bold" if i == j else "normal")
    ax.set_xticks(range(k), names, rotation=30, ha="right")
    ax.set_yticks(range(k), names)
    ax.set_xlabel("reference class (columns)")
    ax.set_ylabel("predicted class (rows)")
    ax.set_title(f"{title}\n{_thousands(m.sum())} points", fontsize=11)
    ax.set_xticks(np.arange(k + 1) - 0.5, minor=True)
    ax.set_yticks(np.arange(k + 1) - 0.5, minor=True)
    ax.grid(which="minor", color="white", linewidth=1.5)
    ax.tick_params(which="minor", length=0)
    cb = fig.colorbar(im, ax=ax, shrink=0.8)
    cb.set_label("share of the reference class (%)")
    return _save(fig, path)


def block_kappa_png(
    block_kappa: Any,
    extent: tuple[float, float, float, float],
    path: str | Path,
    *,
    title: str = "ground/object kappa per block",
    xy: Any = None,
    seed: int = 0,
) -> Path:
    """Map of the per-block kappa.

    block_kappa: (ny, nx) float, row 0 south, NaN (or None) where the block is not
    eligible. extent: (xmin, xmax, ymin, ymax) of the grid, metres (the ``blocks.extent``
    of :func:`lidar_obstacles.core.metrics.block_kappa`). xy: optional (N, 2) points,
    drawn faintly (a sample of 20 000, drawn with ``seed``: fixed, so that the same data
    give the same picture) to show where the data lie.
    Colours run red (0) - yellow - green (1); values are written in the cells; hatched
    grey marks blocks that are not eligible.
    """
    kap = np.array(block_kappa, dtype=np.float64)
    if kap.ndim != 2:
        raise CloudFormatError(f"block_kappa must be (ny, nx), got shape {kap.shape}")
    xmin, xmax, ymin, ymax = (float(v) for v in extent)
    ny, nx = kap.shape
    ox, oy = _offset(np.array([xmin])), _offset(np.array([ymin]))
    ext = (xmin - ox, xmax - ox, ymin - oy, ymax - oy)
    fig, ax = _map_figure(xmax - xmin, ymax - ymin)
    from matplotlib.patches import Rectangle

    ax.add_patch(Rectangle((ext[0], ext[2]), ext[1] - ext[0], ext[3] - ext[2],
                           facecolor="#eeeeee", edgecolor="none", hatch="///", zorder=0))
    im = ax.imshow(np.ma.masked_invalid(kap), origin="lower", extent=ext, cmap="RdYlGn",
                   vmin=0.0, vmax=1.0, interpolation="nearest", zorder=1)
    if xy is not None:
        pts = np.asarray(xy, dtype=np.float64)[:, :2]
        if pts.shape[0] > 20_000:
            pts = pts[np.random.default_rng(seed).choice(pts.shape[0], 20_000, replace=False)]
        ax.scatter(pts[:, 0] - ox, pts[:, 1] - oy, s=0.3, c="black", alpha=0.25,
                   linewidths=0, rasterized=True, zorder=2)
    bw = (ext[1] - ext[0]) / nx
    bh = (ext[3] - ext[2]) / ny
    for r in range(ny):
        for c in range(nx):
            if np.isfinite(kap[r, c]):
                ax.text(ext[0] + (c + 0.5) * bw, ext[2] + (r + 0.5) * bh, f"{kap[r, c]:.2f}",
                        ha="center", va="center", fontsize=8 if nx <= 8 else 6, zorder=3)
    ax.set_xticks(np.linspace(ext[0], ext[1], nx + 1), minor=True)
    ax.set_yticks(np.linspace(ext[2], ext[3], ny + 1), minor=True)
    ax.grid(which="minor", color="white", linewidth=1.0)
    ax.tick_params(which="minor", length=0)
    ax.set_aspect("equal")
    ax.set_xlabel(_coord_label("easting x", ox))
    ax.set_ylabel(_coord_label("northing y", oy))
    finite = kap[np.isfinite(kap)]
    sub = (f"{finite.size} of {kap.size} blocks eligible; kappa > 0.8 in "
           f"{100 * np.mean(finite > 0.8):.1f} %, > 0.6 in {100 * np.mean(finite > 0.6):.1f} %"
           if finite.size else "no eligible block")
    ax.set_title(f"{title}\n{sub}", fontsize=10)
    cb = fig.colorbar(im, ax=ax, shrink=0.8)
    cb.set_label("Cohen's kappa (ground vs object)")
    return _save(fig, path)


# --------------------------------------------------------------------------- DEM


def _grid_extent(shape: tuple[int, int], resolution: float, origin: tuple[float, float]):
    rows, cols = shape
    ox, oy = float(origin[0]), float(origin[1])
    return (ox, ox + cols * resolution, oy, oy + rows * resolution)


def _grid(elevation: Any, resolution: float, name: str) -> np.ndarray:
    grid = np.asarray(elevation, dtype=np.float64)
    if grid.ndim != 2 or grid.size == 0:
        raise CloudFormatError(f"{name} must be a non-empty (rows, cols) grid, got {grid.shape}")
    if not resolution > 0:
        raise CloudFormatError(f"resolution must be > 0 m, got {resolution}")
    return grid


def _grid_figure(grid: np.ndarray, resolution: float, origin: tuple[float, float]):
    """Figure and axes for a map of the grid, equal scale, offset coordinates."""
    ext = _grid_extent(grid.shape, resolution, origin)
    ox, oy = _offset(np.array([ext[0]])), _offset(np.array([ext[2]]))
    ext = (ext[0] - ox, ext[1] - ox, ext[2] - oy, ext[3] - oy)
    fig, ax = _map_figure(float(grid.shape[1]), float(grid.shape[0]))
    ax.set_xlabel(_coord_label("easting x", ox))
    ax.set_ylabel(_coord_label("northing y", oy))
    ax.set_aspect("equal")
    return fig, ax, ext


def hillshade_png(
    elevation: Any,
    resolution: float,
    origin: tuple[float, float],
    path: str | Path,
    *,
    title: str = "DEM",
    azimuth_deg: float = 315.0,
    altitude_deg: float = 45.0,
) -> Path:
    """Hill-shaded elevation map with an elevation colour bar.

    elevation: (rows, cols) float, metres, NaN = unknown (shown light grey); row 0 south.
    resolution: m/cell; origin: (x, y) of the grid's south-west corner, metres.
    Light from ``azimuth_deg`` (clockwise from north) at ``altitude_deg``, true scale
    (no vertical exaggeration), blended over a terrain colour ramp.
    """
    grid = _grid(elevation, resolution, "elevation")
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import LightSource, Normalize

    fig, ax, ext = _grid_figure(grid, resolution, origin)
    known = np.isfinite(grid)
    if known.any():
        lo, hi = np.nanpercentile(grid, [1, 99])
        if hi <= lo:
            lo, hi = lo - 0.5, hi + 0.5
        # shading needs a value everywhere: unknown cells take their nearest known value
        # (a constant fill would cast false cliffs around every hole) and are hidden after
        from scipy.ndimage import distance_transform_edt

        nearest = distance_transform_edt(~known, return_distances=False, return_indices=True)
        filled = grid[tuple(nearest)]
        ls = LightSource(azdeg=azimuth_deg, altdeg=altitude_deg)
        import matplotlib
        from matplotlib.colors import ListedColormap

        # gist_earth without its black low end and white high end, so that white can
        # only mean "unknown" and shading stays visible on the highest terrain
        cmap = ListedColormap(matplotlib.colormaps["gist_earth"](np.linspace(0.12, 0.88, 256)))
        norm = Normalize(lo, hi)
        # LightSource works with row 0 at the top; the grid has row 0 south, so flip.
        rgb = ls.shade(filled[::-1], cmap=cmap, norm=norm, blend_mode="overlay",
                       vert_exag=1.0, dx=resolution, dy=resolution)[::-1]
        rgb[~known] = (1.0, 1.0, 1.0, 0.0)
        ax.set_facecolor("#e4e4e4")
        ax.imshow(rgb, origin="lower", extent=ext, interpolation="nearest")
        cb = fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax, shrink=0.8)
        cb.set_label("elevation (m)")
    share = 100.0 * known.mean()
    ax.set_title(f"{title}\n{grid.shape[1]} × {grid.shape[0]} cells of {resolution:g} m, "
                 f"{share:.1f} % known", fontsize=10)
    return _save(fig, path)


def dem_error_png(
    error: Any,
    resolution: float,
    origin: tuple[float, float],
    path: str | Path,
    *,
    title: str = "DEM error",
    limit_m: float | None = None,
) -> Path:
    """Map of a DEM's error (estimate − reference), diverging colours centred at 0.

    error: (rows, cols) float, metres, NaN = not compared; row 0 south. resolution: m/cell;
    origin: south-west corner, metres. Colours are clipped at ±``limit_m`` (default: the
    99th percentile of |error|), blue below the reference, red above; the title gives
    RMSE, bias and the number of cells.
    """
    grid = _grid(error, resolution, "error")
    fig, ax, ext = _grid_figure(grid, resolution, origin)
    known = np.isfinite(grid)
    vals = grid[known]
    if limit_m is None:
        limit_m = float(np.percentile(np.abs(vals), 99)) if vals.size else 1.0
    limit_m = max(float(limit_m), 1e-3)
    im = ax.imshow(np.ma.masked_invalid(grid), origin="lower", extent=ext, cmap="RdBu_r",
                   vmin=-limit_m, vmax=limit_m, interpolation="nearest")
    cb = fig.colorbar(im, ax=ax, shrink=0.8, extend="both")
    cb.set_label("DEM − reference (m)")
    if vals.size:
        stats = (f"RMSE {np.sqrt(np.mean(vals ** 2)):.3f} m, bias {vals.mean():+.3f} m, "
                 f"{_thousands(vals.size)} cells")
    else:
        stats = "no cell compared"
    ax.set_title(f"{title}\n{stats}", fontsize=10)
    return _save(fig, path)


# --------------------------------------------------------------------------- k choice, latency


def elbow_png(ks: Any, sse: Any, chosen_k: int, path: str | Path, *,
              title: str = "elbow method") -> Path:
    """Within-cluster SSE against k, the chosen k circled (seeds 000/003 and 002; the
    DEM benchmark draws it). ks: (M,) int; sse: (M,) float, sum of squared distances in
    standardised units."""
    k = np.asarray(ks, dtype=np.float64).ravel()
    v = np.asarray(sse, dtype=np.float64).ravel()
    if k.size == 0 or k.shape != v.shape:
        raise CloudFormatError(f"ks and sse must be 1-D of equal non-zero length, got "
                               f"{k.shape} and {v.shape}")
    fig = _figure(6.4, 4.2)
    ax = fig.add_subplot()
    ax.plot(k, v, "-o", color="#1f5fd6", markersize=5, linewidth=1.5)
    hit = np.flatnonzero(k == chosen_k)
    if hit.size:
        ax.axvline(chosen_k, color="#d62728", linestyle="--", linewidth=1)
        ax.plot(k[hit], v[hit], "o", markersize=11, markerfacecolor="none",
                markeredgecolor="#d62728", markeredgewidth=2, label=f"chosen k = {chosen_k}")
        ax.legend(frameon=False)
    ax.set_xticks(k)
    ax.set_xlabel("number of clusters k")
    ax.set_ylabel("within-cluster SSE (standardised units²)")
    if (v > 0).all():  # SSE falls by orders of magnitude; the sweep may reach 0
        ax.set_yscale("log")
    ax.set_title(f"{title}\nthe bend marks where more clusters stop paying", fontsize=10)
    ax.grid(True, color="#e6e6e6")
    return _save(fig, path)


def latency_histogram_png(latencies_s: Any, path: str | Path, *,
                          title: str = "processing latency per message") -> Path:
    """Histogram of per-message latencies in milliseconds with p50/p95/p99 lines.

    latencies_s: (M,) seconds (NaN ignored).
    """
    lat = np.asarray(latencies_s, dtype=np.float64).ravel()
    lat = lat[np.isfinite(lat)] * 1000.0
    if lat.size == 0:
        raise CloudFormatError("latency_histogram_png: no finite latency")
    stats = latency_stats(lat / 1000.0)
    fig = _figure(7.0, 4.2)
    ax = fig.add_subplot()
    ax.hist(lat, bins=min(60, max(10, lat.size // 5)), color="#9ab6d8", edgecolor="white",
            linewidth=0.5)
    for key, colour, style in (("p50_s", "#1f5fd6", "-"), ("p95_s", "#ff7f0e", "--"),
                               ("p99_s", "#d62728", ":")):
        ax.axvline(stats[key] * 1000.0, color=colour, linestyle=style, linewidth=1.5,
                   label=f"{key[:3]} = {stats[key] * 1000.0:.1f} ms")
    ax.legend(frameon=False)
    ax.set_xlabel("latency (ms)")
    ax.set_ylabel("messages")
    ax.set_title(f"{title}\n{lat.size} messages, max {lat.max():.1f} ms", fontsize=10)
    ax.grid(True, axis="y", color="#e6e6e6")
    return _save(fig, path)


# --------------------------------------------------------------------------- HTML report

# Short explanations shown next to metric values, by the last key of their path.
EXPLANATIONS: dict[str, str] = {
    "n_points": "points compared",
    "overall_accuracy": "P_c = Σ q_ii / Q: share of points whose class is right",
    "kappa": "Cohen's kappa (P_o − P_e) / (1 − P_e): agreement beyond chance; 1 perfect, 0 chance",
    "users_accuracy": "q_ii / Q_i+: of the points labelled this class, the share that is it",
    "producers_accuracy": "q_ii / Q_+i: of the reference points of this class, the share found",
    "users_kappa": "conditional kappa of the points labelled this class",
    "producers_kappa": "conditional kappa of the reference points of this class",
    "type_i": "ground points rejected / reference ground (ISPRS Type I)",
    "type_ii": "object points accepted as ground / reference objects (ISPRS Type II)",
    "total_error": "ground/object misclassifications / all points",
    "n_ground": "reference ground points",
    "n_object": "reference object points",
    "n_eligible": "blocks where ground and object each hold ≥ min_class_share of the points",
    "share_kappa_gt_0_8": "eligible blocks with kappa > 0.8 (the paper's: 88.6 %)",
    "share_kappa_gt_0_6": "eligible blocks with kappa > 0.6 (the paper's: 91.67 %)",
    "mean_kappa": "mean kappa of the eligible blocks",
    "wire_as_ground": "wire points (13, 14) predicted as ground: a UAV would not see them",
    "tower_as_ground": "tower points (15, 16) predicted as ground",
    "obstacle_as_ground": "wire and tower points predicted as ground",
    "n_wire": "reference wire points (13, 14)",
    "n_tower": "reference tower points (15, 16)",
    "n_raised_object": "reference object points of any class more than 1 m above the "
                       "reference ground",
    "raised_object_as_ground": "those predicted as ground: a UAV would fly into them",
    "rmse_m": "root mean square height error, metres",
    "mae_m": "mean absolute height error, metres",
    "bias_m": "mean of (estimate − reference), metres",
    "max_abs_m": "largest absolute height error, metres",
    "r2": "coefficient of determination 1 − SS_res / SS_tot",
    "n": "values compared",
    "coverage": "share of the reference DEM's cells inside the data that the DEM has",
    "p50_s": "median latency, seconds",
    "p95_s": "95th percentile latency, seconds",
    "p99_s": "99th percentile latency, seconds",
    "max_s": "largest latency, seconds",
    "mean_s": "mean latency, seconds",
    "correlation": "Pearson r of the simplified and the full raster (the paper's: 0.890)",
    "reduction": "share of points removed",
}

_PERCENT_KEYS = {
    "overall_accuracy", "users_accuracy", "producers_accuracy", "type_i", "type_ii",
    "total_error", "share_kappa_gt_0_8", "share_kappa_gt_0_6", "wire_as_ground",
    "tower_as_ground", "obstacle_as_ground", "reduction", "coverage",
    "raised_object_as_ground",
}

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:2em auto;
max-width:1150px;color:#1a1a1a;line-height:1.45;padding:0 1em}
h1{font-size:1.6em;margin-bottom:.2em}h2{font-size:1.25em;margin-top:1.8em;
border-bottom:1px solid #ddd;padding-bottom:.2em}h3{font-size:1.05em;margin-top:1.2em}
table{border-collapse:collapse;margin:.6em 0;font-size:.92em}
th,td{border:1px solid #d8d8d8;padding:.25em .6em;text-align:right;vertical-align:top}
th{background:#f3f3f3}td.k,th.k{text-align:left;font-family:ui-monospace,monospace}
td.x{text-align:left;color:#555;font-size:.92em}.headline{display:flex;flex-wrap:wrap;
gap:.8em;margin:1em 0}.card{border:1px solid #ddd;border-radius:6px;padding:.5em .9em;
min-width:9em}.card .v{font-size:1.4em;font-weight:600}.card .l{color:#555;font-size:.85em}
figure{margin:1.2em 0}figure img{max-width:100%;border:1px solid #eee}
figcaption{color:#444;font-size:.9em}.notes{background:#f8f8f4;border-left:4px solid #c8b88a;
padding:.5em 1em}code{font-size:.92em}
"""

_CAPTIONS: dict[str, str] = {
    "confusion": "Confusion matrix: rows predicted, columns reference; colour and "
                 "percentage are the share of the reference class (the diagonal is the "
                 "producer's accuracy).",
    "block_kappa": "Ground/object kappa per block; hatched blocks are not eligible "
                   "(one class under the minimum share).",
    "cloud_reference": "Reference classes, top and side view.",
    "cloud_predicted": "Predicted classes, top and side view.",
    "errors": "Where the prediction is wrong: Type I (ground rejected), Type II "
              "(object taken as ground), other (wrong object class).",
    "hillshade": "Hill-shaded DEM.",
    "dem": "Hill-shaded DEM.",
    "dem_error": "DEM minus reference; blue below, red above the reference.",
    "elbow": "Elbow method: within-cluster SSE against k.",
    "silhouette": "Mean silhouette coefficient against k.",
    "latency": "Processing latency per message.",
}


def _fmt(key: str, value: Any) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return _thousands(value)
    if isinstance(value, float):
        if key in _PERCENT_KEYS:
            return f"{100.0 * value:.2f} %"
        if key.endswith("_s"):
            return f"{1000.0 * value:.2f} ms"
        if key.endswith("_m"):
            return f"{value:.3f} m"
        return f"{value:.4f}"
    return html.escape(str(value))


def _is_matrix(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(r, list) for r in value)


def _flat_rows(prefix: str, value: Any) -> list[tuple[str, str, str]]:
    """(dotted key, formatted value, explanation) for the leaves of a nested dict."""
    if isinstance(value, dict):
        rows = []
        for k, v in value.items():
            rows += _flat_rows(f"{prefix}.{k}" if prefix else str(k), v)
        return rows
    if _is_matrix(value):
        return []  # matrices are shown as tables or pictures, not as one cell
    leaf = prefix.rsplit(".", 1)[-1]
    if isinstance(value, list):
        text = html.escape(", ".join(str(v) for v in value))
    else:
        text = _fmt(leaf, value)
    return [(prefix, text, EXPLANATIONS.get(leaf, ""))]


def _table_flat(section: Mapping[str, Any]) -> str:
    rows = "".join(
        f'<tr><td class="k">{html.escape(k)}</td><td>{v}</td>'
        f'<td class="x">{html.escape(x)}</td></tr>'
        for k, v, x in _flat_rows("", section)
    )
    return ("<table><tr><th class='k'>metric</th><th>value</th><th class='k'>meaning</th></tr>"
            f"{rows}</table>")


def _classes_html(sec: Mapping[str, Any]) -> str:
    """Tables for an :func:`evaluate_classes` result."""
    out = []
    go = sec.get("ground_object") or {}
    blocks = sec.get("blocks") or {}
    cards = [
        ("overall accuracy", _fmt("overall_accuracy", sec.get("overall_accuracy"))),
        ("kappa (all classes)", _fmt("kappa", sec.get("kappa"))),
        ("Type I", _fmt("type_i", go.get("type_i"))),
        ("Type II", _fmt("type_ii", go.get("type_ii"))),
        ("total error", _fmt("total_error", go.get("total_error"))),
        ("ground/object kappa", _fmt("kappa", go.get("kappa"))),
    ]
    if blocks:
        cards.append(("blocks with kappa > 0.8",
                      _fmt("share_kappa_gt_0_8", blocks.get("share_kappa_gt_0_8"))))
    safety = sec.get("safety") or {}
    if safety.get("obstacle_as_ground") is not None:
        cards.append(("wires/towers taken as ground",
                      _fmt("obstacle_as_ground", safety.get("obstacle_as_ground"))))
    if sec.get("reference_classes_objects") is False:
        out.append("<p class='x'>The reference tells ground from object only (its objects "
                   "are ASPRS 0 or 1, as ISPRS's): the predicted objects count as "
                   "<i>other</i>, and the figures over all classes are those of ground "
                   "and object.</p>")
    elif sec.get("merged_into_other"):
        out.append("<p class='x'>The reference has no " + html.escape(
            " or ".join(sec["merged_into_other"])) + " class (its <i>other</i> holds them, "
                   "as AHN4's class 1): the points predicted so count as <i>other</i>.</p>")
    out.append("<div class='headline'>" + "".join(
        f"<div class='card'><div class='v'>{v}</div><div class='l'>{html.escape(label)}</div></div>"
        for label, v in cards) + "</div>")
    conf = sec.get("confusion") or {}
    matrix, labels = conf.get("matrix"), conf.get("labels")
    if _is_matrix(matrix) and labels:
        m = np.asarray(matrix, dtype=np.int64)
        keep = (m.sum(axis=0) + m.sum(axis=1)) > 0
        idx = np.flatnonzero(keep) if keep.any() else np.arange(len(labels))
        head = "".join(f"<th>{html.escape(labels[j])}</th>" for j in idx)
        body = "".join(
            f"<tr><th class='k'>{html.escape(labels[i])}</th>"
            + "".join(f"<td>{_fmt('', int(m[i, j]))}</td>" for j in idx)
            + f"<td><b>{_fmt('', int(m[i].sum()))}</b></td></tr>" for i in idx)
        foot = "".join(f"<td><b>{_fmt('', int(m[:, j].sum()))}</b></td>" for j in idx)
        out.append("<h3>Confusion matrix (rows predicted, columns reference)</h3>"
                   f"<table><tr><th class='k'>predicted \\ reference</th>{head}"
                   "<th>Q<sub>i+</sub></th></tr>"
                   f"{body}<tr><th class='k'>Q<sub>+i</sub></th>{foot}"
                   f"<td><b>{_fmt('', int(m.sum()))}</b></td></tr></table>")
    per = sec.get("per_class") or {}
    cols = ("reference_count", "predicted_count", "users_accuracy", "producers_accuracy",
            "users_kappa", "producers_kappa")
    rows = "".join(
        f"<tr><th class='k'>{html.escape(name)}</th>"
        + "".join(f"<td>{_fmt(c, d.get(c))}</td>" for c in cols) + "</tr>"
        for name, d in per.items() if d.get("reference_count") or d.get("predicted_count"))
    if rows:
        out.append("<h3>Per class</h3><table><tr><th class='k'>class</th>"
                   + "".join(f"<th>{c.replace('_', ' ')}</th>" for c in cols)
                   + f"</tr>{rows}</table>"
                   "<p class='x'>User's accuracy q<sub>ii</sub>/Q<sub>i+</sub> (commission "
                   "side), producer's accuracy q<sub>ii</sub>/Q<sub>+i</sub> (omission side); "
                   "conditional kappa user's (Q q<sub>ii</sub> − Q<sub>i+</sub>Q<sub>+i</sub>) / "
                   "(Q Q<sub>i+</sub> − Q<sub>i+</sub>Q<sub>+i</sub>), producer's with "
                   "Q<sub>+i</sub> in the denominator.</p>")
    rest = {k: v for k, v in sec.items() if k in ("n_points", "overall_accuracy", "kappa")}
    for name in ("ground_object", "blocks", "safety"):
        if sec.get(name):
            rest[name] = sec[name]
    out.append("<h3>All figures</h3>" + _table_flat(rest))
    return "".join(out)


# what _classes_html shows of an evaluate_classes result
_CLASS_KEYS = ("n_points", "groups", "reference_classes_objects", "merged_into_other",
               "confusion", "overall_accuracy", "kappa", "per_class", "ground_object", "blocks",
               "safety")


def _sections(metrics: dict[str, Any]) -> dict[str, Any]:
    """The report's sections. `evaluate`'s figures come flat, the classes' beside the
    input's, the DEM's and the latency's: its classes make one section (the headline
    cards, the confusion matrix, the per-class table), its plain values another, each
    other dict one more. A dict of sections passes as it is."""
    if not isinstance(metrics.get("confusion"), dict):
        return metrics
    classes = {k: metrics[k] for k in _CLASS_KEYS if k in metrics}
    rest = {k: v for k, v in metrics.items() if k not in classes}
    plain = {k: v for k, v in rest.items() if not isinstance(v, dict) or k == "reject_reasons"}
    return {"classes": classes, **({"input": plain} if plain else {}),
            **{k: v for k, v in rest.items() if k not in plain}}


def write_report(
    out_dir: str | Path,
    metrics: Mapping[str, Any],
    images: Mapping[str, str | Path],
    *,
    title: str = "lidar_obstacles evaluation",
    notes: str = "",
) -> Path:
    """Write ``report.html`` (self-contained) and ``metrics.json`` into ``out_dir``.

    metrics: JSON-like dict of sections, e.g. ``{"classes": evaluate_classes(...),
        "dem": grid_errors(...), "latency": latency_stats(...)}``; a section that has a
        ``confusion`` key is rendered as classification tables (headline figures,
        confusion matrix, per-class table), any other as a metric/value/meaning table.
        NumPy values are converted; NaN becomes null. `evaluate`'s flat dict (an
        evaluate_classes result with the input's, the DEM's and the latency's figures beside
        it) is split into such sections for the page; metrics.json keeps it as given.
    images: caption key -> PNG path, embedded in the given order as base64 data URIs
        (known keys such as ``confusion``, ``block_kappa``, ``errors``, ``dem_error``
        get a standard caption).
    notes: plain text shown under the title (input file, parameters...).
    Both files are written atomically. Returns the path of ``report.html``.
    Raises LidarObstaclesError when an image is missing.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    clean = jsonable(dict(metrics))
    figures = []
    for key, p in images.items():
        p = Path(p)
        if not p.is_file():
            raise LidarObstaclesError(f"report image '{key}' not found: {p}")
        data = base64.b64encode(p.read_bytes()).decode("ascii")
        caption = _CAPTIONS.get(key, key.replace("_", " "))
        figures.append(f"<figure id='fig-{html.escape(key)}'><img alt='{html.escape(key)}' "
                       f"src='data:image/png;base64,{data}'><figcaption><b>"
                       f"{html.escape(key)}</b> — {html.escape(caption)}</figcaption></figure>")
    sections = []
    for name, sec in _sections(clean).items():
        sections.append(f"<h2>{html.escape(str(name))}</h2>")
        if isinstance(sec, dict) and "confusion" in sec:
            sections.append(_classes_html(sec))
        elif isinstance(sec, dict):
            sections.append(_table_flat(sec))
        else:
            sections.append(_table_flat({name: sec}))
    from lidar_obstacles import __version__

    notes_html = (f"<div class='notes'>{'<br>'.join(html.escape(l) for l in notes.splitlines())}"
                  "</div>") if notes.strip() else ""
    doc = (
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width,initial-scale=1'>"
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>"
        f"<h1>{html.escape(title)}</h1><p style='color:#666'>lidar_obstacles {__version__}. "
        "Rates are shares of points; rows of confusion matrices are the prediction, "
        "columns the reference. The same figures are in <code>metrics.json</code>.</p>"
        f"{notes_html}{''.join(sections)}"
        + ("<h2>Pictures</h2>" + "".join(figures) if figures else "")
        + "</body></html>\n"
    )
    text = json.dumps(clean, indent=2, allow_nan=False) + "\n"
    atomic_write_text(out / "metrics.json", text, kind=JSON)
    return atomic_write_text(out / "report.html", doc, kind=HTML)
