"""The depth-layer step: raised structures nearer to the camera than the
ground move more under its translations; a candidate change that registers at
some relative depth is parallax, not change (METHOD.md section 3, item 8)."""

import numpy as np
import pytest

from rsmb import ops

SHAPE, EXPOSURE = (384, 384), 20.0


def _path(tx=(15.0, 19.0), ty=(3.0, 6.0)):
    duration = SHAPE[0] + EXPOSURE + 1.0
    t = np.linspace(0.0, duration, 32)
    poses = np.zeros((t.size, 6))
    poses[:, 0] = np.linspace(*tx, t.size)
    poses[:, 1] = np.linspace(*ty, t.size)
    return ops.CameraPath(t, poses)


@pytest.fixture(scope="module")
def raised():
    """Four roofs at relative depths 0.4 to 0.8 under a translation of 15 to
    19 px, and five new objects: rendered with the independent renderer."""
    pair = ops.synthesize_pair(SHAPE, path=_path(), exposure=EXPOSURE, changes=5, noise=0.002, seed=41,
                               interpolation="cubic", structures=4, depths=(0.4, 0.8))
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera)
    return pair, reg, ops.detect_changes(reg, pair.distorted, camera=pair.camera)


def test_raised_structures_are_parallax_not_change(raised):
    pair, reg, plain = raised
    assert len(pair.depths) == 4
    before = ops.confusion(plain.mask, pair.change_mask)
    layers = ops.depth_layers(reg, pair.reference, pair.distorted, camera=pair.camera, threshold=plain.threshold)
    reg.registered[:], reg.chi[:] = layers.registered, layers.chi
    after = ops.detect_changes(reg, pair.distorted, camera=pair.camera).mask & ~layers.parallax
    counts = ops.confusion(after, pair.change_mask)
    assert before.precision < 0.8  # without the step, the roofs are reported as change
    assert counts.precision >= 0.95 and counts.recall >= 0.9, counts.as_dict()
    # every roof is found at about its depth, and no new object is called parallax
    found = sorted(c["depth"] for c in layers.components if c["pixels"] > 200)
    assert len(found) == 4 and np.abs(np.array(found) - np.sort(pair.depths)).max() <= 0.1, (found, pair.depths)
    assert not (layers.parallax & pair.change_mask).any()


def test_without_parallax_nothing_is_a_layer():
    pair = ops.synthesize_pair(SHAPE, motion="inplane", exposure=EXPOSURE, changes=6, noise=0.002, seed=42,
                               interpolation="cubic")
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera)
    plain = ops.detect_changes(reg, pair.distorted, camera=pair.camera)
    layers = ops.depth_layers(reg, pair.reference, pair.distorted, camera=pair.camera, threshold=plain.threshold)
    assert not (layers.parallax & pair.change_mask).any()
    assert all(c["pixels"] < 60 for c in layers.components)  # at most a few stray residual specks


def _tile_method(pair, params):
    """Register, re-ground and run the depth step as ``rsmb detect`` does a tile:
    the registration, the change threshold and the depth layers."""
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera, params=params)
    threshold = ops.detect_changes(reg, pair.distorted, camera=pair.camera).threshold
    reg = ops.reground(reg, pair.reference, pair.distorted, camera=pair.camera, params=params, threshold=threshold)
    layers, _, _ = ops.depth_step(reg, pair.reference, pair.distorted, camera=pair.camera, threshold=threshold,
                                  space=params.resolved(pair.camera).space, lambda_w=params.lambda_w,
                                  lambda_chi=params.lambda_chi)
    return reg, threshold, layers


@pytest.mark.parametrize("seed", [1, 7])
def test_objects_on_and_against_a_block_stay_changes(seed):
    """Parallax per pixel (issue 15): a new object on a roof or touching a block
    is not explained at the block's depth and stays a change, while the block
    itself is parallax.  Registered as ``rsmb detect`` does a tile (register,
    re-ground, depth step)."""
    from rsmb.ops.synthetic._raised import AWAY, raised_pair

    pair, objects = raised_pair((256, 256), seed=seed, blocks=2, away=1, block_size=(36, 48), object_size=(14, 20))
    changes, params = ops.ChangeParams(), ops.RegistrationParams()
    reg, threshold, layers = _tile_method(pair, params)
    score = np.where(layers.parallax | ~reg.valid, 0.0, ops.change_score(layers.chi, layers.registered, params=changes))
    mask = ops.change_mask(score, threshold, params=changes)
    near = [m for kind, m in objects if kind != AWAY]
    assert len(near) == 2 and all(m.sum() > 50 for m in near)
    for m in near:
        assert mask[m].mean() >= 0.9
        assert layers.parallax[m].mean() <= 0.05
    roofs = pair.parallax_mask & pair.valid
    assert mask[roofs].mean() <= 0.02  # the blocks (and the ground they hid) are no change
    assert ops.confusion(mask, pair.change_mask).precision >= 0.95


