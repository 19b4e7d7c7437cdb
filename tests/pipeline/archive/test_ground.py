"""A night's GIS products are where the changes are on the ground: captures
whose nominal georeferencing is off by a few metres, as real navigation is,
each pasted change's ground position known by construction
(:mod:`rsmb.pipeline.bench._bench_ground`)."""

from pathlib import Path

import numpy as np
import pytest

from rsmb import ops
from rsmb.pipeline.archive._survey import survey
from rsmb.pipeline.bench._bench_ground import OFFSETS_M, capture_distances, product_agreement, write_night


@pytest.fixture(scope="module")
def night(tmp_path_factory):
    root = tmp_path_factory.mktemp("ground")
    scene = (0.05 + 0.7 * ops.aerial_scene((2 * 256 + 64, 256 + 64), seed=8)).astype(np.float32)
    references, incoming = write_night(root, scene, captures=2, side=256, changes=4, seed=70)
    result = survey(references, str(incoming / "*.tif"), root / "out", report=False, settle=0)
    return incoming, result


def test_polygons_lie_on_the_true_ground_positions(night):
    """Per capture, the median distance from each true change to its polygon
    is at most 1 px, every true change has one; the polygons the capture-frame
    arrays would give on the capture's nominal transform are several pixels
    off (the navigation error and the rolling shutter's warp)."""
    _, result = night
    assert result.done == 2 and result.failed == 0
    assert max(np.hypot(*OFFSETS_M[k]) for k in range(2)) / 0.5 > 5  # nominal transforms off by > 5 px
    for capture in result.captures:
        dist = capture_distances(capture.output, Path(capture.capture).with_suffix(".truth"))
        assert np.isfinite(dist["ground"]).all(), (capture.capture, dist)
        assert np.median(dist["ground"]) <= 1.0, (capture.capture, dist)
        assert np.median(dist["capture_frame"]) > 3.0, (capture.capture, dist)


def test_products_agree_with_the_ground_frame(night):
    """The COGs are the store's ground-frame arrays, and the polygons
    rasterised on its grid are exactly change_mask_reference == 1."""
    _, result = night
    for capture in result.captures:
        agreement = product_agreement(capture.output)
        assert all(agreement.values()), (capture.capture, agreement)
