"""The vector figures of ``rsmb report`` written as SVG text: the trajectory
panels (``trajectory.svg``), the per-tile maps (``gain.svg``,
``agreement.svg``) and the frame of the change score (axes, title and colorbar
around ``change_score.png``, inline in the page).

Nothing here reads a store or imports matplotlib: the callers pass arrays and
colours.  Coordinates are SVG user-space pixels rounded to 0.1 px; text is
drawn by the browser, so its width is only estimated (for centring the legend
and placing the y label beside the tick labels).
"""

import html
import math

import numpy as np

FONT = "DejaVu Sans, Verdana, Arial, Helvetica, sans-serif"
_SIZE = 14  # px, axis labels; tick labels and notes are smaller
_TICK_SIZE = 13
# line widths, px: matplotlib's defaults in points (1.6 pt the fused path, 0.8 pt thin lines) at 100 dpi
_BOLD, _THIN, _TICK = 2.2, 1.1, 4.9
_CHAR = 0.6  # estimated mean glyph width, ems
_LEVELS = (256, 64, 16, 4, 2)  # chunk lengths of the polyline simplification, each dividing the one before
_TOLERANCE = 0.05  # px: a dropped point is at most this far from the drawn chord (plus 0.05 px of rounding)


# --------------------------------------------------------------------------- primitives


def nice_ticks(lo, hi, nbins):
    """Ticks in ``[lo, hi]`` at a step of 1, 2, 2.5 or 5 times a power of ten,
    at most ``nbins`` steps apart end to end (matplotlib's ``MaxNLocator``).

    Returns
    -------
    ticks : list of float
    step : float
    """
    raw = max(hi - lo, 1e-300) / nbins
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(s * mag for s in (1.0, 2.0, 2.5, 5.0, 10.0) if s * mag >= raw * (1 - 1e-9))
    first = math.ceil(lo / step - 1e-9)
    count = math.floor(hi / step + 1e-9) - first + 1
    return [(first + i) * step for i in range(max(count, 0))], step


def tick_labels(ticks, step):
    """Labels with as many decimals as ``step`` needs (all alike); scientific
    notation when that would be more than 6; a typographic minus sign."""
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    while decimals < 12 and abs(round(step, decimals) - step) > 1e-9 * step:
        decimals += 1
    if decimals > 6:
        labels = [f"{t:.2g}" if abs(t) > 0.5 * step else "0" for t in ticks]
    else:
        labels = [f"{0.0 if abs(t) < 1e-9 * step else t:.{decimals}f}" for t in ticks]
    return [s.replace("-", "\u2212") for s in labels]


def text_width(text, size):
    """Estimated width of ``text`` at font size ``size``, px."""
    return _CHAR * size * len(text)


def esc(value):
    return html.escape(str(value), quote=True)


def _n(value):
    """A coordinate: 0.1 px, no trailing ``.0``."""
    return f"{value:.1f}".removesuffix(".0")


def _text(x, y, value, *, size=_SIZE, anchor="start", middle=False, rotate=False, fill=None):
    """A ``<text>``; ``middle`` centres it vertically on ``y``, ``rotate``
    turns it a quarter counter-clockwise about ``(x, y)``."""
    attrs = f'x="{_n(x)}" y="{_n(y)}"'
    if rotate:
        attrs += f' transform="rotate(-90 {_n(x)} {_n(y)})"'
    if anchor != "start":
        attrs += f' text-anchor="{anchor}"'
    if middle:
        attrs += ' dominant-baseline="central"'
    if size != _SIZE:
        attrs += f' font-size="{size}"'
    if fill is not None:
        attrs += f' fill="{fill}"'
    return f"<text {attrs}>{esc(value)}</text>"


def _document(width, height, body, *, standalone=True):
    """The ``<svg>`` element (with an XML declaration when ``standalone``)."""
    head = '<?xml version="1.0" encoding="utf-8"?>\n' if standalone else ""
    return (f'{head}<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
            f'viewBox="0 0 {width} {height}" font-family="{FONT}" font-size="{_SIZE}">\n'
            + "\n".join(body) + "\n</svg>\n")


# --------------------------------------------------------------------------- compact polylines