def test_an_object_left_beside_a_layer_does_not_borrow_it_at_another_depth():
    """What a block's depth leaves of its component is tested again on its own
    (:func:`ops.depth._layers._layers_of`), but no depth explains a pixel by
    showing the block at a depth other than its own: here the object against
    the block is left beside it, and a nearer depth paints the block's roof
    over it.  Without that rule the object was a layer of its own, wholly
    parallax (this seed); with it, the object stays a change."""
    from rsmb.ops.synthetic._raised import AGAINST_BLOCK, raised_pair

    pair, objects = raised_pair((256, 256), seed=6, blocks=2, away=1, block_size=(36, 48), object_size=(14, 20))
    changes, params = ops.ChangeParams(), ops.RegistrationParams()
    reg, threshold, layers = _tile_method(pair, params)
    score = np.where(layers.parallax | ~reg.valid, 0.0, ops.change_score(layers.chi, layers.registered, params=changes))
    mask = ops.change_mask(score, threshold, params=changes)
    (against,) = [m for kind, m in objects if kind == AGAINST_BLOCK]
    assert against.sum() > 50
    assert mask[against].mean() >= 0.85 and layers.parallax[against].mean() <= 0.2
    assert mask[pair.parallax_mask & pair.valid].mean() <= 0.02  # the blocks are still no change


def test_one_renderer_at_inverse_depth_is_the_row_warp_at_depth(raised):
    """The depth steps' one renderer (inverse depth ``q`` multiplies the
    translations) gives what the row warp of ``ops._warp`` gives with the
    translations divided by the relative depth ``1 / q`` (how the layers were
    rendered before): the same values to float32 rounding, NaN at the same pixels."""
    from rsmb.ops._camera import full_poses
    from rsmb.ops._warp import _build_row
    from rsmb.ops.depth._layers import _Frame

    pair, reg, _ = raised
    frame = _Frame(reg, pair.reference, pair.distorted, pair.camera, (0, 0), (0, 0))
    rows, cols = slice(100, 160), slice(37, 301)
    inplane = reg.axes[:next(iter(reg.row_weights.values()))[0].shape[1]]
    cx, cy = pair.camera.center_xy
    for depth in (0.45, 0.8, 1.3):
        want = np.full((rows.stop - rows.start, cols.stop - cols.start), np.nan, np.float32)
        for n, row in enumerate(range(rows.start, rows.stop)):
            poses, w = reg.row_weights[row]
            p6 = full_poses(poses, inplane)
            p6[:, :3] /= depth
            buf = np.empty((len(w), want.shape[1]), np.float32)
            valid = _build_row(np.asarray(pair.reference, np.float32), float(row), float(cols.start), p6,
                               float(pair.camera.focal), cx, cy, buf)
            gain = 1.0 if reg.column_gain is None else reg.column_gain[cols]
            want[n] = np.where(valid != 0, (w @ buf) * gain, np.nan)
        got = frame.render(rows, cols, 1.0 / depth)
        assert np.isfinite(want).mean() > 0.9
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)


def test_an_object_on_a_roof_is_judged_against_the_roof():
    """A new object on a roof that its component's depth leaves unexplained is
    compared with the roof at that depth (what it lies on), not with the ground
    the registered plane samples there: it keeps its full contrast and stays a
    change.  Seed 6 of the small case: with the plane's values two thirds of
    the object were lost to the change rule's half-maximum test."""
    from rsmb.ops.synthetic._raised import ON_ROOF, raised_pair

    pair, objects = raised_pair((256, 256), seed=6, blocks=2, away=1, block_size=(36, 48), object_size=(14, 20))
    changes, params = ops.ChangeParams(), ops.RegistrationParams()
    reg, threshold, layers = _tile_method(pair, params)
    roof = next(m for kind, m in objects if kind == ON_ROOF)
    assert layers.on_layer[roof].mean() >= 0.5  # most of it is its layer's component, judged there
    # the model there is the roof (bright), the object dark: its residual is the object's contrast
    judged = roof & layers.on_layer
    assert np.median(layers.registered[judged] - pair.distorted[judged]) >= 0.5
    score = np.where(layers.parallax | ~reg.valid, 0.0, ops.change_score(layers.chi, layers.registered, params=changes))
    mask = ops.change_mask(score, threshold, params=changes)
    assert mask[roof].mean() >= 0.9 and layers.parallax[roof].mean() <= 0.05


