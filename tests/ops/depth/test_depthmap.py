"""The dense depth map: with the rows' weights fixed, every pixel takes the
relative depth whose re-rendering explains its window clearly better than the
registered plane (METHOD.md section 3, item 8, extended to the whole residual).
Raised structures are explained at about their depth; new objects are
explained at none and are still detected."""

import dataclasses

import numpy as np
import pytest
from scipy import ndimage

from rsmb import ops
from rsmb.ops.depth._depthmap import (_BIG, _INDEX, _active, _Best, _Fit, _geometry, _RowPoses, _runs, _sweep,
                                      _window_cost)

from .test_layers import EXPOSURE, SHAPE, _path  # the same scene and camera path


def _run(pair):
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera)
    plain = ops.detect_changes(reg, pair.distorted, camera=pair.camera)
    dense = ops.depth_map(reg, pair.reference, pair.distorted, camera=pair.camera, threshold=plain.threshold)
    return reg, plain, dense


def _rmse(registered, distorted, mask):
    return float(np.sqrt(np.mean((registered[mask] - distorted[mask]) ** 2)))


@pytest.fixture(scope="module")
def raised():
    """Four roofs at relative depths 0.4 to 0.8 under a translation of 15 to
    19 px, and five new objects: rendered with the independent renderer."""
    pair = ops.synthesize_pair(SHAPE, path=_path(), exposure=EXPOSURE, changes=5, noise=0.002, seed=41,
                               interpolation="cubic", structures=4, depths=(0.4, 0.8))
    return (pair, *_run(pair))


def _explainable(pair, reg, threshold):
    """Pixels of the roofs (not the ground they hid) that the rows' weights
    explain at one of the true depths: what the depth map can reach."""
    rows = _RowPoses.of(reg, pair.distorted.shape[0])
    geometry = _geometry(pair.camera, (0, 0), (0, 0))
    best = np.full(pair.distorted.shape, np.inf)
    for depth in pair.depths:
        rendered = rows.render(np.ascontiguousarray(pair.reference, np.float32), geometry, 1.0 / depth,
                               np.ones(pair.distorted.shape, bool))
        best = np.fmin(best, np.abs(rendered - pair.distorted))
    ok = reg.valid & np.isfinite(reg.registered)
    return pair.parallax_mask & ~pair.change_mask & ok & (best < threshold)


def test_raised_structures_are_explained_at_a_depth(raised):
    pair, reg, plain, dense = raised
    reachable = _explainable(pair, reg, plain.threshold)
    assert reachable.sum() > 2000
    before, after = [np.abs(r - pair.distorted)[reachable] for r in (reg.registered, dense.registered)]
    assert np.mean(before <= plain.threshold) < 0.5  # on the plane, the roofs are mostly residual
    assert np.mean(after <= plain.threshold) >= 0.7, np.mean(after <= plain.threshold)
    assert np.sqrt(np.mean(after ** 2)) < 0.6 * np.sqrt(np.mean(before ** 2))
    # the roofs are nearer than the ground: where a depth was taken on them, it is nearer
    taken = reachable & (dense.inverse_depth != 1.0)
    assert np.mean(dense.inverse_depth[taken] > 1.0) > 0.9
    # the ground off the roofs keeps its plane
    ok = reg.valid & np.isfinite(reg.registered)
    ground = ok & ~ndimage.binary_dilation(pair.parallax_mask | pair.change_mask, iterations=8)
    assert np.mean(dense.inverse_depth[ground] != 1.0) < 0.02


def test_new_objects_are_explained_at_no_depth(raised):
    pair, reg, plain, dense = raised
    assert not (dense.explained & pair.change_mask).any()
    rerendered = dataclasses.replace(reg, registered=dense.registered, chi=dense.chi)  # the fixture's stays
    after = ops.detect_changes(rerendered, pair.distorted, camera=pair.camera).mask
    roofs = pair.parallax_mask & ~pair.change_mask
    # the changes alone (roof pixels not counted): as well detected as on the plane
    before_counts = ops.confusion(plain.mask & ~roofs, pair.change_mask)
    counts = ops.confusion(after & ~roofs, pair.change_mask)
    assert counts.recall >= before_counts.recall - 0.01 and counts.precision >= before_counts.precision - 0.01, \
        (before_counts.as_dict(), counts.as_dict())
    assert counts.recall >= 0.9
    # and the roofs are no longer change
    assert (after & roofs).sum() < 0.5 * (plain.mask & roofs).sum()


def test_without_parallax_the_plane_stays():
    pair = ops.synthesize_pair(SHAPE, motion="inplane", exposure=EXPOSURE, changes=6, noise=0.002, seed=42,
                               interpolation="cubic")
    reg, plain, dense = _run(pair)
    ok = reg.valid & np.isfinite(reg.registered)
    assert np.mean(dense.inverse_depth[ok] != 1.0) < 0.01
    assert not (dense.explained & pair.change_mask).any()
    reg.registered[:], reg.chi[:] = dense.registered, dense.chi
    after = ops.detect_changes(reg, pair.distorted, camera=pair.camera).mask
    assert ops.confusion(after, pair.change_mask).f_measure >= ops.confusion(plain.mask, pair.change_mask).f_measure - 0.005


