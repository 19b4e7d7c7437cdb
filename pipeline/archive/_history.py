"""The change history of a survey across nights: ``OUT_DIR/changes.gpkg``.

DESIGN.md, "Survey archives".  One feature per change on the ground, in the
reference mosaic's CRS, with ``change_id`` (stable across nights),
``first_seen``, ``last_seen`` (the UTC start of the nights, ISO 8601),
``nights_seen``, ``captures`` (a JSON list of the captures that ever saw it),
``gone_since`` and ``status``.

Sources: each capture done is one observation, read from its ground-frame mask
``change_mask_reference.tif`` (no-data 255): its *coverage* is where the mask
has evidence, its changes are the mask's 8-connected components, both
reprojected to the reference CRS.  A night's observations are those of the
captures whose done attempt carries the night's name in the ledger; a capture
skipped is no observation.  The history remembers which attempts it has taken
in (layer ``footprints``: one feature per attempt, its coverage), so a night
whose history was not written (killed after its captures) is taken in by the
next one, in night order, and an attempt is never counted twice.

Matching rule (ground overlap, shapely): two polygons are the same change when
their intersection covers at least :data:`MIN_OVERLAP` of the smaller one's
area.  Tonight's changes of overlapping captures are first joined by that rule
(one change seen by two captures is one feature); each joined change then
continues the not-``gone`` feature it overlaps most by the rule, or starts a
new one.

Status after a night (of every feature):

- ``new``: first seen tonight;
- ``persisting``: seen tonight and on an earlier night;
- ``gone``: not seen tonight although tonight's coverage holds at least
  :data:`COVERED` of its area and no change of tonight touches it (final: a
  change seen again there later is a new feature);
- ``unobserved``: not seen tonight and not covered so (its status before is
  kept when it was ``gone``).

The geometry of a feature is its latest observation.  Each night with
observations also writes its own layer ``night_<night>``: the features seen
that night (``new``, ``persisting``) and those found ``gone``.  A night
without observations (nothing new, all skipped) leaves the file as it was.
The file is written aside and renamed into place.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

__all__ = ["HISTORY_NAME", "Change", "Footprint", "History", "NightCounts", "read_history", "update_history",
           "observe_capture", "read_observation"]

HISTORY_NAME = "changes.gpkg"
CHANGES_LAYER = "changes"
FOOTPRINTS_LAYER = "footprints"
#: Fraction of the smaller polygon's area two polygons must share to be one change.
MIN_OVERLAP = 0.25
#: Fraction of a feature's area tonight's coverage must hold for "not seen" to mean "gone".
COVERED = 0.9
STATUSES = ("new", "persisting", "gone", "unobserved")
MASK_NAME = "change_mask_reference.tif"
MASK_NODATA = 255
_FIELDS = ("change_id", "status", "first_seen", "last_seen", "nights_seen", "captures", "gone_since")


@dataclass
class Change:
    """One feature of the history (geometry: shapely, reference CRS)."""

    change_id: int
    geometry: object
    status: str
    first_seen: str
    last_seen: str
    nights_seen: int = 1
    captures: list = field(default_factory=list)
    gone_since: str | None = None


@dataclass(frozen=True)
class Footprint:
    """One observation: a capture's done attempt (ledger id), its night and its coverage."""

    run_id: int
    capture: str
    night: str
    geometry: object


@dataclass(frozen=True)
class NightCounts:
    """The counts of one night: its features ``new``, ``persisting``, ``gone`` (tonight) and of the
    whole history after it (``unobserved``, ``total``); ``captures`` observed that night."""

    night: str | None
    captures: int = 0
    new: int = 0
    persisting: int = 0
    gone: int = 0
    unobserved: int = 0
    total: int = 0


@dataclass(frozen=True)
class History:
    """The history as read or written: its file, CRS (WKT), features, footprints, the counts of the
    night just taken in (``tonight``; zeros when the night had no observation) and whether this call
    took any observation in (``updated``: the file was rewritten)."""

    path: Path
    crs: str | None
    changes: list
    footprints: list
    tonight: NightCounts
    updated: bool = False


def night_time(night):
    """A night's name (``2026-11-23T21-29-52Z``) as ISO 8601 (``2026-11-23T21:29:52Z``)."""
    day, _, clock = night.partition("T")
    return f"{day}T{clock.replace('-', ':')}" if clock else night


