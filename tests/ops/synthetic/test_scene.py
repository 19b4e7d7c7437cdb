import numpy as np
import pytest
from scipy import ndimage as ndi

from rsmb.ops._errors import InputError, ParameterError
from rsmb.ops.synthetic._scene import aerial_scene, paste_changes

SHAPE = (384, 512)


@pytest.fixture(scope="module")
def scene():
    return aerial_scene(SHAPE, seed=5)


def test_scene_is_deterministic_and_seed_dependent(scene):
    again = aerial_scene(SHAPE, seed=5)
    assert np.array_equal(scene, again)
    assert not np.array_equal(scene, aerial_scene(SHAPE, seed=6))


def test_scene_dtype_shape_range(scene):
    assert scene.dtype == np.float32 and scene.shape == SHAPE
    assert scene.min() >= 0.0 and scene.max() <= 1.0
    # uses the dynamic range: dark trees and shadows, bright roads and roofs
    assert np.quantile(scene, 0.01) < 0.2 and np.quantile(scene, 0.99) > 0.7
    assert 0.25 < scene.mean() < 0.65


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rows_and_columns_have_gradients(seed):
    img = aerial_scene(SHAPE, seed=seed)
    row_dx = np.abs(np.diff(img, axis=1)).mean(axis=1)  # horizontal gradient per row
    col_dy = np.abs(np.diff(img, axis=0)).mean(axis=0)
    assert np.mean(row_dx > 0.008) > 0.95
    assert np.mean(col_dy > 0.008) > 0.95
    # also locally: nearly every 32-px piece of a row has horizontal texture
    pieces = np.abs(np.diff(img, axis=1))[:, : 511 // 32 * 32].reshape(SHAPE[0], -1, 32).mean(-1)
    assert np.mean(pieces > 0.004) > 0.95


def test_scene_has_homogeneous_and_busy_areas(scene):
    local_std = np.sqrt(np.maximum(ndi.uniform_filter(scene.astype(np.float64) ** 2, 15)
                                   - ndi.uniform_filter(scene.astype(np.float64), 15) ** 2, 0))
    assert np.mean(local_std < 0.03) > 0.05  # smooth fields
    assert np.mean(local_std > 0.08) > 0.05  # edges, buildings, trees


def test_object_counts_are_parameters():
    bare = aerial_scene((128, 128), seed=1, n_roads=0, n_buildings=0, n_trees=0)
    busy = aerial_scene((128, 128), seed=1, n_roads=4, n_buildings=40, n_trees=400)
    assert bare.std() < busy.std()
    assert aerial_scene((64, 80), seed=0, blur_sigma=0).shape == (64, 80)


def test_scene_parameter_errors():
    with pytest.raises(ParameterError, match="shape"):
        aerial_scene((8, 100), seed=0)
    with pytest.raises(ParameterError, match="n_trees"):
        aerial_scene((64, 64), seed=0, n_trees=-1)
    with pytest.raises(ParameterError, match="blur_sigma"):
        aerial_scene((64, 64), seed=0, blur_sigma=-1.0)


@pytest.fixture(scope="module")
def pasted(scene):
    changed, mask = paste_changes(scene, count=12, size_range=(12, 40), seed=9, margin=20)
    return scene, changed, mask


def test_paste_changes_only_inside_mask(pasted):
    scene, changed, mask = pasted
    assert changed.dtype == np.float32 and mask.dtype == bool
    assert changed.shape == mask.shape == scene.shape
    assert np.array_equal(changed[~mask], scene[~mask])
    assert changed.min() >= 0 and changed.max() <= 1
    # the mask is the pasted pixels: almost all of them differ clearly
    assert np.mean(np.abs(changed[mask] - scene[mask]) > 0.05) > 0.95


def test_paste_changes_objects_count_size_margin(pasted):
    scene, changed, mask = pasted
    labels, n = ndi.label(mask, structure=np.ones((3, 3)))
    assert n == 12  # no two objects overlap or touch
    areas = np.bincount(labels.ravel())[1:]
    # long side 12..40 px, short side 0.4..1 of it (ellipses ~ pi/4 of the box)
    assert areas.min() >= 0.4 * 0.785 * 12 * 12 * 0.7
    assert areas.max() <= 40 * 40 * 1.05
    rows, cols = np.nonzero(mask)
    assert rows.min() >= 20 and cols.min() >= 20
    assert rows.max() < SHAPE[0] - 20 and cols.max() < SHAPE[1] - 20


def test_paste_changes_contrast(pasted):
    scene, changed, mask = pasted
    labels, n = ndi.label(mask, structure=np.ones((3, 3)))
    for i, sl in enumerate(ndi.find_objects(labels), start=1):
        obj = labels == i
        ring = ndi.binary_dilation(obj, iterations=8) & ~mask
        contrast = abs(changed[obj].mean() - scene[ring].mean())
        assert contrast >= 0.25, f"object {i}: contrast {contrast:.3f}"
        assert changed[obj].std() > 0.005  # some internal texture


def test_paste_changes_deterministic(scene):
    a = paste_changes(scene, count=5, seed=3)
    b = paste_changes(scene, count=5, seed=3)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    c = paste_changes(scene, count=5, seed=4)
    assert not np.array_equal(a[1], c[1])
    none, empty = paste_changes(scene, count=0, seed=3)
    assert not empty.any() and np.array_equal(none, scene)


def test_paste_changes_errors(scene):
    with pytest.raises(ParameterError, match="count"):
        paste_changes(np.zeros((40, 40), np.float32), count=50, size_range=(20, 30), seed=0)
    with pytest.raises(ParameterError, match="size_range"):
        paste_changes(scene, count=1, size_range=(30, 10), seed=0)
    with pytest.raises(ParameterError, match="margin"):
        paste_changes(scene, count=1, seed=0, margin=-2)
    with pytest.raises(InputError, match="scene"):
        paste_changes(np.zeros(10), count=1, seed=0)