def test_a_flat_scene_is_swept_at_its_change_candidates_only():
    """A depth explains too few of the pixels above the threshold: only their
    windows are swept, where the whole sweep explains the same pixels;
    everywhere else the plane stays."""
    pair = ops.synthesize_pair(SHAPE, motion="inplane", exposure=EXPOSURE, changes=6, noise=0.002, seed=43,
                               interpolation="cubic")
    reg, plain, dense = _run(pair)
    whole = ops.depth_map(reg, pair.reference, pair.distorted, camera=pair.camera, threshold=plain.threshold,
                          params=ops.DepthMapParams(min_share=0.0))
    ok = reg.valid & np.isfinite(reg.registered)
    assert np.mean(whole.explained[ok]) < ops.DepthMapParams().min_share
    above = ok & (np.abs(pair.distorted - reg.registered) > plain.threshold)
    near = ndimage.binary_dilation(above, np.ones((7, 7), bool))
    assert 0 < near.mean() < 0.2
    np.testing.assert_array_equal(dense.registered[~near], reg.registered[~near])
    assert (dense.inverse_depth[~near] == 1.0).all() and (whole.inverse_depth[~near] != 1.0).any()
    np.testing.assert_array_equal(dense.explained, whole.explained)
    # the fine pass's depth ranges come from the active neighbours, fewer here
    assert np.mean(dense.inverse_depth[near] == whole.inverse_depth[near]) > 0.99


def test_a_scene_with_depth_is_swept_whole(raised):
    pair, reg, plain, dense = raised
    whole = ops.depth_map(reg, pair.reference, pair.distorted, camera=pair.camera, threshold=plain.threshold,
                          params=ops.DepthMapParams(min_share=0.0))
    assert dense.depths == whole.depths > 0
    np.testing.assert_array_equal(dense.inverse_depth, whole.inverse_depth)
    np.testing.assert_array_equal(dense.registered, whole.registered)


def test_no_residual_no_work():
    """A registration that explains every pixel renders no depth at all."""
    pair = ops.synthesize_pair((96, 96), motion="inplane", exposure=8.0, changes=0, noise=0.0, seed=3,
                               interpolation="cubic")
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera)
    dense = ops.depth_map(reg, pair.reference, pair.distorted, camera=pair.camera, threshold=1.0)
    assert dense.depths == 0 and (dense.inverse_depth == 1.0).all()
    np.testing.assert_array_equal(dense.registered, reg.registered)


def test_isolated_pixels_open_no_window():
    """Only 8-connected groups of ``min_seed`` pixels above the threshold open
    a window to sweep: a lone pixel and a pair do not, a diagonal run of three
    does, and a pixel without data counts for no group."""
    residual = np.zeros((40, 60), np.float32)
    valid = np.ones(residual.shape, bool)
    residual[5, 5] = 1.0  # alone
    residual[20, 10:12] = 1.0  # a pair
    residual[[30, 31, 32], [40, 41, 42]] = 1.0  # three, corner to corner
    residual[10, 50:53] = 1.0  # three, one of them without data
    valid[10, 52] = False
    seeded = _active(residual, valid, 1.0, 7, 3)  # above half of 1.0
    group = np.zeros(residual.shape, bool)
    group[[30, 31, 32], [40, 41, 42]] = True
    np.testing.assert_array_equal(seeded, ndimage.binary_dilation(group, np.ones((7, 7), bool)) & valid)
    every = _active(residual, valid, 1.0, 7)  # min_seed 1: every pixel above the threshold
    np.testing.assert_array_equal(every, ndimage.binary_dilation(valid & (residual > 0.5), np.ones((7, 7), bool))
                                  & valid)
    for bad in (0, -1, 2.5, True, "3"):
        with pytest.raises(ops.ParameterError, match="min_seed"):
            ops.DepthMapParams(min_seed=bad)


def test_lone_pixels_keep_the_plane():
    """Lone pixels far above the threshold on a flat scene take no depth and
    keep the plane's values in their windows."""
    pair = ops.synthesize_pair(SHAPE, motion="inplane", exposure=EXPOSURE, changes=6, noise=0.002, seed=43,
                               interpolation="cubic")
    reg, plain, _ = _run(pair)
    ok = reg.valid & np.isfinite(reg.registered)
    far = ok & ~ndimage.binary_dilation(pair.change_mask | ~ok, np.ones((31, 31), bool))
    rows, cols = np.nonzero(far)
    pick = np.random.default_rng(1).choice(len(rows), 12, replace=False)
    g = pair.distorted.astype(np.float32).copy()
    g[rows[pick], cols[pick]] += 0.4
    spikes = np.zeros(g.shape, bool)
    spikes[rows[pick], cols[pick]] = True
    windows = ndimage.binary_dilation(spikes, np.ones((7, 7), bool))
    kw = dict(camera=pair.camera, threshold=plain.threshold)
    dense = ops.depth_map(reg, pair.reference, g, **kw)
    np.testing.assert_array_equal(dense.registered[windows], reg.registered[windows])
    assert (dense.inverse_depth[windows] == 1.0).all()


