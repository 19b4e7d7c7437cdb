"""What a night leaves across nights, written once at its end: the change
history (``changes.gpkg``, :mod:`pipeline.archive._history`), the STAC catalog
(``stac/``, :mod:`pipeline.archive._stac`) and the map of the index page
(``map.png``, :mod:`pipeline.archive._survey_map`).  Each takes in every done
attempt of the ledger it does not hold yet, so a night that stopped before
this step is caught up by the next one."""

from dataclasses import dataclass
from pathlib import Path

from rsmb import tiles

from ._history import History, update_history
from ._stac import update_catalog
from ._survey_map import MAP_NAME, write_map

__all__ = ["NightRecord", "close_night"]


@dataclass(frozen=True)
class NightRecord:
    """The night's history (:class:`History`, with tonight's counts), catalog and map (None: nothing to draw)."""

    night: str
    history: History
    catalog: Path
    map: Path | None


def latest_done(ledger):
    """The latest done attempt of every capture of ``ledger``, by capture."""
    done = {}
    for row in ledger.runs():
        if row.status == "done":
            done[row.capture] = row
    return [done[capture] for capture in sorted(done)]


def close_night(out, ledger, night, references, *, observed=None):
    """Update ``out``'s history, catalog and map after the night ``night`` (its captures recorded in
    ``ledger``); the history is in the CRS of the first reference file.  ``observed``: the masks the
    night read already (:func:`update_history`).  Returns a NightRecord."""
    out = Path(out)
    rows = latest_done(ledger)
    crs = tiles.probe_header(references[0])[1].crs
    history = update_history(out, rows, night, crs, observed=observed)
    catalog = update_catalog(out, rows, history=history.path if history.path.is_file() else None)
    drawn = out / MAP_NAME
    if history.updated or not drawn.is_file():  # the map is a function of the history
        drawn = write_map(drawn, history)
    return NightRecord(night, history, catalog, drawn if drawn and drawn.is_file() else None)