def polylines(x, y):
    """``points`` attributes of the line through ``(x, y)``: one per run of
    finite ``y`` (NaN breaks the line), coordinates rounded to 0.1 px, without
    the points that the line through the kept ones passes within
    :data:`_TOLERANCE` of.

    Parameters
    ----------
    x : ndarray, shape (n,)
        Strictly increasing, px.
    y : ndarray, shape (n,)
        px; NaN where unknown.

    Returns
    -------
    list of str
        A lone finite point gives a two-point line of zero length (a dot with
        round caps).
    """
    finite = np.isfinite(y)
    edges = np.flatnonzero(np.diff(np.concatenate([[False], finite, [False]]).astype(np.int8)))
    out = []
    for start, stop in zip(edges[::2].tolist(), edges[1::2].tolist()):
        xs, ys = x[start:stop], y[start:stop]
        if xs.size == 1:
            xs, ys = np.repeat(xs, 2), np.repeat(ys, 2)
        else:
            keep = _simplify(xs, ys, _TOLERANCE)
            xs, ys = xs[keep], ys[keep]
        pairs = zip(np.round(xs, 1).tolist(), np.round(ys, 1).tolist())
        text = " ".join(f"{a:.1f},{b:.1f}" for a, b in pairs) + " "
        out.append(text.replace(".0,", ",").replace(".0 ", " ").rstrip())
    return out