# ----------------------------------------------------------------------- observations


def _to_crs(geometry, source, target):
    """``geometry`` from CRS ``source`` to ``target`` (no-op when they are equal)."""
    import shapely
    from pyproj import CRS, Transformer

    if source is None or target is None or CRS.from_user_input(source) == CRS.from_user_input(target):
        return geometry
    transformer = Transformer.from_crs(CRS.from_user_input(source), CRS.from_user_input(target), always_xy=True)
    return shapely.transform(geometry, lambda xy: np.column_stack(transformer.transform(xy[:, 0], xy[:, 1])))


def observe_capture(mask_path, crs, *, read=None):
    """(coverage, changes) of a capture's ground-frame mask COG, in ``crs``.

    Parameters
    ----------
    mask_path : path-like
        ``change_mask_reference.tif``: 1 change, 0 no change, 255 no evidence.
    crs : str
        The history's CRS (WKT or ``EPSG:...``).
    read : tuple, optional
        What :func:`read_observation` gave for this file (a night reads each
        capture's mask as the capture ends, beside the other captures'
        detection); read now when None.

    Returns
    -------
    coverage : shapely geometry
        Where the mask has evidence (0 or 1).
    changes : list of shapely geometry
        One (multi)polygon per 8-connected component of 1s.
    """
    coverage, changes, source = read_observation(mask_path) if read is None else read
    return _to_crs(coverage, source, crs), [_to_crs(g, source, crs) for g in changes]


def read_observation(mask_path):
    """(coverage, changes, CRS as WKT or None) of a capture's ground-frame
    mask COG in the mask's own CRS: what :func:`observe_capture` reprojects.

    Notes
    -----
    Reads the mask whole: one byte per pixel of the capture.
    """
    import rasterio
    import shapely
    from rasterio.features import shapes
    from scipy import ndimage

    with rasterio.open(mask_path) as ds:
        mask, transform, source = ds.read(1), ds.transform, ds.crs
    valid = mask != MASK_NODATA
    cover = [shapely.geometry.shape(g) for g, _ in shapes(valid.astype(np.uint8), mask=valid, transform=transform)]
    labels, n = ndimage.label(mask == 1, structure=np.ones((3, 3), bool))
    parts = {}
    for geom, value in shapes(labels.astype(np.int32), mask=labels > 0, connectivity=4, transform=transform):
        parts.setdefault(int(value), []).append(shapely.geometry.shape(geom))
    # the polygons of one raster class never overlap (a coverage): their union is a coverage union,
    # the same geometry as a general union at a fraction of its cost
    changes = [shapely.coverage_union_all(parts[k]) for k in range(1, n + 1)]
    return shapely.coverage_union_all(cover), changes, source.to_wkt() if source is not None else None


# ----------------------------------------------------------------------- matching


def _same(a, b):
    """The matching rule: ``a`` and ``b`` share at least MIN_OVERLAP of the smaller one's area."""
    smaller = min(a.area, b.area)
    return smaller > 0 and a.intersection(b).area >= MIN_OVERLAP * smaller


def _join(observed):
    """Tonight's changes ``observed`` ([(geometry, capture)]) joined by the matching rule
    (connected components of the overlapping pairs): [(geometry, sorted captures)]."""
    import shapely
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if not observed:
        return []
    geoms = np.array([g for g, _ in observed], dtype=object)
    tree = shapely.STRtree(geoms)
    pairs = np.array([(i, j) for i, j in zip(*tree.query(geoms, predicate="intersects"))
                      if i < j and _same(geoms[i], geoms[j])], dtype=np.int64).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(geoms),) * 2)
    _, labels = connected_components(graph, directed=False)
    groups = {}
    for i, label in enumerate(labels):
        groups.setdefault(label, []).append(i)
    return [(shapely.union_all([geoms[i] for i in members]), sorted({observed[i][1] for i in members}))
            for members in sorted(groups.values())]


def _best(geometry, candidates, tree):
    """The Change of ``candidates`` (indexed by the STRtree ``tree``) that ``geometry`` overlaps most,
    among those it matches by the rule, else None."""
    near = [candidates[i] for i in tree.query(geometry, predicate="intersects")]
    matching = [c for c in near if _same(geometry, c.geometry)]
    return max(matching, key=lambda c: (geometry.intersection(c.geometry).area, -c.change_id), default=None)


