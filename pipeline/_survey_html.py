"""The pages of a survey: ``thumbnail.png`` per capture and ``OUT_DIR/index.html``.

The index lists every capture the ledger has ever seen (its latest attempt):
status, reason, changes and their area, its thumbnail and a link to its
report.  Links are relative and there is no script, so the page opens from
disk without a server.
"""

import html
import os
from pathlib import Path

from ._report_figures import block_reduce, overlay_rgb

__all__ = ["write_index", "write_thumbnail"]

THUMBNAIL = 256  # px, the longer side


def write_thumbnail(group, path, *, side=THUMBNAIL):
    """The change overlay (:func:`overlay_rgb`) of a detect store, reduced so
    that its longer side is at most ``side`` pixels."""
    from PIL import Image

    h, w = group["change_mask"].shape
    factor = max(1, -(-max(h, w) // side))
    rgb = overlay_rgb(block_reduce(group["registered"], factor, "mean"),
                      block_reduce(group["change_mask"], factor, "max"))
    Image.fromarray(rgb, mode="RGB").save(path, compress_level=3)
    return Path(path)


_STYLE = """body{font-family:sans-serif;margin:1.5em;color:#222}
table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:4px 8px;vertical-align:middle}
th{background:#eee}td.num{text-align:right}.done{color:#161}.failed{color:#b00;font-weight:bold}
.running{color:#a60}img{display:block;max-width:256px;max-height:256px}"""


def _cell(value, numeric=False):
    text = "" if value is None else (f"{value:,.1f}" if isinstance(value, float) else str(value))
    return f"<td class='num'>{html.escape(text)}</td>" if numeric else f"<td>{html.escape(text)}</td>"


def _row(out, row):
    outputs = row.outputs
    folder = outputs.get("output")
    link = lambda target: os.path.relpath(target, out).replace(os.sep, "/")  # noqa: E731
    thumb = report = ""
    if folder and Path(folder, "thumbnail.png").is_file():
        thumb = f"<img src='{html.escape(link(Path(folder, 'thumbnail.png')))}' alt='thumbnail'>"
    if folder and Path(folder, "report", "index.html").is_file():
        report = f"<a href='{html.escape(link(Path(folder, 'report', 'index.html')))}'>report</a>"
    return (f"<tr><td><code>{html.escape(row.capture)}</code></td>"
            f"<td class='{html.escape(row.status)}'>{html.escape(row.status)}</td>{_cell(row.reason)}"
            f"{_cell(outputs.get('changes'), True)}{_cell(outputs.get('changed_m2'), True)}"
            f"<td>{thumb}</td><td>{report}</td>{_cell(row.finished or row.started)}</tr>")


def write_index(out, rows):
    """``out/index.html``: one row per capture of ``rows`` (the ledger's
    latest attempts), written aside and renamed.  Returns its path."""
    out = Path(out)
    counts = {s: sum(r.status == s for r in rows) for s in ("done", "failed", "running")}
    body = "\n".join(_row(out, r) for r in rows)
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>rsmb survey: {html.escape(out.name)}"
            f"</title><style>{_STYLE}</style></head><body><h1>rsmb survey: {html.escape(str(out))}</h1>"
            f"<p>{len(rows)} captures: {counts['done']} done, {counts['failed']} failed"
            f"{', %d interrupted' % counts['running'] if counts['running'] else ''}.</p>"
            f"<table><tr><th>capture</th><th>status</th><th>reason</th><th>changes</th><th>changed m&sup2;</th>"
            f"<th>thumbnail</th><th>report</th><th>when (UTC)</th></tr>\n{body}\n</table></body></html>\n")
    path = out / "index.html"
    tmp = out / ".index.html.partial"
    tmp.write_text(page, encoding="utf-8")
    os.replace(tmp, path)
    return path