def test_lone_pixels_render_no_depth():
    """A registration that explains every pixel but a few lone ones renders no
    depth at all; swept with ``min_seed`` 1 (every pixel above the threshold
    a seed), the same pixels are rendered at every depth."""
    pair = ops.synthesize_pair((96, 96), motion="inplane", exposure=8.0, changes=0, noise=0.0, seed=3,
                               interpolation="cubic")
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera)
    ok = reg.valid & np.isfinite(reg.registered)
    g = pair.distorted.astype(np.float32).copy()
    threshold = 0.2
    assert np.abs(g - reg.registered)[ok].max() < 0.5 * threshold  # nothing else active
    for y, x in ((30, 30), (30, 60), (60, 45)):
        assert ok[y, x]
        g[y, x] += 0.5
    kw = dict(camera=pair.camera, threshold=threshold)
    assert ops.depth_map(reg, pair.reference, g, **kw).depths == 0
    assert ops.depth_map(reg, pair.reference, g, params=ops.DepthMapParams(min_seed=1), **kw).depths > 0


def test_depth_count_fits_the_sweeps_indices():
    """The sweep keeps depth indices in :data:`_INDEX` integers below its
    sentinel: more depths than that are refused, not wrapped around."""
    assert ops.DepthMapParams(max_depths=_BIG - 1).max_depths == _BIG - 1
    for bad in (_BIG, 1):
        with pytest.raises(ops.ParameterError, match="max_depths"):
            ops.DepthMapParams(max_depths=bad)


def test_the_sweep_is_each_depth_rendered_and_box_filtered(raised):
    """The fused sweep (one kernel for every depth, costs only on active pixels)
    against the sweep written out: each depth rendered on the dilated mask,
    its truncated residual box-filtered by OpenCV, the lowest cost kept."""
    pair, reg, plain, dense = raised
    g = pair.distorted.astype(np.float32)
    g[5, 7:12] = np.nan  # no capture data: never takes a depth
    tau, window = float(plain.threshold), 7
    rng = np.random.default_rng(0)
    active = ndimage.binary_dilation(rng.random(g.shape) < 0.002, iterations=4)
    active[:3], active[:, -2:] = True, True  # the borders (replicated) too
    render_mask = ndimage.binary_dilation(active, np.ones((window, window), bool))
    rows = _RowPoses.of(reg, g.shape[0])
    geometry = _geometry(pair.camera, (0, 0), (0, 0))
    ref = np.ascontiguousarray(pair.reference, np.float32)
    qs = np.linspace(0.0, 3.0, 13)
    want_best = np.full(g.shape, np.inf, np.float32)
    want_chosen, want_depth = np.full(g.shape, np.nan, np.float32), np.ones(g.shape, np.float32)
    for q in qs:
        rendered = rows.render(ref, geometry, float(q), render_mask)
        cost = _window_cost(np.where(np.isfinite(rendered), np.abs(g - rendered), tau), tau, window)
        better = active & (cost < want_best) & np.isfinite(rendered)
        want_best[better], want_chosen[better], want_depth[better] = cost[better], rendered[better], q
    best = np.full(g.shape, np.inf, np.float32)
    chosen, depth = np.full(g.shape, np.nan, np.float32), np.ones(g.shape, np.float32)
    scene = rows.scene(ref, geometry)
    render_mask = render_mask.astype(np.uint8)
    fit = _Fit(g, render_mask, active.astype(np.uint8), tau, window // 2, _runs(render_mask))
    _sweep(scene, fit, qs, 1, _Best(best, chosen, depth, np.full(g.shape, -1, _INDEX)))
    assert np.isfinite(want_best).sum() > 0.9 * active.sum() and not np.isfinite(best[~active]).any()
    np.testing.assert_allclose(best, want_best, rtol=1e-5, atol=1e-6)
    # depths whose costs tie to rounding may swap; everywhere else the same depth and value
    same = depth == want_depth
    assert same.mean() > 0.999
    np.testing.assert_array_equal(chosen[same], want_chosen[same])
    # coarse to fine: never below the full sweep's cost, and the same depth almost everywhere
    fine = np.full(g.shape, np.inf, np.float32)
    fine_chosen, fine_depth = np.full(g.shape, np.nan, np.float32), np.ones(g.shape, np.float32)
    _sweep(scene, fit, qs, 4, _Best(fine, fine_chosen, fine_depth, np.full(g.shape, -1, _INDEX)))
    swept = np.isfinite(want_best)
    assert np.array_equal(np.isfinite(fine), swept)
    assert (fine[swept] >= want_best[swept] - 1e-6).all()
    assert np.mean(fine_depth[swept] == want_depth[swept]) > 0.95, np.mean(fine_depth[swept] == want_depth[swept])
