"""The HTML page of ``rsmb report``: inputs, summary, figures with captions,
timings, parameters and georeferencing of one detect store.

Self-contained apart from the figure files next to it: no JavaScript, no
network; every value from the store is escaped.  Figures are ``<img>`` elements
with their size.
"""

import datetime
import html
import json

import numpy as np

from ._report_figures import FIGURES

_STATES = {1: "solved", 2: "homogeneous", 3: "failed"}


def _esc(value):
    return html.escape(str(value), quote=True)

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 2em auto;
       max-width: 1100px; padding: 0 1em; color: #222; line-height: 1.4; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; } h2 { margin-top: 1.6em; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; margin: 0.5em 0 1em; font-size: 0.92em; }
th, td { border: 1px solid #ddd; padding: 0.25em 0.6em; text-align: left; vertical-align: top; }
th { background: #f4f4f4; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
code, .mono { font-family: ui-monospace, Menlo, Consolas, monospace; font-size: 0.9em; word-break: break-all; }
figure { margin: 1.2em 0 2em; } figcaption { font-size: 0.92em; color: #444; max-width: 900px; margin-top: 0.4em; }
img { max-width: 100%; height: auto; border: 1px solid #ccc; }
img.pixels { image-rendering: pixelated; }
.meta { color: #666; font-size: 0.9em; }
pre { white-space: pre-wrap; font-size: 0.8em; background: #f8f8f8; padding: 0.5em; }
"""

_SUMMARY_LABELS = {
    "shape": "image size (H, W), px",
    "tiles": "tiles (y, x)",
    "tile_size": "core tile side, px",
    "halo": "tile halo, px",
    "threshold": "change threshold (score units)",
    "changed_pixels": "changed pixels",
    "changed_fraction": "changed fraction",
    "components": "change components",
    "gain_min": "gain, smallest tile",
    "gain_max": "gain, largest tile",
    "resolved_tiles": "re-solved tiles (y, x)",
    "tile_agreement_px_max": "largest tile disagreement, px",
    "tasks_per_tile": "tasks per tile",
    "megapixels_per_s": "throughput, megapixels/s",
    "failed_rows": "failed tile rows (no fit, or unconverged)",
    "clipped_reference": "clipped fraction of the reference (bounds)",
    "clipped_capture": "clipped fraction of the capture (bounds)",
    "no_evidence": "fraction of pixels without evidence (NaN score)",
}


def _fmt(value):
    """Short text of an attribute value."""
    if value is None:
        return "&ndash;"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return _esc(f"{value:.6g}") if value == value else "NaN"
    if isinstance(value, list) and value and all(isinstance(v, list) for v in value):
        return _esc(", ".join("(" + ", ".join(str(x) for x in v) + ")" for v in value))
    if isinstance(value, list):
        return _esc(", ".join(str(v) for v in value)) if value else "none"
    if isinstance(value, dict):
        return f"<code>{_esc(json.dumps(value, default=str))}</code>"
    return _esc(value)


def _table(rows, header=None, numeric=()):
    """HTML table from rows of already escaped cell text."""
    head = "<tr>" + "".join(f"<th>{_esc(h)}</th>" for h in header) + "</tr>" if header else ""
    body = []
    for row in rows:
        cells = [f'<td class="num">{c}</td>' if i in numeric else f"<td>{c}</td>" for i, c in enumerate(row)]
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table>{head}{''.join(body)}</table>"


def _flatten(mapping, prefix=""):
    for key, value in mapping.items():
        if isinstance(value, dict) and value:
            yield from _flatten(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def _inputs_table(attrs):
    inputs = attrs.get("inputs") or {}
    rows = [[_esc(role), f"<code>{_esc(info.get('path', ''))}</code>", f"<code>{_esc(info.get('sha256', ''))}</code>"]
            for role, info in inputs.items()]
    return _table(rows, ["input", "path", "sha256"]) if rows else "<p>No input record in the store.</p>"


def _summary_table(summary):
    keys = [k for k in _SUMMARY_LABELS if k in summary]
    keys += [k for k in summary if k not in _SUMMARY_LABELS and k not in ("timings", "output")]
    rows = [[_esc(_SUMMARY_LABELS.get(k, k)), _fmt(summary[k])] for k in keys]
    return _table(rows, ["quantity", "value"], numeric=(1,))


def _timings_table(timings):
    rows = []
    for key, value in timings.items():
        if isinstance(value, dict):  # cpu_s: CPU-seconds per stage, summed over tasks
            rows += [[_esc(f"CPU, {k.replace('_', ' ')} (s, summed over tasks)"), f"{v:.3f}"] for k, v in value.items()]
            continue
        label = key[:-2] + " (s)" if key.endswith("_s") else (key[:-6] + " (s, summed over tasks)"
                                                              if key.endswith("_s_sum") else key)
        text = f"{value:.3f}" if isinstance(value, float) else _fmt(value)
        rows.append([_esc(label.replace("_", " ")), text])
    return _table(rows, ["stage", "value"], numeric=(1,)) if rows else "<p>No timings recorded.</p>"


def _row_state_table(group):
    if "tile_row_state" not in group:
        return ""
    states = np.asarray(group["tile_row_state"][:])
    rows = []
    for tx in range(states.shape[1]):
        counts = [int((states[:, tx] == s).sum()) for s in _STATES]
        rows.append([str(tx)] + [str(c) for c in counts] + [str(int(states.shape[0] - sum(counts)))])
    header = ["tile column"] + list(_STATES.values()) + ["no tile rows"]
    return "<h3>Rows per tile column by solver state</h3>" + _table(rows, header, numeric=(1, 2, 3, 4))


def _geo_rows(attrs, prefix=""):
    keys = [k for k in attrs if k.startswith(("proj:", "spatial:")) or k in ("crs", "transform", "nodata")]
    rows = []
    for key in keys:
        value = attrs[key]
        if isinstance(value, str) and len(value) > 120:
            text = f"<details><summary>{_esc(value[:60])}&hellip;</summary><pre>{_esc(value)}</pre></details>"
        else:
            text = _fmt(value)
        rows.append((key, value, [f"<code>{_esc(prefix + key)}</code>", text]))
    return rows


def _geo_section(attrs):
    rows = _geo_rows(attrs) + _geo_rows(attrs.get("reference_georeferencing") or {}, "reference ")
    if not any(key != "nodata" and value is not None for key, value, _ in rows):
        return "<h2>Georeferencing</h2><p>The capture had no georeferencing (pixel coordinates only).</p>"
    return "<h2>Georeferencing</h2>" + _table([cells for _, _, cells in rows], ["attribute", "value"])


def _captions(attrs, factor, score_factor, flat_axes=()):
    s = attrs.get("summary") or {}
    flat = (f" No panel for {', '.join(flat_axes)}: zero on every row, fused and in every tile."
            if flat_axes else "")
    tile = attrs["tile_grid"]["tile"]
    tol = (attrs.get("parameters") or {}).get("agreement")
    down = (f"Downsampled by {factor} (block mean of the image, block maximum of the mask, so that small changes "
            f"stay visible)." if factor > 1 else "Full resolution, one image pixel per PNG pixel.")
    overlay = (f"Detected changes (red fill, yellow outline, a ring around tiny ones; {s.get('changed_pixels', '?')} "
               f"px in {s.get('components', '?')} component(s)) on the registered reference, i.e. the reference "
               f"warped and blurred to match the capture (grayscale; dark blue where unknown). Faint cyan lines: "
               f"the {tile} px tile grid. {down}")
    agreement = ("How far each tile's path is from the fused one: RMS over rows of the largest displacement of the "
                 "row ends, px; grey: n/a." + (f" Tolerance {tol:g} px (black line on the colorbar)." if tol else "")
                 + f" Dashed red outlines: tiles re-solved around the other tiles' path "
                   f"({len(s.get('resolved_tiles', []))}).")
    score = ("Magnitude of the change term."
             + (f" Threshold {s['threshold']:.4g} (cyan line on the colorbar)." if "threshold" in s else "")
             + (f" Block maximum over {score_factor} x {score_factor} px, so that small changes stay visible."
                if score_factor > 1 else ""))
    before_after = (f"The reference (before) and the capture (after) as the inputs show them, in colour where they "
                    f"have it, the detected changes outlined in magenta on both (a circle around the small ones): "
                    f"on the reference where the changes are on the ground "
                    f"(change_mask_reference), on the capture where its rolling shutter recorded them "
                    f"(change_mask). Previews kept in the store at detect time, at most 1024 px a side.")
    return {
        "before_after.jpg": before_after,
        "overlay.png": overlay,
        "trajectory.png": "Per-row camera pose in global pose coordinates, one panel per axis. Black: the fused "
                          "trajectory (median over tiles of solved rows); thin coloured lines: each tile column's "
                          "own estimate; dashed verticals: tile-row boundaries." + flat,
        "gain.png": "Illumination gain of the capture against the reference, one value per tile.",
        "agreement.png": agreement,
        "change_score.png": score,
    }


def _figures_html(figures, captions, one_tile=False):
    parts = []
    for name in FIGURES:
        if name not in figures:
            why = ("one tile: its gain is in the summary" if name in ("gain.png", "agreement.png") and one_tile
                   else "the store has no input previews (written by an earlier rsmb)" if name == "before_after.jpg"
                   else "the store has no data for it")
            parts.append(f"<p>{_esc(name)}: not available ({why}).</p>")
            continue
        w, h = figures[name]["size"]
        cls = ' class="pixels"' if name == "overlay.png" else ""
        shown = f'<img src="{_esc(name)}"{cls} width="{w}" height="{h}" alt="{_esc(name)}">'
        parts.append(f'<figure id="{_esc(name[:-4])}"><a href="{_esc(name)}">{shown}</a>'
                     f"<figcaption>{_esc(captions[name])}</figcaption></figure>")
    return "\n".join(parts)


def html_page(store, attrs, group, figures, factor, score_factor):
    summary = attrs.get("summary") or {}
    params = attrs.get("parameters") or {}
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    # where the store lives: a survey builds it aside and records its final place
    location = summary.get("output") or store.resolve()
    meta = (f"Store <code>{_esc(location)}</code> &middot; rsmb {_esc(attrs.get('rsmb_version', '?'))} "
            f"&middot; scheduler {_esc(attrs.get('scheduler', '?'))} &middot; report written {now}")
    param_rows = [[f"<code>{_esc(k)}</code>", _fmt(v)] for k, v in _flatten(params)]
    sections = [
        f"<h1>rsmb report: {_esc(store.name)}</h1>", f'<p class="meta">{meta}</p>',
        "<h2>Inputs</h2>", _inputs_table(attrs),
        "<h2>Summary</h2>", _summary_table(summary), _row_state_table(group),
        "<h2>Figures</h2>", _figures_html(figures, _captions(attrs, factor, score_factor,
                                                       figures.get("trajectory.png", {}).get("flat_axes", ())),
                                             list(attrs.get("tile_grid", {}).get("tiles", [])) == [1, 1]),
        "<h2>Timings</h2>", _timings_table(summary.get("timings") or {}),
        "<h2>Parameters</h2>", _table(param_rows, ["parameter", "value"]),
        _geo_section(attrs),
    ]
    body = "\n".join(sections)
    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f"<title>rsmb report: {_esc(store.name)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n{body}\n"
            f"</body>\n</html>\n")