@pytest.mark.parametrize("seed", [9, 14])
def test_every_block_is_a_layer_at_its_own_depth(seed):
    """A uniform roof is explained at every depth that moves it over its
    component's pixels, nearer ones included: what tells its depth is the
    ground beside it, which a nearer depth paints over.  Both blocks of the
    small case are found, each within one depth step (0.05) of its true depth
    (on these seeds the component's own count alone found one block only)."""
    from rsmb.ops.synthetic._raised import raised_pair

    pair, _ = raised_pair((256, 256), seed=seed, blocks=2, away=1, block_size=(36, 48), object_size=(14, 20))
    _, _, layers = _tile_method(pair, ops.RegistrationParams())
    found = sorted(c["depth"] for c in layers.components if c["pixels"] > 200)
    assert len(found) == 2, (found, pair.depths)
    assert np.abs(np.array(found) - np.sort(pair.depths)).max() <= 0.05 + 1e-9, (found, pair.depths)



def _touching_roofs(seed=3, depths=(0.75, 0.45), gap=4, side=256):
    """Two flat roofs side by side along the camera's translation, ``gap`` px
    apart on the ground, at two relative depths: the nearer moves over the
    ground the farther hid, so their residuals touch and make one candidate
    component.  No new object: every candidate pixel is parallax."""
    from rsmb.ops._camera import Camera
    from rsmb.ops.synthetic._layered import Structure, render_layered, with_roofs
    from rsmb.ops.synthetic._synth import _margin, readout_path

    shape, exposure = (side, side), 24.0
    camera = Camera.for_shape(shape)
    path = readout_path(side, exposure, tx=(15.0, 19.0), ty=(3.0, 6.0), rz=(-0.5, 0.5))
    m = _margin(path, camera, shape)
    scene = (0.05 + 0.7 * ops.aerial_scene((side + 2 * m, side + 2 * m), seed=seed)).astype(np.float32)
    rng = np.random.default_rng(seed)
    roofs, top, left = [], m + side // 2 - 20, m + side // 2 - 40
    for depth, tone in zip(depths, (0.85, 0.8)):
        mask = np.zeros(scene.shape, bool)
        mask[top:top + 40, left:left + 34] = True
        roof = np.clip(tone + 0.03 * rng.standard_normal(scene.shape), 0, 1)
        roofs.append(Structure(mask, np.where(mask, roof, 0).astype(np.float32), depth))
        left += 34 + gap
    kw = dict(shape=shape, camera=camera, row_delay=1.0, exposure=exposure, source_origin_yx=(m, m),
              interpolation="cubic")
    image, _, parallax = render_layered(scene, roofs, path, **kw)
    distorted = (image + rng.normal(0, 0.002, image.shape)).astype(np.float32)
    reference = np.ascontiguousarray(with_roofs(scene, roofs)[m:m + side, m:m + side])
    return reference, distorted, camera, parallax


