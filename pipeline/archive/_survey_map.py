"""The map of a survey on its index page: ``OUT_DIR/map.png``.

The surveyed area in the history's CRS (:mod:`pipeline.archive._history`):
every capture's coverage (those of the history's latest night outlined in
blue, earlier nights' in grey; the map is a function of the history alone)
and every change of the history filled by its status (new red, persisting
orange, gone hollow grey, unobserved purple), drawn by matplotlib (Agg, no
display) and written aside and renamed.  Changes are small beside a capture:
each is also marked by a dot of its status's colour so that none disappears at
the map's scale.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["MAP_NAME", "STATUS_COLOURS", "preload", "write_map"]

MAP_NAME = "map.png"
STATUS_COLOURS = {"new": "#d62728", "persisting": "#ff7f0e", "gone": "#7f7f7f", "unobserved": "#9467bd"}


def _path(geometry):
    """A matplotlib Path of a shapely (multi)polygon (exterior and holes, even-odd filled)."""
    import shapely
    from matplotlib.path import Path as MPath

    rings = []
    for polygon in shapely.get_parts(geometry):
        if polygon.geom_type != "Polygon" or polygon.is_empty:
            continue
        rings.append(MPath(np.asarray(polygon.exterior.coords)[:, :2], closed=True))
        rings.extend(MPath(np.asarray(r.coords)[:, :2], closed=True) for r in polygon.interiors)
    return MPath.make_compound_path(*rings) if rings else None


def _crs_name(crs):
    """A short name of the history's CRS for the axis label (its code, else its name)."""
    from pyproj import CRS

    if crs is None:
        return "no CRS"
    crs = CRS.from_user_input(crs)
    code = crs.to_authority()
    return f"{crs.name} ({':'.join(code)})" if code else crs.name


def _patches(geometries, **style):
    from matplotlib.collections import PathCollection

    paths = [p for p in map(_path, geometries) if p is not None]
    return PathCollection(paths, **style) if paths else None


def preload():
    """Import what :func:`write_map` draws with (matplotlib, whose import is
    long-running Python): a night calls it in a thread of its own as its
    captures start, so that the imports run beside their detection, not after
    the last one.  It
    never raises: an import that fails here fails again, and is reported, when
    the map is drawn."""
    try:
        _matplotlib()
    except Exception:  # noqa: BLE001 - write_map reports it
        pass


def _matplotlib():
    """matplotlib on its Agg backend (no display) with every module the map
    draws with imported (:func:`_path`, :func:`_patches` and the canvas that
    writes the PNG too); returns ``(Figure, Line2D, Patch)``."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.backends.backend_agg  # noqa: F401
    from matplotlib import collections, figure, lines, patches, path  # noqa: F401

    return figure.Figure, lines.Line2D, patches.Patch


def write_map(path, history, *, width_px=900):
    """Draw ``history`` (a :class:`History`) into ``path`` (PNG), its latest night's footprints in blue.

    Returns the path, or None when the history has no footprint (nothing to draw)."""
    Figure, Line2D, Patch = _matplotlib()
    if not history.footprints:
        return None
    night = max(f.night for f in history.footprints)
    fig = Figure(figsize=(width_px / 100, width_px / 100 * 0.75), dpi=100)
    ax = fig.add_subplot()
    earlier = [f.geometry for f in history.footprints if f.night != night]
    tonight = [f.geometry for f in history.footprints if f.night == night]
    for geoms, edge in ((earlier, "#999999"), (tonight, "#1f77b4")):
        patches = _patches(geoms, facecolor=(0.85, 0.88, 0.92, 0.35), edgecolor=edge, linewidth=1.2)
        if patches is not None:
            ax.add_collection(patches)
    handles = [Patch(facecolor=(0.85, 0.88, 0.92), edgecolor="#1f77b4", label=f"capture, night {night}"),
               Patch(facecolor=(0.85, 0.88, 0.92), edgecolor="#999999", label="capture, earlier night")]
    for status, colour in STATUS_COLOURS.items():
        geoms = [c.geometry for c in history.changes if c.status == status]
        hollow = status == "gone"
        patches = _patches(geoms, facecolor="none" if hollow else colour, edgecolor=colour, linewidth=1.0)
        if patches is not None:
            ax.add_collection(patches)
            centres = np.array([[g.centroid.x, g.centroid.y] for g in geoms])
            ax.scatter(centres[:, 0], centres[:, 1], s=14, marker="o", facecolors="none" if hollow else colour,
                       edgecolors=colour, linewidths=1.0, zorder=3)
        handles.append(Line2D([], [], marker="o", linestyle="none", markerfacecolor="none" if hollow else colour,
                              markeredgecolor=colour, label=f"{status} ({len(geoms)})"))
    import shapely

    x0, y0, x1, y1 = shapely.total_bounds([f.geometry for f in history.footprints])
    pad = 0.03 * max(x1 - x0, y1 - y0, 1e-9)
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    ax.set_aspect("equal")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(labelsize=8)
    ax.set_xlabel(f"x, {_crs_name(history.crs)}", fontsize=9)
    ax.set_ylabel("y", fontsize=9)
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    fig.tight_layout()
    path = Path(path)
    tmp = path.with_name(f".{path.name}.partial")
    fig.savefig(tmp, format="png", bbox_inches="tight")  # no margin around the area
    os.replace(tmp, path)
    return path