def _continue(changes, joined, stamp):
    """Each change of tonight ``joined`` continues the not-gone feature of ``changes`` it matches best,
    or starts a new one (appended); returns the features seen tonight, updated."""
    import shapely

    active = [c for c in changes if c.status != "gone"]
    tree = shapely.STRtree(np.array([c.geometry for c in active], dtype=object))
    seen = {}
    next_id = max((c.change_id for c in changes), default=0) + 1
    for geometry, captures in joined:
        target = _best(geometry, active, tree)
        if target is None:
            target = Change(next_id, geometry, "new", stamp, stamp, 0, [])
            next_id += 1
            changes.append(target)
        seen.setdefault(target.change_id, (target, []))[1].append((geometry, captures))
    for target, parts in seen.values():
        target.geometry = shapely.union_all([g for g, _ in parts])
        target.captures = sorted(set(target.captures).union(*(set(c) for _, c in parts)))
        target.nights_seen += 1
        target.last_seen = stamp
        target.status = "new" if target.first_seen == stamp else "persisting"
    return [target for target, _ in seen.values()]


def _not_seen(changes, seen, coverage, tonight, stamp):
    """The not-gone features of ``changes`` not ``seen`` tonight: ``gone`` where ``coverage`` holds
    COVERED of them and no change of ``tonight`` touches them, else ``unobserved``; returns the gone."""
    gone, seen = [], {c.change_id for c in seen}
    for change in changes:
        if change.status == "gone" or change.change_id in seen:
            continue
        area = change.geometry.area
        covered = area > 0 and change.geometry.intersection(coverage).area >= COVERED * area
        if covered and not change.geometry.intersects(tonight):
            change.status, change.gone_since = "gone", stamp
            gone.append(change)
        else:
            change.status = "unobserved"
    return gone


def _take_in_night(changes, night, observations):
    """Update ``changes`` (list of Change, in place and extended) with one night's ``observations``
    ([(Footprint, [change geometry])]); returns the features of the night's layer (copies)."""
    import shapely

    stamp = night_time(night)
    joined = _join([(g, fp.capture) for fp, geoms in observations for g in geoms])
    before = [c for c in changes if c.status != "gone"]
    seen = _continue(changes, joined, stamp)
    coverage = shapely.union_all([fp.geometry for fp, _ in observations])
    tonight = shapely.union_all([g for g, _ in joined]) if joined else shapely.Polygon()
    gone = _not_seen(before, seen, coverage, tonight, stamp)
    return [replace(c) for c in sorted(seen + gone, key=lambda c: c.change_id)]


# ----------------------------------------------------------------------- the file


def _multi(geometry):
    """A MultiPolygon of ``geometry``'s polygons (GeoPackage layers here are MultiPolygon)."""
    import shapely

    polygons = [g for g in shapely.get_parts(geometry) if g.geom_type == "Polygon" and not g.is_empty]
    return shapely.MultiPolygon(polygons)


def _write_changes(path, layer, changes, crs):
    from pyogrio.raw import write

    import shapely

    geometry = np.array([shapely.to_wkb(_multi(c.geometry)) for c in changes], dtype=object)
    data = [np.array([c.change_id for c in changes], dtype=np.int64),
            np.array([c.status for c in changes], dtype=object),
            np.array([c.first_seen for c in changes], dtype=object),
            np.array([c.last_seen for c in changes], dtype=object),
            np.array([c.nights_seen for c in changes], dtype=np.int64),
            np.array([json.dumps(c.captures) for c in changes], dtype=object),
            np.array([c.gone_since for c in changes], dtype=object)]
    write(str(path), geometry, data, list(_FIELDS), layer=layer, driver="GPKG", geometry_type="MultiPolygon",
          crs=crs)


def _write_footprints(path, footprints, crs):
    from pyogrio.raw import write

    import shapely

    geometry = np.array([shapely.to_wkb(_multi(f.geometry)) for f in footprints], dtype=object)
    data = [np.array([f.run_id for f in footprints], dtype=np.int64),
            np.array([f.capture for f in footprints], dtype=object),
            np.array([night_time(f.night) for f in footprints], dtype=object),
            np.array([f.night for f in footprints], dtype=object)]
    write(str(path), geometry, data, ["run_id", "capture", "night_time", "night"], layer=FOOTPRINTS_LAYER,
          driver="GPKG", geometry_type="MultiPolygon", crs=crs)


