"""What a :func:`~rsmb.pipeline.detect` run works on, decided before anything
is written: its configuration (:class:`DetectConfig`), its summary
(:class:`DetectResult`), the default tile and halo, the pairing of the
capture with its reference, the tile grid and blocks, and the run key that a
``--resume`` must find unchanged (stage 1 of ``detect``)."""

import dataclasses
import hashlib
import json
import logging
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

from rsmb import ops
from rsmb import tiles
from rsmb.ops import ChangeParams, RegistrationParams

__all__ = ["DetectConfig", "DetectResult", "default_overlap", "default_tile", "VERSION"]

try:
    VERSION = version("rsmb")
except PackageNotFoundError:  # a source tree that is not installed
    VERSION = "0+unknown"
log = logging.getLogger("rsmb")


@dataclass(frozen=True)
class DetectConfig:
    """Everything that decides the result of :func:`detect`.

    Attributes
    ----------
    registration : RegistrationParams
    changes : ChangeParams
    tile : int or None
        Core tile side in pixels; None picks :func:`default_tile`.
    overlap : int or None
        Halo in pixels; None derives it from the search range (see
        :func:`default_overlap`).
    focal : float or None
        Focal length in pixels of the whole image (default 1.2 x larger side).
    agreement : float
        A tile whose path differs from its band's by more than this (px: the
        95th percentile over its rows of the displacement of the row ends), and
        by more than three times the band's median, is re-solved around the
        others' path; a tile left more than five times this from the fused
        path is warned about.  A positive number.
    """

    registration: RegistrationParams = field(default_factory=RegistrationParams)
    changes: ChangeParams = field(default_factory=ChangeParams)
    tile: int | None = None
    overlap: int | None = None
    focal: float | None = None
    agreement: float = 2.0

    def __post_init__(self):
        a = self.agreement
        if isinstance(a, bool) or not isinstance(a, (int, float, np.integer, np.floating)) or not 0 < a < np.inf:
            raise ops.ParameterError(f"agreement: expected a positive number of pixels, got {a!r}")


@dataclass(frozen=True)
class DetectResult:
    """Summary of one :func:`detect` run (also stored in the root attribute
    ``summary`` of the output store).

    Attributes
    ----------
    output : str
        The store written.
    shape : list of int
        (H, W) of the capture.
    tiles : list of int
        (tiles_y, tiles_x).
    tile_size, halo : int
        Core tile side and halo, px.
    threshold : float
        The change threshold (score units).
    changed_pixels : int
    changed_fraction : float
    components : int
        Changes kept (connected components).
    gain_min, gain_max : float or None
        Range of the per-tile illumination gain; None when no tile had data
        to fit one.
    resolved_tiles : list
        Tiles re-solved around their band's path.
    tile_agreement_px_max : float or None
        Largest RMS disagreement of a tile's path with the fused one, px.
    tasks_per_tile : float
        Scheduled tasks per tile.
    megapixels_per_s : float
        Throughput of the whole run.
    timings : dict
        Seconds per stage and task sums.
    pairing : str
        "georeferenced" (the reference set resampled onto the capture grid) or
        "pixel" (compared pixel for pixel).
    reference_coverage : float or None
        Fraction of the capture's footprint the reference set covers
        (georeferenced pairing); the rest is no-data, never change.
    failed_rows : int
        Tile rows whose solve failed (no fit, or stopped at the iteration
        limit before converging; ``tile_row_state`` 3): their pose is
        interpolated from the rows around them.
    clipped_reference, clipped_capture : float
        Fraction of each image's valid pixels that are clipped (at zero or at
        a saturation value; left out of the row solves; bounds of the change
        test: :mod:`ops.changes._bounds`).
    no_evidence : float
        Fraction of the capture's pixels without evidence (NaN
        ``change_score``: no-data, not covered by the reference, or clipped
        where the model interval says nothing).
    parallax_components, parallax_pixels : int
        Candidate changes found to be depth layers (parallax, not change;
        ``parallax_mask``), and their pixels.
    """

    output: str
    shape: list
    tiles: list
    tile_size: int
    halo: int
    threshold: float
    changed_pixels: int
    changed_fraction: float
    components: int
    gain_min: float | None
    gain_max: float | None
    resolved_tiles: list
    tile_agreement_px_max: float | None
    tasks_per_tile: float
    megapixels_per_s: float
    timings: dict
    pairing: str = "pixel"
    reference_coverage: float | None = None
    failed_rows: int = 0
    clipped_reference: float = 0.0
    clipped_capture: float = 0.0
    no_evidence: float = 0.0
    parallax_components: int = 0
    parallax_pixels: int = 0

    def as_dict(self):
        """The fields as a JSON-ready dict."""
        return tiles.jsonable(dataclasses.asdict(self))


def default_tile(shape):
    """1024-px tiles when the image holds at least 4 x 4 of them, else 512: large
    tiles pay the per-tile start (wide search, start block) a quarter as often,
    small ones keep the cores busy on small images (four tiles on two cores
    leave a core idle while the slowest finishes).
    Depends on the shape only, so a ``--resume`` finds the same grid."""
    return 1024 if min(shape) >= 4 * 1024 else 512


def whole_image_side(shape):
    """The side of one tile that holds an image of ``shape`` (at least the
    smallest tile, 32 px): a tile or halo asked larger is cut to it."""
    return max(max(shape), 32)


