"""The survey's thumbnail of a capture: the change overlay on the capture's
own colours (its stored preview), or on the registered reference for a store
written before previews were kept."""

import numpy as np
import zarr
from PIL import Image

from rsmb.pipeline.archive._survey_html import write_thumbnail


def _store(path, *, preview):
    """A store with what the thumbnail reads: a 600 x 400 mask with one
    changed square, the registered image, and (optionally) a capture preview
    of factor 2 that is pure green, unknown on its first 10 preview rows."""
    group = zarr.open_group(str(path), mode="w")
    mask = np.zeros((600, 400), np.uint8)
    mask[200:300, 100:200] = 1
    group.create_array("change_mask", data=mask)
    group.create_array("registered", data=np.tile(np.linspace(0, 1, 400, dtype=np.float32), (600, 1)))
    if preview:
        rgba = np.zeros((300, 200, 4), np.uint8)
        rgba[..., 1], rgba[10:, :, 3] = 200, 255
        group.create_array("preview_capture", data=rgba).attrs["factor"] = 2
    return group


def test_thumbnail_shows_the_capture_in_colour_with_its_changes(tmp_path):
    write_thumbnail(_store(tmp_path / "s.zarr", preview=True), tmp_path / "t.png")
    rgb = np.asarray(Image.open(tmp_path / "t.png").convert("RGB")).astype(int)
    assert rgb.shape == (150, 100, 3)  # the 300 x 200 preview halved: the longer side at most 256
    assert tuple(rgb[100, 10]) == (0, 200, 0)  # the capture's own colour, outside the change
    assert rgb[60, 35, 0] > rgb[60, 35, 2] + 60  # the change (rows 50-74, columns 25-49 here): red
    assert rgb[1, 50, 2] > rgb[1, 50, 0]  # no capture data: dark blue


def test_thumbnail_without_preview_draws_the_registered_reference(tmp_path):
    write_thumbnail(_store(tmp_path / "s.zarr", preview=False), tmp_path / "t.png")
    rgb = np.asarray(Image.open(tmp_path / "t.png").convert("RGB")).astype(int)
    assert rgb.shape == (200, 134, 3)  # 600 x 400 reduced by 3
    outside = rgb[20, :]
    assert (outside[:, 0] == outside[:, 1]).all() and (outside[:, 1] == outside[:, 2]).all()  # gray
    assert rgb[80, 50, 0] > rgb[80, 50, 2] + 60  # the change in red