def read_history(path):
    """The history at ``path`` (a :class:`History` with no night counts), or None when absent."""
    import pyogrio
    import shapely
    from pyogrio.raw import read

    path = Path(path)
    if not path.exists():
        return None
    meta, _, geometry, values = read(str(path), layer=CHANGES_LAYER)
    rows = [dict(zip(meta["fields"], v)) for v in zip(*values)] if len(geometry) else []
    changes = [Change(int(r["change_id"]), shapely.from_wkb(g), r["status"], r["first_seen"], r["last_seen"],
                      int(r["nights_seen"]), json.loads(r["captures"]), r["gone_since"] or None)
               for g, r in zip(geometry, rows)]
    footprints = []
    if FOOTPRINTS_LAYER in pyogrio.list_layers(str(path))[:, 0]:
        fmeta, _, fgeometry, fvalues = read(str(path), layer=FOOTPRINTS_LAYER)
        frows = [dict(zip(fmeta["fields"], v)) for v in zip(*fvalues)] if len(fgeometry) else []
        footprints = [Footprint(int(r["run_id"]), r["capture"], r["night"], shapely.from_wkb(g))
                      for g, r in zip(fgeometry, frows)]
    return History(path, meta["crs"], changes, footprints, NightCounts(None))


def _counts(night, changes, layer, captures):
    return NightCounts(night, captures, *(sum(c.status == s for c in layer) for s in ("new", "persisting", "gone")),
                       sum(c.status == "unobserved" for c in changes), len(changes))


def update_history(out, rows, night, crs, *, observed=None):
    """Take the observations not yet in ``OUT_DIR/changes.gpkg`` into it (module docstring: rules).

    Parameters
    ----------
    out : path-like
        The survey folder.
    rows : sequence of LedgerRow
        The latest done attempt of each capture (:func:`pipeline.archive._night_end.latest_done`);
        those whose output folder holds the ground-frame mask and that are not taken in yet are
        observations, grouped by their night (other rows are passed over).
    night : str
        Tonight's name (for the counts returned).
    crs : str
        The reference mosaic's CRS (WKT or ``EPSG:...``); an existing history keeps its own.
    observed : dict, optional
        Mask path (str) -> its :func:`read_observation`, for the masks read
        already (the others are read here).

    Returns
    -------
    History
        Its ``tonight`` counts the features of ``night`` (zeros if it had no observation).
    """
    out = Path(out)
    path = out / HISTORY_NAME
    before = read_history(path)
    changes = list(before.changes) if before else []
    footprints = list(before.footprints) if before else []
    crs = (before.crs if before and before.crs else crs)
    taken = {f.run_id for f in footprints}
    pending = {}
    for row in rows:
        folder = row.outputs.get("output")
        if row.status != "done" or row.id in taken or not folder or not row.night:
            continue
        mask = Path(folder) if Path(folder).is_absolute() else out / folder
        if (mask / MASK_NAME).is_file():
            pending.setdefault(row.night, []).append((row, mask / MASK_NAME))
    tonight, layers = NightCounts(night), {}
    for name in sorted(pending):
        observations = []
        for row, mask in sorted(pending[name], key=lambda p: p[0].id):
            coverage, geoms = observe_capture(mask, crs, read=(observed or {}).get(str(mask)))
            observations.append((Footprint(row.id, row.capture, name, coverage), geoms))
        layers[name] = _take_in_night(changes, name, observations)
        footprints.extend(fp for fp, _ in observations)
        if name == night:
            tonight = _counts(night, changes, layers[name], len(observations))
    if layers:
        _write_file(path, changes, footprints, layers, crs)
    return History(path, crs, changes, footprints, tonight, bool(layers))


def _write_file(path, changes, footprints, layers, crs):
    """All layers into a copy of the history (earlier night layers kept), renamed into place."""
    tmp = path.with_name(f".{path.stem}.partial{path.suffix}")  # GDAL wants the .gpkg suffix
    tmp.unlink(missing_ok=True)
    if path.exists():
        shutil.copyfile(path, tmp)
    try:
        from rsmb.tiles._gdal import quiet_gdal

        with quiet_gdal():
            _write_changes(tmp, CHANGES_LAYER, changes, crs)
            _write_footprints(tmp, footprints, crs)
            for name, layer in layers.items():
                _write_changes(tmp, f"night_{name}", layer, crs)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