def test_two_touching_roofs_at_two_depths_are_both_layers(monkeypatch):
    """Two roofs whose residuals touch make one candidate component that no one
    depth explains: what the first layer's depth leaves of it is tested again
    on its own and found at the other roof's depth.  With one layer per
    component (as before) a band of the farther roof, its edge and the ground
    it hid, stayed a change candidate (``kept``); where that
    layer's depth was a compromise between both roofs, its footprint kept the
    dense depth map from giving the band its own depth, and the band was
    reported as change (the bench's 1024 px parallax case)."""
    from types import SimpleNamespace

    from rsmb.ops.depth import _layers

    reference, distorted, camera, parallax = _touching_roofs()
    pair = SimpleNamespace(reference=reference, distorted=distorted, camera=camera)
    min_area = ops.LayerParams().min_area

    def layers_of_the_pair():
        _, _, layers = _tile_method(pair, ops.RegistrationParams())
        depths = [c["depth"] for c in layers.components]
        return layers, [any(abs(d - true) <= 0.05 + 1e-9 for d in depths) for true in (0.75, 0.45)]

    layers, found = layers_of_the_pair()
    assert all(found), [c["depth"] for c in layers.components]
    assert not ops.large_components(layers.kept, min_area).any()  # what is left of the roofs: specks
    assert not (layers.kept & ~parallax).any()
    monkeypatch.setattr(_layers, "MAX_LAYERS", 1)  # one layer per component
    layers, found = layers_of_the_pair()
    assert found == [False, True]
    assert ops.large_components(layers.kept & parallax, min_area).sum() >= 100


def _far_patch_pair():
    """Smooth dark ground moving 19 px, a bright uniform new object in the
    capture, and a bright patch of its value in the reference where a depth
    of 0.1 (inverse depth 10: ten times the ground's motion) carries it."""
    from scipy import ndimage

    ground = ndimage.gaussian_filter(np.random.default_rng(3).normal(0.0, 1.0, SHAPE), 3.0)
    scene = (0.25 + 0.04 * ground / ground.std()).astype(np.float32)
    scene[112:140, 86:114] = 0.9  # 190 px left of the object's ground point and 24 px up
    rendered = ops.render(scene, _path(tx=(19.0, 19.0), ty=(2.0, 3.0)), shape=SHAPE, exposure=EXPOSURE,
                          interpolation="cubic")
    capture = rendered.image + np.random.default_rng(4).normal(0.0, 0.002, SHAPE).astype(np.float32)
    new = np.zeros(SHAPE, bool)
    new[142:158, 282:298] = True
    capture[new] = 0.9
    capture[~rendered.valid] = np.nan
    return scene, capture, new


def test_no_layer_borrows_a_patch_far_away():
    """No layer nearer than 0.3 (the depth map's reach): a nearer depth moves
    a pixel far enough for a uniform new object to find a patch of its own
    brightness by chance, and would call it parallax."""
    scene, capture, new = _far_patch_pair()
    camera = ops.Camera.for_shape(SHAPE)
    reg = ops.register(scene, capture, camera=camera)
    threshold = ops.detect_changes(reg, capture, camera=camera).threshold
    near = ops.LayerParams(depths=(0.1,) + ops.LayerParams().depths)
    borrowed = ops.depth_layers(reg, scene, capture, camera=camera, threshold=threshold, params=near)
    assert borrowed.parallax[new].mean() > 0.9  # the scene does hold the chance: at depth 0.1 it is parallax
    layers = ops.depth_layers(reg, scene, capture, camera=camera, threshold=threshold)
    assert min(ops.LayerParams().depths) >= 0.3
    assert not layers.parallax[new].any() and not layers.components


def test_a_thin_rim_along_an_explained_structure_is_its_remnant():
    """:func:`rims_along`: the pixels of rims thinner than 3 px that touch an
    explained structure, even where the rim joins a new object; never a thick
    candidate's own edge, nor the ring around a speck explained by chance."""
    from rsmb.ops.depth._layers import rims_along

    explained = np.zeros((40, 40), bool)
    explained[10:30, 5:15] = True  # a structure the depth map explains
    candidates = np.zeros_like(explained)
    candidates[10:30, 18:30] = True  # a new object beside it
    candidates[9, 5:20] = True  # a 1-px rim along the structure's top, joining the object
    candidates[10:30, 15:17] = True  # a 2-px rim along its right side: the pixels that touch it
    candidates[30:38, 5:15] = True  # a thick object against its bottom
    rims = rims_along(candidates, explained, 20)
    assert rims[9, 5:16].all() and rims[10:30, 15].all() and not rims[10:30, 16].any()
    assert not rims[9, 17:20].any()  # thin, but touches no explained pixel
    assert not rims[10:30, 18:30].any() and not rims[30:38, 5:15].any()
    speck = np.zeros_like(explained)
    speck[15:18, 19:22] = True  # a few pixels explained by chance inside the object, 1 px from its edge
    assert rims_along(candidates & ~speck, speck, 1)[15:18, 18].all()  # as a structure, it would make a rim
    assert not rims_along(candidates & ~speck, speck, 20).any()