def default_overlap(params, camera, shape, *, slow_reach=None):
    """Halo (px) that holds every displacement the wide search allows anywhere in
    the image, plus the row neighbourhood: the extreme poses of the search box
    are applied to the image corners.  ``slow_reach`` (deg) replaces the slow
    axes' search range: the largest slow rotation actually found."""
    axes = params.axes + params.slow_axes
    slow = params.slow_search if slow_reach is None else float(slow_reach)
    search = np.asarray(params.search + (slow,) * len(params.slow_axes))
    corners = np.array([[0, 0, 1], [shape[1] - 1, 0, 1], [0, shape[0] - 1, 1], [shape[1] - 1, shape[0] - 1, 1.0]]).T
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * len(axes), indexing="ij")).reshape(len(axes), -1).T
    hom = ops.pose_homographies(signs * search, camera, axes=axes, inverse=True)
    pts = hom @ corners
    pts = pts[:, :2] / pts[:, 2:3]
    reach = float(np.abs(pts - corners[None, :2]).max())
    hw = max([params.half_width[d] for d, a in enumerate(axes) if a in ("tx", "ty")] + [0.0])
    return int(np.ceil(reach + 3 * hw)) + 8


def _run_key(ref_infos, dist_info, config, grid):
    """What a ``--resume`` must find unchanged: the inputs' checksums, the
    configuration, the grid, the installed version and the kernels' version
    (:data:`ops.KERNEL_VERSION`, raised whenever the kernels' results change)."""
    text = json.dumps(tiles.jsonable({"reference": [r.sha256 for r in ref_infos], "distorted": dist_info.sha256,
                                      "config": config, "grid": [grid.shape, grid.tile, grid.halo],
                                      "version": VERSION, "kernels": ops.KERNEL_VERSION}), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


BLOCK = 1024  # px: the side the ingest, label and mask tasks aim for


def _block_grid(grid):
    """Blocks of tiles for ingest, labelling and masks: about :data:`BLOCK` px on a
    side and at least two per axis when there are four tiles or more (both cores
    stay busy).  Those tasks cost a few zarr calls and read a margin or halo
    around their core: per block, not per small tile."""
    ny, nx = grid.grid_shape
    return grid.coarsened(max(1, min(BLOCK // grid.tile, ny // 2, nx // 2)))


@dataclass(frozen=True)
class _Plan:
    """What a run works on, derived before anything is written."""

    pairing: tiles.Pairing
    references: tuple  # ImageInfo of each reference file read
    distorted: tiles.ImageInfo
    output: Path
    config: DetectConfig
    camera: ops.Camera
    params: RegistrationParams
    grid: tiles.TileGrid
    blocks: tiles.TileGrid
    key: str
    reach: int  # px: the halo of the whole search, slow axes included
    halo_given: bool  # the user chose the halo (--overlap)

    @property
    def shape(self):
        return self.grid.shape

    @property
    def margin(self):
        """Pixels of reference ingested around the capture: the reach of the
        whole search when the reference is resampled onto the capture grid (it
        may extend beyond the capture), none when the two are compared pixel
        for pixel."""
        return self.reach if self.pairing.mode == "georeferenced" else 0

    def for_rows(self, slow):
        """This plan with the tiles' halo the rows need once the slow part is
        known (``slow``: rx, ry per row in degrees, NaN without one): the
        search's reach with the slow axes' range replaced by the largest slow
        rotation found (none: the in-plane reach alone).  A halo chosen by the
        user stays."""
        if self.halo_given or not self.params.slow_axes:
            return self
        found = np.abs(np.asarray(slow, dtype=np.float64)[:, :2])
        reach = float(np.nanmax(found)) if np.isfinite(found).any() else 0.0
        halo = min(self.reach, default_overlap(self.params, self.camera, self.shape, slow_reach=reach))
        return dataclasses.replace(self, grid=tiles.TileGrid(self.shape, self.grid.tile, halo))

    @property
    def reference_blocks(self):
        """Blocks of the reference array (the capture grid grown by the margin)."""
        m = self.margin
        if m == 0:
            return self.blocks
        shape = (self.shape[0] + 2 * m, self.shape[1] + 2 * m)
        return tiles.TileGrid(shape, self.grid.tile, 0).coarsened(self.blocks.tile // self.grid.tile)


def _plan(references, distorted, output, config):
    """Pair the capture with its reference set (by footprint when both are
    georeferenced, else pixel for pixel), probe the inputs and derive the
    camera, the resolved parameters, the tile grid and the run key."""
    pairing = tiles.pair_images(references, distorted)
    dist_info = tiles.probe_image(distorted)
    read = pairing.reference_grids if pairing.mode == "georeferenced" else pairing.references
    ref_infos = tuple(tiles.probe_image(getattr(r, "path", r)) for r in read)
    shape = dist_info.shape
    camera = ops.Camera.for_shape(shape, focal=config.focal)
    params = config.registration.resolved(camera)
    config_overlap = config.overlap
    halo = config.overlap if config.overlap is not None else default_overlap(params, camera, shape)
    tile = config.tile or default_tile(shape)
    side = whole_image_side(shape)  # one tile of this side holds the image; a halo this wide reaches across it
    if tile > side:
        if config.tile:  # asked for, not the default
            log.warning("note: tile size %d px is larger than the image (%d x %d px, width x height): one tile "
                        "of %d px", tile, shape[1], shape[0], side)
        tile = side
    if halo > side:
        log.warning("note: overlap %d px reaches beyond the image (%d x %d px, width x height): using %d px", halo,
                    shape[1], shape[0], side)
        halo = side
    grid = tiles.TileGrid(shape, tile, halo)
    # what runs, 'auto' resolved: the same run keys the same whichever way it was asked for
    config = dataclasses.replace(config, registration=params, tile=grid.tile, overlap=grid.halo)
    return _Plan(pairing, ref_infos, dist_info, Path(output), config, camera, params, grid, _block_grid(grid),
                 _run_key(ref_infos, dist_info, config, grid), grid.halo, config_overlap is not None)