def _simplify(x, y, tol):
    """Mask of the points to keep so that every dropped point lies within
    ``tol`` (vertically, so at least as close across the line) of the chord
    between the kept points around it.

    Chunks of :data:`_LEVELS` points, coarse to fine: a chunk whose inner
    points all lie within ``tol`` of its end points' chord drops them.  The
    chunks nest, so the ends of a chunk that drops points are kept (they are
    never inside another dropping chunk) and the drawn line between them is
    that chord.  Vectorised: a few numpy passes per level, no loop over points.
    """
    n = x.size
    dropped = np.zeros(n, bool)
    idx = np.arange(n - 1)
    for k in _LEVELS:
        starts = np.arange(0, n - 1, k)
        s = idx - idx % k
        e = np.minimum(s + k, n - 1)
        chord = y[s] + (y[e] - y[s]) * (x[idx] - x[s]) / (x[e] - x[s])
        worst = np.maximum.reduceat(np.abs(y[idx] - chord), starts)
        dropped[:-1] |= (worst <= tol)[idx // k] & (idx % k != 0)
    return ~dropped


# --------------------------------------------------------------------------- trajectory


def trajectory_svg(rows, fused, per_tile, labels, colors, edges, *, flat=(), width=1000):
    """The trajectory figure: one panel per drawn pose axis.

    Parameters
    ----------
    rows : ndarray, shape (H,)
        Row of each pose, px (increasing).
    fused : ndarray, shape (H, P)
        The fused trajectory of the ``P`` drawn axes.
    per_tile : ndarray, shape (H, tiles_x, P), or None
        Each tile column's own trajectory; NaN where unsolved.
    labels : list of str, length P
        Axis labels with units, ``"tx (px)"``.
    colors : list of str
        One CSS colour per tile column.
    edges : sequence of float
        Tile-row boundaries, px (dashed verticals).
    flat : sequence of str
        Labels of the axes not drawn (zero on every row): a note under the panels.
    width : int
        Figure width, px.

    Returns
    -------
    svg : str
    height : int
        Figure height, px.
    """
    count = fused.shape[1]
    left, right, top, gap, panel = 90, 21, 58, 12, 170
    height = round(top + count * panel + (count - 1) * gap + 50 + (22 if flat else 0))
    pw = width - left - right
    x0, x1 = float(rows[0]), max(float(rows[-1]), float(rows[0]) + 1.0)
    px = (rows - x0) * (pw / (x1 - x0))
    xticks, xstep = nice_ticks(x0, x1, 9)
    xt = [(t - x0) * pw / (x1 - x0) for t in xticks]
    body = [_text(width / 2, 22, "Per-row camera pose (centroid)", size=17, anchor="middle")]
    body += _legend(width / 2, 42, colors)
    for i in range(count):
        tiles = None if per_tile is None else per_tile[:, :, i]
        body.append(f'<g class="panel" transform="translate({left} {top + i * (panel + gap)})">')
        body += _panel(px, fused[:, i], tiles, colors, xt, [(e - x0) * pw / (x1 - x0) for e in edges],
                       pw, panel, labels[i])
        body.append("</g>")
    base = top + count * panel + (count - 1) * gap
    body += [_text(left + x, base + 19, s, size=_TICK_SIZE, anchor="middle")
             for x, s in zip(xt, tick_labels(xticks, xstep))]
    body.append(_text(left + pw / 2, base + 40, "row (px); dashed: tile-row boundaries", anchor="middle"))
    if flat:
        body.append(_text(left, height - 8, f"Not drawn, zero on every row: {', '.join(flat)}", size=_TICK_SIZE))
    return _document(width, height, body), height


def _panel(px, fused, tiles, colors, xt, edges, pw, ph, label):
    """One axis in panel coordinates (origin at its top-left corner): grid,
    tile-row boundaries, the tile columns' paths, the fused path, frame,
    ticks and labels."""
    values = fused if tiles is None else np.concatenate([fused, tiles.ravel()])
    lo, hi = _padded_range(values)
    scale = ph / (hi - lo)
    yticks, ystep = nice_ticks(lo, hi, 5)
    yt = [(hi - t) * scale for t in yticks]
    grid = "".join(f"M{_n(x)} 0V{ph}" for x in xt) + "".join(f"M0 {_n(y)}H{pw}" for y in yt)
    ticks = "".join(f"M{_n(x)} {ph}v{_TICK}" for x in xt) + "".join(f"M0 {_n(y)}h-{_TICK}" for y in yt)
    out = [f'<path d="{grid}" stroke="#e6e6e6" stroke-width="0.8"/>']
    if edges:
        out.append(f'<path d="{"".join(f"M{_n(x)} 0V{ph}" for x in edges)}" stroke="#737373" '
                   f'stroke-width="{_THIN}" stroke-dasharray="4.1 1.8"/>')
    lines = '<g fill="none" stroke-linejoin="round" stroke-linecap="round">'
    if tiles is not None:
        alpha = 0.85 if len(colors) <= 10 else 0.5
        for tx in range(tiles.shape[1]):
            pts = polylines(px, (hi - tiles[:, tx]) * scale)
            lines += (f'<g stroke="{colors[tx]}" stroke-width="{_THIN}" stroke-opacity="{alpha}">'
                      + "".join(f'<polyline points="{p}"/>' for p in pts) + "</g>")
    lines += (f'<g stroke="#000" stroke-width="{_BOLD}">'
              + "".join(f'<polyline points="{p}"/>' for p in polylines(px, (hi - fused) * scale)) + "</g></g>")
    out.append(lines)
    out.append(f'<rect width="{pw}" height="{ph}" fill="none" stroke="#000" stroke-width="{_THIN}"/>')
    out.append(f'<path d="{ticks}" stroke="#000" stroke-width="{_THIN}"/>')
    names = tick_labels(yticks, ystep)
    out += [_text(-6, y, s, size=_TICK_SIZE, anchor="end", middle=True) for y, s in zip(yt, names)]
    widest = max((text_width(s, _TICK_SIZE) for s in names), default=0.0)
    out.append(_text(max(-78.0, -widest - 18), ph / 2, label, anchor="middle", rotate=True))
    return out


def _padded_range(values):
    """Axis limits around the finite ``values`` with 5 % room (a flat or empty
    series gets a unit-wide range)."""
    finite = values[np.isfinite(values)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 0.0)
    pad = 0.05 * (hi - lo) if hi > lo else max(0.5, 0.05 * abs(lo))
    return lo - pad, hi + pad


def _legend(cx, y, colors):
    """Fused first, then one entry per tile column (one for all beyond 8),
    centred on ``cx``."""
    entries = [("fused", "#000", _BOLD)]
    if len(colors) > 8:
        entries.append((f"tile columns 0..{len(colors) - 1}", colors[len(colors) // 2], _THIN))
    else:
        entries += [(f"tile column {tx}", c, _THIN) for tx, c in enumerate(colors)]
    size = _TICK_SIZE
    widths = [28 + 6 + text_width(name, size) for name, _, _ in entries]
    x = cx - (sum(widths) + 20 * (len(widths) - 1)) / 2
    out = []
    for (name, color, lw), w in zip(entries, widths):
        out.append(f'<path d="M{_n(x)} {y}h28" stroke="{color}" stroke-width="{lw}"/>')
        out.append(_text(x + 34, y, name, size=size, middle=True))
        x += w + 20
    return out


# --------------------------------------------------------------------------- change score frame


def score_frame_svg(href, size, *, factor, zoom, vmax, threshold, stops):
    """Axes, title and colorbar around the score image ``href``, for the page.

    Parameters
    ----------
    href : str
        The score PNG, one value per pixel, relative to the page.
    size : (int, int)
        Its width and height, PNG pixels; drawn ``zoom`` times larger.
    factor : int
        Full-resolution pixels per PNG pixel on a side (the tick values are
        full-resolution rows and columns).
    zoom : int
        Display pixels per PNG pixel on a side; above 1 the pixels are drawn as
        squares (no smoothing).
    vmax : float
        Top of the colour scale (score units); the colorbar starts at 0.
    threshold : float or None
        Drawn as a cyan line across the colorbar.
    stops : ndarray, uint8, shape (n, 3)
        The colormap sampled evenly from 0 to ``vmax``; the last colour is also
        the triangle above the bar (scores above ``vmax``).

    Returns
    -------
    svg : str
        An ``<svg>`` element without XML declaration.
    width, height : int
        Its size, px.
    """
    w, h = size[0] * zoom, size[1] * zoom
    left, top, bottom, bar_w = 76, 33, 50, 19
    bar_h = max(h + 2, 403)  # room for the colorbar's label beside a short image
    bar_x = left + w + 24
    width = max(bar_x + bar_w + 97, 640)
    height = top + max(h + 2 + bottom, bar_h + 14)
    title = "Change score" + (f" (block maximum of {factor} x {factor} px)" if factor > 1 else "")
    style = ' style="image-rendering:pixelated"' if zoom > 1 else ""
    body = [_text(left + w / 2, top - 10, title, anchor="middle", size=16),
            f'<image href="{esc(href)}" x="{left + 1}" y="{top + 1}" width="{w}" height="{h}" '
            f'preserveAspectRatio="none"{style}/>',
            f'<rect x="{left + 0.5}" y="{top + 0.5}" width="{w + 1}" height="{h + 1}" fill="none" stroke="#000" '
            f'stroke-width="1"/>']
    body += _image_axes(left + 1, top + 1, w, h, factor / zoom, size[0] * factor, size[1] * factor)
    label = "change score (intensity units)" + ("; cyan line: threshold" if threshold is not None else "")
    body += _colorbar(bar_x, top, bar_w, bar_h, 0.0, vmax, stops, label=label, gid="score-colormap", mark=threshold,
                      mark_color="cyan", extend=True)
    return _document(width, height, body, standalone=False), width, height


def _image_axes(x0, y0, w, h, scale, cols, rows):
    """Ticks at full-resolution rows and columns (a pixel's centre) along the
    left and bottom of the image box, ``scale`` full-resolution px per display px."""
    xticks, xstep = nice_ticks(0, cols - 1, max(2, round(w / 170)))
    yticks, ystep = nice_ticks(0, rows - 1, max(2, round(h / 170)))
    xs = [x0 + (t + 0.5) / scale for t in xticks]
    ys = [y0 + (t + 0.5) / scale for t in yticks]
    ticks = "".join(f"M{_n(x)} {y0 + h + 1}v{_TICK}" for x in xs) + "".join(f"M{x0 - 1} {_n(y)}h-{_TICK}" for y in ys)
    out = [f'<path d="{ticks}" stroke="#000" stroke-width="{_THIN}"/>']
    out += [_text(x, y0 + h + 19, s, size=_TICK_SIZE, anchor="middle") for x, s in zip(xs, tick_labels(xticks, xstep))]
    out += [_text(x0 - 7, y, s, size=_TICK_SIZE, anchor="end", middle=True)
            for y, s in zip(ys, tick_labels(yticks, ystep))]
    out.append(_text(x0 + w / 2, y0 + h + 40, "column (px)", anchor="middle"))
    out.append(_text(x0 - 58, y0 + h / 2, "row (px)", anchor="middle", rotate=True))
    return out


def _colorbar(x, top, w, h, lo, hi, stops, *, label, gid, mark=None, mark_color="#000", extend=False):
    """A vertical colorbar from ``lo`` (bottom) to ``hi``, ticks and their
    values on the right, then ``label``; ``mark`` a value drawn as a line
    across the bar; ``extend`` a triangle above it in the top colour (values
    beyond ``hi``).  ``gid`` names the gradient, unique in its document."""
    tri = round(0.05 * h) if extend else 0
    y0, y1 = top + tri, top + h  # the bar proper, hi at y0 and lo at y1
    last = len(stops) - 1
    gradient = "".join(f'<stop offset="{i / last:.4g}" stop-color="{_hex(c)}"/>' for i, c in enumerate(stops.tolist()))
    ticks, step = nice_ticks(lo, hi, max(3, round((y1 - y0) / 60)))
    ys = [y1 - (t - lo) / (hi - lo) * (y1 - y0) for t in ticks]
    outline = f"M{x} {y0}L{_n(x + w / 2)} {top}L{x + w} {y0}V{y1}H{x}Z" if extend else f"M{x} {y0}H{x + w}V{y1}H{x}Z"
    out = [f'<defs><linearGradient id="{gid}" x1="0" y1="1" x2="0" y2="0">{gradient}</linearGradient></defs>',
           f'<rect x="{x}" y="{y0}" width="{w}" height="{y1 - y0}" fill="url(#{gid})"/>']
    if extend:
        out.append(f'<path d="M{x} {y0}L{_n(x + w / 2)} {top}L{x + w} {y0}Z" fill="{_hex(stops[-1].tolist())}"/>')
    if mark is not None:
        ym = y1 - min(max((mark - lo) / (hi - lo), 0.0), 1.0) * (y1 - y0)
        out.append(f'<path d="M{x} {_n(ym)}h{w}" stroke="{mark_color}" stroke-width="2"/>')
    out.append(f'<path d="{outline}" fill="none" stroke="#000" stroke-width="{_THIN}"/>')
    out.append(f'<path d="{"".join(f"M{x + w} {_n(y)}h{_TICK}" for y in ys)}" stroke="#000" stroke-width="{_THIN}"/>')
    names = tick_labels(ticks, step)
    out += [_text(x + w + 7, y, s, size=_TICK_SIZE, middle=True) for y, s in zip(ys, names)]
    widest = max((text_width(s, _TICK_SIZE) for s in names), default=0.0)
    out.append(_text(x + w + 7 + widest + 16, (top + y1) / 2, label, anchor="middle", middle=True, rotate=True))
    return out


def _hex(rgb):
    return "#{:02x}{:02x}{:02x}".format(*rgb[:3])


# --------------------------------------------------------------------------- per-tile maps


def tile_map_svg(values, colors, stops, *, lo, hi, title, label, fmt, marked=(), marked_label=None, line=None):
    """A map of one value per tile with the values written in the cells (up to
    400 cells) and a colorbar.

    Parameters
    ----------
    values : ndarray, shape (tiles_y, tiles_x)
        NaN where unknown (grey, "n/a").
    colors : ndarray, uint8, shape (tiles_y, tiles_x, 3)
        Each cell's colour.
    stops : ndarray, uint8, shape (n, 3)
        The colormap sampled evenly from ``lo`` to ``hi``, for the colorbar.
    lo, hi : float
        Range of the colorbar, ``lo < hi``.
    title, label : str
        Figure title and colorbar label.
    fmt : str
        Format of a value in its cell, ``".4f"``.
    marked : sequence of (int, int)
        ``(tile_y, tile_x)`` of tiles outlined dashed red, explained by
        ``marked_label`` in a legend under the map.
    line : (float, str), optional
        A value drawn as a black line across the colorbar and its name,
        appended to the label.

    Returns
    -------
    svg : str
    width, height : int
    """
    ny, nx = values.shape
    width = round(100 * min(11.0, max(6.4, 0.95 * nx + 2.6)))
    height = round(100 * min(10.0, max(3.6, 0.8 * ny + 1.8)))
    legend = bool(len(marked) and marked_label)
    left, top, bar_w, bar_room = 69, 33, 13, 104
    aw, ah = width - left - bar_room - bar_w - 17, height - top - 47 - (22 if legend else 0)
    cw, ch = aw / nx, ah / ny
    body = [_text(left + aw / 2, top - 10, title, size=16, anchor="middle"),
            f'<g transform="translate({left} {top})">', '<g shape-rendering="crispEdges">']
    xe, ye = [round(t * cw) for t in range(nx + 1)], [round(t * ch) for t in range(ny + 1)]  # whole px: no seams
    body += [f'<rect x="{xe[tx]}" y="{ye[ty]}" width="{xe[tx + 1] - xe[tx]}" height="{ye[ty + 1] - ye[ty]}" '
             f'fill="{_hex(colors[ty, tx].tolist()) if np.isfinite(values[ty, tx]) else "#d9d9d9"}"/>'
             for ty in range(ny) for tx in range(nx)]
    body.append("</g>")
    body += _cell_texts(values, colors, cw, ch, fmt)
    for ty, tx in marked:
        body.append(f'<rect x="{_n((tx + 0.03) * cw)}" y="{_n((ty + 0.03) * ch)}" width="{_n(0.94 * cw)}" '
                    f'height="{_n(0.94 * ch)}" fill="none" stroke="red" stroke-width="3.5" '
                    f'stroke-dasharray="12.8 5.6"/>')
    body.append(f'<rect width="{_n(aw)}" height="{_n(ah)}" fill="none" stroke="#000" stroke-width="{_THIN}"/>')
    body += _cell_axes(nx, ny, cw, ch, ah)
    body.append("</g>")
    body += _colorbar(width - bar_room - bar_w, top, bar_w, ah, lo, hi, stops, gid="colormap",
                      label=label if line is None else f"{label}; line: {line[1]}",
                      mark=None if line is None else line[0])
    if legend:
        x = width / 2 - (30 + text_width(marked_label, _TICK_SIZE)) / 2
        body.append(f'<rect x="{_n(x)}" y="{height - 23}" width="20" height="12" fill="none" stroke="red" '
                    f'stroke-width="2" stroke-dasharray="5 2.2"/>')
        body.append(_text(x + 28, height - 17, marked_label, size=_TICK_SIZE, middle=True))
    return _document(width, height, body), width, height


def _cell_texts(values, colors, cw, ch, fmt):
    """The values written in the cells, black or white by the cell's
    luminance; none beyond 400 cells."""
    ny, nx = values.shape
    if ny * nx > 400:
        return []
    size = 14 if ny * nx <= 36 else (11 if ny * nx <= 144 else 8)
    out = []
    for ty in range(ny):
        for tx in range(nx):
            x, y, v = (tx + 0.5) * cw, (ty + 0.5) * ch, float(values[ty, tx])
            if not math.isfinite(v):
                out.append(_text(x, y, "n/a", size=size, anchor="middle", middle=True, fill="#4d4d4d"))
                continue
            r, g, b = colors[ty, tx].tolist()
            fill = "#000" if 0.299 * r + 0.587 * g + 0.114 * b > 127.5 else "#fff"
            out.append(_text(x, y, format(v, fmt), size=size, anchor="middle", middle=True, fill=fill))
    return out


def _cell_axes(nx, ny, cw, ch, ah):
    """Tile indices at the cells' centres (at most 16 a side) and the axis labels."""
    xs = range(0, nx, max(1, math.ceil(nx / 16)))
    ys = range(0, ny, max(1, math.ceil(ny / 16)))
    ticks = ("".join(f"M{_n((t + 0.5) * cw)} {_n(ah)}v{_TICK}" for t in xs)
             + "".join(f"M0 {_n((t + 0.5) * ch)}h-{_TICK}" for t in ys))
    out = [f'<path d="{ticks}" stroke="#000" stroke-width="{_THIN}"/>']
    out += [_text((t + 0.5) * cw, ah + 19, t, size=_TICK_SIZE, anchor="middle") for t in xs]
    out += [_text(-8, (t + 0.5) * ch, t, size=_TICK_SIZE, anchor="end", middle=True) for t in ys]
    out.append(_text(nx * cw / 2, ah + 40, "tile column (tile_x)", anchor="middle"))
    out.append(_text(-42, ny * ch / 2, "tile row (tile_y)", anchor="middle", rotate=True))
    return out
