"""The pages of a survey: ``thumbnail.png`` per capture and ``OUT_DIR/index.html``.

The index starts with the night across nights (tonight's new, persisting and
gone changes of the history, links to ``changes.gpkg`` and the STAC catalog,
the map of the surveyed area), then lists every capture the ledger has ever
seen (its latest attempt):
capture, status, reason, changes and their area, its thumbnail and a link to
its report.  Links are relative and there is no script, so the page opens from
disk without a server.  Layout rules: the table is as wide as the window and no
wider (fixed columns; long paths and reasons wrap anywhere), a capture under
the night's glob prefix is shown relative to it (the name the survey's log and
folders use; its full path in the cell's tooltip), and a reason does not
repeat the capture's path it starts with.
"""

import html
import os
from pathlib import Path

from ..report._previews import read_preview, reduce_preview
from ..report._report_figures import _Changed, block_reduce, overlay_rgb

__all__ = ["write_index", "write_thumbnail"]

THUMBNAIL = 256  # px, the longer side


def write_thumbnail(group, path, *, side=THUMBNAIL):
    """The change overlay (:func:`overlay_rgb`) of a detect store, reduced so
    that its longer side is at most ``side`` pixels: on the capture in its own
    colours (the store's ``preview_capture``), or on the registered reference
    for a store without previews."""
    from PIL import Image

    preview, step = read_preview(group, "preview_capture")
    if preview is None:
        h, w = group["change_mask"].shape
        factor = max(1, -(-max(h, w) // side))
        image = block_reduce(group["registered"], factor, "mean")
    else:
        k = max(1, -(-max(preview.shape[:2]) // side))
        factor, image = step * k, reduce_preview(preview, k)
    rgb = overlay_rgb(image, block_reduce(_Changed(group["change_mask"]), factor, "max"))
    Image.fromarray(rgb, mode="RGB").save(path, compress_level=3)
    return Path(path)


_STYLE = """body{font-family:sans-serif;margin:1.5em;color:#222;overflow-wrap:anywhere}
table{border-collapse:collapse;width:100%;table-layout:fixed}
td,th{border:1px solid #ccc;padding:4px 8px;vertical-align:middle}th{background:#eee}
td.num{text-align:right}.done{color:#161}.failed{color:#b00;font-weight:bold}.running{color:#a60}
code{font-size:90%}img{display:block;max-width:100%;max-height:160px}
img.map{max-height:none;width:auto;border:1px solid #ccc}.new{color:#d62728}.persisting{color:#c76200}
.gone{color:#555}"""
#: (header, width) of the index's columns; the thumbnail column fits a 160-px thumbnail and its padding
_COLUMNS = (("capture", "16%"), ("status", "6em"), ("reason", "auto"), ("changes", "6em"), ("changed m&sup2;", "7em"),
            ("thumbnail", "178px"), ("report", "5em"), ("when (UTC)", "8em"))


def _cell(value, numeric=False):
    text = "" if value is None else (f"{value:,.1f}" if isinstance(value, float) else str(value))
    return f"<td class='num'>{html.escape(text)}</td>" if numeric else f"<td>{html.escape(text)}</td>"


def _shown(capture, prefix):
    """A capture's path as the index shows it: relative to the night's glob
    prefix when it lies under it, else whole."""
    if prefix is not None and Path(prefix) in Path(capture).parents:
        return Path(capture).relative_to(prefix).as_posix()
    return capture


def _reason(row):
    """The reason without the capture's path it starts with (errors name their file)."""
    return row.reason.removeprefix(f"{row.capture}: ")


def _when(stamp):
    """``2026-11-23T21:29:52.722Z`` -> ``2026-11-23 21:29:52``."""
    return stamp.replace("T", " ")[:19] if stamp else None


def _row(out, row, prefix):
    outputs = row.outputs
    folder = outputs.get("output")
    link = lambda target: html.escape(os.path.relpath(target, out).replace(os.sep, "/"))  # noqa: E731
    thumb = report = ""
    if folder and Path(folder, "report", "index.html").is_file():
        report = f"<a href='{link(Path(folder, 'report', 'index.html'))}'>report</a>"
    if folder and Path(folder, "thumbnail.png").is_file():
        image = f"<img src='{link(Path(folder, 'thumbnail.png'))}' alt='thumbnail'>"
        thumb = f"<a href='{link(Path(folder, 'thumbnail.png'))}'>{image}</a>"
    return (f"<tr><td title='{html.escape(row.capture)}'><code>{html.escape(_shown(row.capture, prefix))}</code></td>"
            f"<td class='{html.escape(row.status)}'>{html.escape(row.status)}</td>{_cell(_reason(row))}"
            f"{_cell(outputs.get('changes'), True)}{_cell(outputs.get('changed_m2'), True)}"
            f"<td>{thumb}</td><td>{report}</td>{_cell(_when(row.finished or row.started))}</tr>")


def _across_nights(out, record):
    """The section on the history: tonight's counts, links to the history and
    the catalog, the map (:class:`NightRecord` ``record``; empty without one)."""
    if record is None:
        return ""
    link = lambda target: html.escape(os.path.relpath(target, out).replace(os.sep, "/"))  # noqa: E731
    t = record.history.tonight
    counts = (f"<p class='night'>Tonight ({html.escape(record.night)}, {t.captures} capture(s) observed): "
              f"<b class='new'>{t.new} new</b>, <b class='persisting'>{t.persisting} persisting</b>, "
              f"<b class='gone'>{t.gone} gone</b>. The history holds {len(record.history.changes)} change(s), "
              f"{sum(c.status == 'unobserved' for c in record.history.changes)} unobserved since last seen.")
    files = [f"<a href='{link(record.history.path)}'>changes.gpkg</a> (history)"] \
        if record.history.path.is_file() else []
    files.append(f"<a href='{link(record.catalog)}'>STAC catalog</a>")
    image = (f"<a href='{link(record.map)}'><img class='map' src='{link(record.map)}' alt='map of the surveyed "
             f"area: capture footprints and changes by status'></a>") if record.map else ""
    return f"<h2>Across nights</h2>{counts} {', '.join(files)}.</p>{image}<h2>Captures</h2>"


def write_index(out, rows, *, prefix=None, record=None):
    """``out/index.html``: one row per capture of ``rows`` (the ledger's
    latest attempts), written aside and renamed.  Captures under ``prefix``
    (the night's glob prefix, a directory) are shown relative to it.  With a
    ``record`` (:class:`NightRecord`), the page starts with tonight's new,
    persisting and gone counts, links to the history and the STAC catalog, and
    the map.  Returns its path."""
    out = Path(out)
    counts = {s: sum(r.status == s for r in rows) for s in ("done", "failed", "running")}
    body = "\n".join(_row(out, r, prefix) for r in rows)
    columns = "".join(f"<col style='width:{width}'>" for _, width in _COLUMNS)
    headers = "".join(f"<th>{name}</th>" for name, _ in _COLUMNS)
    under = f" Captures under <code>{html.escape(str(prefix))}/</code> are named relative to it." if prefix else ""
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>rsmb survey: {html.escape(out.name)}"
            f"</title><style>{_STYLE}</style></head><body><h1>rsmb survey: {html.escape(str(out))}</h1>"
            f"<p>{len(rows)} captures: {counts['done']} done, {counts['failed']} failed"
            f"{', %d interrupted' % counts['running'] if counts['running'] else ''}.{under}</p>"
            f"{_across_nights(out, record)}"
            f"<table><colgroup>{columns}</colgroup><tr>{headers}</tr>\n{body}\n</table></body></html>\n")
    path = out / "index.html"
    tmp = out / ".index.html.partial"
    tmp.write_text(page, encoding="utf-8")
    os.replace(tmp, path)
    return path
