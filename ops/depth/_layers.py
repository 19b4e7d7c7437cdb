"""The depth-layer step (METHOD.md section 3, item 8; the paper's Algorithm 1).

The registration explains the ground.  Anything nearer to the camera than the
ground (a roof, a tree crown) moves more under the camera's translations and
is left in ``chi``.  Each candidate change component is tested against depth
layers: the rows' weights stay fixed, the translations of their poses (tx, ty
and s) are divided by a relative depth ``rho`` (rotations stay), the
reference is warped and blurred again at that depth inside the component, and
its pixels whose residual falls below the change threshold are *explained*.

A component's depth is the one that explains most of its pixels less the
pixels of the ground ring around it (:data:`RING`: explained on the plane,
within that many px of the component) that it leaves unexplained: a layer
tried nearer than its own paints its edge over the ground beside it, and on a
uniform roof that is the only thing that tells the depths apart (its pixels
are explained at every depth that moves the roof over them).

A component is **parallax, not change** when at its depth:

- at least :data:`MIN_EXPLAINED` of its pixels are explained, and
- explained pixels plus the *disoccluded* ones, pixels whose ground point
  lies under the layer in the reference (the reference cannot show what the
  roof hid), make up at least :data:`MIN_COVERED` of it.

New objects are explained at no depth (the reference has nothing like them
there); the depth ``rho = 1`` is the ground itself and is not tried.

The decision is per component, its consequence per pixel: of a layer's
component, only the pixels explained at its depth, those on its edge (between
the values the layer renders around them: blur and the capture's optics),
the disoccluded ones and remnants (smaller than a change, or rims thinner
than 3 px) join ``parallax``.
The rest, a new object on the roof or touching the block, stays a change
candidate (``kept``), judged at the layer's depth only.

Two layers at different depths whose residuals touch (a near roof moving over
the ground a farther one hid) make one component that no one depth explains:
each connected piece of what a layer's depth leaves beside the layer (at
least ``min_area`` pixels; what falls on the layer is judged against it) is
tested again on its own, with the same rules, except that its
depth explains none of the pixels at which it would show a layer already found
at another depth than that layer's own (:func:`sees_a_layer_elsewhere`'s
rule: a new object beside a roof is not the roof seen nearer), and that it
needs evidence of a depth of its own: some pixel that depth alone explains.
"""

from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numpy as np
from scipy import ndimage

from .._camera import full_poses, pose_homographies
from .._oracle import optimal_chi
from ..changes._changes import large_components, over_threshold
from ._depthmap import _geometry, _RowPoses, render_at

__all__ = ["LayerParams", "LayerResult", "depth_layers", "sees_a_layer_elsewhere"]

MIN_EXPLAINED = 0.25
MIN_COVERED = 0.6
#: Most layers found in one candidate component (:func:`_layers_of`).
MAX_LAYERS = 4
#: Width (px) of the ground ring judged with a component's depth.  The ring's
#: first pixels show a layer painted beyond its edge; a wider ring takes in
#: ground whose texture a small shift still explains, which favours the depths
#: near the ground's.
RING = 2


@dataclass(frozen=True)
class LayerParams:
    """Tuning of :func:`depth_layers`.

    Attributes
    ----------
    depths : tuple of float
        Relative depths swept, evenly spaced (distance over the ground's;
        below 1 is nearer): every fourth first, then those within four steps
        of the best of them.  None nearer than 0.3, about the depth map's
        largest inverse depth (:attr:`DepthMapParams.max_inverse_depth`): a
        nearer depth moves a pixel by more than three times the ground's
        motion, far enough for a uniform new object to find a patch of its own
        brightness by chance.
    min_area : int
        Smallest component tested, pixels.
    """

    depths: tuple = tuple(round(0.3 + 0.05 * k, 2) for k in range(25) if abs(0.3 + 0.05 * k - 1.0) > 1e-6)
    min_area: int = 20


@dataclass
class LayerResult:
    """Result of :func:`depth_layers`.

    Attributes
    ----------
    parallax : ndarray of bool, shape (H, W)
        Pixels of components found to be depth layers.
    registered, chi : ndarray, shape (H, W), float32
        The registration's, with the explained pixels of those components
        re-rendered at their depth (and ``chi`` 0 on their disoccluded pixels).
    kept : ndarray of bool, shape (H, W)
        Pixels of those components that their depth does not explain and that
        do not see ground the layer hid: change candidates still (a new object
        on or against the layer).
    on_layer : ndarray of bool, shape (H, W)
        Those of ``kept`` that, carried at the layer's depth, fall on its
        footprint (a new object on the roof): judged against the layer
        (``registered`` the layer at its depth), at that depth only.
    components : list of dict
        Per layer: ``row``, ``col`` (centroid, window pixels), ``pixels``,
        ``depth``, ``explained`` (fraction) and ``rmse`` (intensity units, over
        its explained pixels).
    footprint : ndarray of int32, shape (Hr, Wr), or None
        Where each layer lies in the reference window: ``k + 1`` for
        ``components[k]`` (a later layer over an earlier one), 0 elsewhere;
        None when no layer was found.
    """

    parallax: np.ndarray
    registered: np.ndarray
    chi: np.ndarray
    kept: np.ndarray = None
    components: list = field(default_factory=list)
    footprint: np.ndarray = None
    on_layer: np.ndarray = None

    def __post_init__(self):
        if self.kept is None:
            self.kept = np.zeros(self.parallax.shape, bool)
        if self.on_layer is None:
            self.on_layer = np.zeros(self.parallax.shape, bool)


def depth_layers(registration, reference, distorted, *, camera, threshold, reference_origin_yx=(0, 0),
                 distorted_origin_yx=(0, 0), lambda_chi=0.02, params=None):
    """Tell parallax from change among the candidate changes of a registration.

    Parameters
    ----------
    registration : Registration
        Of ``distorted`` against ``reference`` (its row weights are re-used).
    reference : ndarray, shape (Hr, Wr), float32
        The reference window the registration used (NaN for no-data).
    distorted : ndarray, shape (H, W), float32
        The capture window (the values the registration fitted).
    camera : Camera
        Intrinsics of the whole image.
    threshold : float
        The change threshold (score units): components of ``|chi| >
        threshold`` are candidates, and a pixel is explained at a depth when
        its residual there is below it.
    reference_origin_yx, distorted_origin_yx : tuple of int
        The windows' positions in the whole image.
    lambda_chi : float
        eq. 13's weight of ``||chi||_1``, for the change term of re-rendered pixels.
    params : LayerParams, optional

    Returns
    -------
    LayerResult
    """
    params = params or LayerParams()
    out = LayerResult(np.zeros(distorted.shape, bool), registration.registered.copy(), registration.chi.copy())
    candidates = over_threshold(registration.chi, registration.valid, threshold)
    labels, count = ndimage.label(_dilate(candidates, cv2.MORPH_CROSS, 1), structure=np.ones((3, 3)))
    if count == 0:
        return out
    frame = _Frame(registration, reference, distorted, camera, reference_origin_yx, distorted_origin_yx)
    plane = registration.valid & ~candidates & np.isfinite(registration.registered)  # the ground the plane explains
    for index, box in enumerate(ndimage.find_objects(labels), start=1):
        box = tuple(slice(max(b.start - RING, 0), min(b.stop + RING, n)) for b, n in zip(box, labels.shape))
        component = (labels[box] == index) & candidates[box]
        if component.sum() >= params.min_area:
            _layers_of(out, frame, box, component, plane[box], threshold, lambda_chi, params)
    # a pixel a later layer explains is no longer kept by an earlier one
    out.kept &= ~out.parallax
    out.on_layer &= ~out.parallax
    return out


def _layers_of(out, frame, box, component, plane, threshold, lambda_chi, params):
    """The layers of one candidate component.  Two layers at different depths
    whose residuals touch make one component, and no one depth explains both:
    what a layer's depth leaves of it beside the layer (its kept pixels that do
    not fall on the layer: an object on a roof is judged against the roof) is
    tested again, each connected piece of at least ``min_area`` pixels on its
    own, at most :data:`MAX_LAYERS` layers per component.  A new object is
    explained at no depth of its own and stays a change."""
    pending, found_layers = [component], 0
    while pending and found_layers < MAX_LAYERS:
        piece = pending.pop()
        ring = plane & ~piece & _dilate(piece, cv2.MORPH_RECT, RING)
        found = _test_component(frame, box, piece, ring, params.depths, threshold, params.min_area,
                                earlier=out if found_layers else None)
        if found is None:
            continue
        _mark(out, frame, box, piece, found, lambda_chi)
        found_layers += 1
        # neither explained nor disoccluded, nor on the layer (an object on a roof is judged against it)
        rest = piece & ~found[2] & ~found[3] & ~found[5]
        lab, count = ndimage.label(rest, structure=np.ones((3, 3)))
        sizes = np.bincount(lab.ravel(), minlength=count + 1)
        pending.extend(lab == k for k in np.nonzero(sizes >= params.min_area)[0] if k > 0)


class _Frame:
    """What re-rendering a window at a depth needs: the capture and reference
    windows, the registration, the camera, and the rows' weighted poses ready
    for the depth steps' one renderer (:func:`ops.depth._depthmap.render_at`)."""

    def __init__(self, registration, reference, distorted, camera, reference_origin_yx, distorted_origin_yx):
        self.reg, self.ref, self.dist = registration, np.asarray(reference, np.float32), distorted
        self.carry = _Carry.of(registration, camera, reference_origin_yx, distorted_origin_yx)
        self.scene = _RowPoses.of(registration, distorted.shape[0]).scene(
            self.ref, _geometry(camera, reference_origin_yx, distorted_origin_yx))

    def render(self, rows, cols, q):
        """The registered window ``rows`` x ``cols`` re-rendered at inverse depth
        ``q``: float32, NaN where a row has no weights or a pose leaves the reference."""
        shape = (rows.stop - rows.start, cols.stop - cols.start)
        return render_at(self.scene, q, np.ones(shape, bool), (rows.start, cols.start))


class _Carry(NamedTuple):
    """What carrying capture pixels into the reference window needs
    (:func:`_to_reference`): the registration (its rows' centroid poses), the
    camera, the reference window's origin and the capture window's offset in
    it (px)."""

    reg: object
    camera: object
    origin: tuple
    dy: int
    dx: int

    @classmethod
    def of(cls, registration, camera, reference_origin_yx, distorted_origin_yx):
        dy = int(distorted_origin_yx[0] - reference_origin_yx[0])
        dx = int(distorted_origin_yx[1] - reference_origin_yx[1])
        return cls(registration, camera, tuple(reference_origin_yx), dy, dx)


def _test_component(frame, box, component, ring, depths, threshold, min_area, earlier=None):
    """(depth, rendered window, explained, disoccluded, footprint, on_layer)
    of the depth that makes the component parallax, or None.  A depth's
    score: the component's pixels it explains less the ``ring`` pixels (the
    ground beside it, explained on the plane) it leaves unexplained.  With
    ``earlier`` (a LayerResult: the piece was left by a layer), a depth
    explains none of the pixels at which it would show an earlier layer at
    another depth than that layer's own (:func:`_borrows`), and the piece is a
    layer only with a footprint (some pixel only its depth explains)."""
    g = frame.dist[box]
    pixels = int(component.sum())
    tried = {}

    def explain(depth):
        if depth not in tried:
            rendered = frame.render(box[0], box[1], 1.0 / depth)  # depths swept, inverse depths rendered
            fits = np.abs(g - rendered) < threshold
            if earlier is not None and earlier.footprint is not None:
                fits[component] &= ~_borrows(frame.carry, earlier, box, component, 1.0 / depth)
            explained = component & fits
            tried[depth] = (int(explained.sum()) - int((ring & ~fits).sum()), depth, rendered, explained)
        return tried[depth]

    # every fourth depth first, then the depths around the best of them
    coarse = max((explain(d) for d in depths[::4]), key=lambda t: t[0])
    if coarse[3].sum() < 0.5 * MIN_EXPLAINED * pixels:
        return None  # nothing like a layer: a change
    step = 4 * (depths[1] - depths[0]) if len(depths) > 1 else 0.0
    near = [d for d in depths if abs(d - coarse[1]) <= step + 1e-9]
    _, depth, rendered, explained = max((explain(d) for d in near), key=lambda t: t[0])
    count = int(explained.sum())
    if count < MIN_EXPLAINED * pixels:
        return None
    # the layer's footprint from the pixels its depth alone explains: flat ground
    # beside it is explained at many depths and would widen it
    others = [t[3] for d, t in tried.items() if abs(d - depth) > step / 4 + 1e-9]
    decisive = explained & ~np.any(others, axis=0) if others else explained
    edge = _edge(component & ~explained, explained, rendered, g, threshold)
    # the layer as the capture sees it: what its depth explains in the window
    # (a uniform roof's inside is no candidate) connected to its decisive pixels
    seen = np.abs(g - rendered) < threshold
    lab, _ = ndimage.label(seen, structure=np.ones((3, 3)))
    seen = np.isin(lab, np.unique(lab[decisive & seen])) & (lab > 0)
    footprint = _footprint(frame, box, seen | explained, decisive, 1.0 / depth)
    if earlier is not None and not footprint.any():
        return None  # a piece left by a layer, with no pixel only this depth explains: no depth of its own
    disoccluded = _disoccluded(frame, box, component & ~explained & ~edge, footprint, 1.0 / depth) | edge
    if count + disoccluded.sum() < MIN_COVERED * pixels:
        return None
    # what is left of the layer in pieces smaller than a change, or thinner than
    # 3 px (a rim along its edge), is its remnant
    rest = component & ~explained & ~disoccluded
    body = ndimage.binary_propagation(ndimage.binary_erosion(rest, np.ones((3, 3), bool)), mask=rest)
    disoccluded |= rest & ~(large_components(rest, min_area) & body)
    # what is left sees the layer (carried at its depth, it falls on the layer's
    # footprint: a new object on the roof) or the ground beside it
    rest = component & ~explained & ~disoccluded
    on_layer = np.zeros_like(rest)
    if rest.any() and footprint.any():
        on_layer[rest] = _lookup(footprint, _to_reference(frame.carry, box, rest, 1.0 / depth))
    return depth, rendered, explained, disoccluded, footprint, on_layer


def sees_a_layer_elsewhere(layers, registration, pixels, inverse_depth, *, camera, reference_origin_yx=(0, 0),
                           distorted_origin_yx=(0, 0), tolerance=2.0):
    """Which of ``pixels`` would, at their ``inverse_depth``, see a layer of
    ``layers`` at a depth other than the layer's own: carried by their row's
    centroid pose at that inverse depth, they land on the layer's footprint in
    the reference, and that inverse depth moves them by more than
    ``tolerance`` px more or less than the layer's does.  The reference shows
    the layer at its own depth, so no other depth may borrow its values (a new
    object beside a bright roof is not the roof seen at another depth).

    Parameters
    ----------
    layers : LayerResult
    registration : Registration
    pixels : ndarray of bool, shape (H, W)
    inverse_depth : ndarray of float32, shape (H, W)
        Relative inverse depth per pixel (1: the registered plane).
    camera : Camera
    reference_origin_yx, distorted_origin_yx : tuple of int
    tolerance : float
        Pixels.

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    out = np.zeros(pixels.shape, bool)
    if layers.footprint is None or not pixels.any():
        return out
    carry = _Carry.of(registration, camera, reference_origin_yx, distorted_origin_yx)
    whole = (slice(0, pixels.shape[0]), slice(0, pixels.shape[1]))
    out[pixels] = _borrows(carry, layers, whole, pixels, inverse_depth[pixels].astype(np.float64), tolerance)
    return out


def _borrows(carry, layers, box, pixels, q, tolerance=2.0):
    """Per pixel of ``pixels`` (bool in ``box``), in their order: carried by its
    row's centroid pose at inverse depth ``q`` (a number or one per pixel), it
    lands on a layer's footprint, and ``q`` moves it by more than
    ``tolerance`` px more or less than that layer's own inverse depth does."""
    q = np.broadcast_to(np.asarray(q, np.float64), (int(pixels.sum()),))
    points = np.round(_to_reference(carry, box, pixels, q)).astype(int)
    r, c = points.T
    ok = (r >= 0) & (c >= 0) & (r < layers.footprint.shape[0]) & (c < layers.footprint.shape[1])
    label = np.zeros(len(q), np.int32)
    label[ok] = layers.footprint[r[ok], c[ok]]
    layer_q = np.array([0.0] + [1.0 / comp["depth"] for comp in layers.components])[label]
    rows = np.nonzero(pixels)[0] + box[0].start
    p6 = full_poses(carry.reg.trajectory[rows], carry.reg.axes)
    shift = np.hypot(p6[:, 0], p6[:, 1])  # px a unit of inverse depth moves the pixel
    return (label > 0) & (np.abs(q - layer_q) * np.maximum(shift, 1.0) > tolerance)


def _edge(pixels, explained, rendered, g, threshold):
    """Which of ``pixels`` touch explained ones and lie between the values the
    layer renders around them (3 x 3): its edge, blurred and sampled
    differently by the capture's optics."""
    finite = np.isfinite(rendered)
    lo = ndimage.minimum_filter(np.where(finite, rendered, np.inf), 3)
    hi = ndimage.maximum_filter(np.where(finite, rendered, -np.inf), 3)
    near = _dilate(explained, cv2.MORPH_RECT, 1)
    return pixels & near & (g >= lo - threshold) & (g <= hi + threshold)


def _footprint(frame, box, explained, decisive, q):
    """The layer at inverse depth ``q`` in the reference window (bool, its
    shape): where its ``explained`` pixels (window box) come from, holes
    filled (objects on it included), within the convex hull of where its
    ``decisive`` pixels (explained at that depth only) come from: flat ground
    beside a layer is explained at its depth too and would widen it."""
    if not decisive.any():
        return np.zeros(frame.ref.shape, bool)
    inside = _filled(frame, _to_reference(frame.carry, box, explained, q))
    return inside & _hull(frame, _to_reference(frame.carry, box, decisive, q))


def _disoccluded(frame, box, pixels, footprint, q):
    """Which of ``pixels`` (window box) see, on the ground, a point that the
    layer at inverse depth ``q`` (its reference ``footprint``) covered in the
    reference, and do not see the layer itself (carried at ``q``, they fall
    off it): the ground the layer hid."""
    if not pixels.any() or not footprint.any():
        return np.zeros_like(pixels)
    near = cv2.dilate(footprint.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    hit = _lookup(near, _to_reference(frame.carry, box, pixels, 1.0)) & \
        ~_lookup(footprint, _to_reference(frame.carry, box, pixels, q))
    out = np.zeros_like(pixels)
    out[pixels] = hit
    return out


def _inside(frame, points):
    shape = frame.ref.shape
    keep = (points[:, 0] >= 0) & (points[:, 1] >= 0) & (points[:, 0] < shape[0] - 1) & (points[:, 1] < shape[1] - 1)
    return np.round(points[keep]).astype(np.int32)


def _filled(frame, points):
    """The reference-window pixels under ``points`` (n, 2) (row, col), closed
    and with their holes filled."""
    out = np.zeros(frame.ref.shape, bool)
    r, c = _inside(frame, points).T
    if not len(r):
        return out
    # within the points' box and a margin of 2 px: the closing reaches 1 px
    # beyond them, and the background around the box reaches the border
    box = tuple(slice(max(int(x.min()) - 2, 0), min(int(x.max()) + 3, n)) for x, n in zip((r, c), out.shape))
    mask = np.zeros(out[box].shape, np.uint8)
    mask[r - box[0].start, c - box[1].start] = 1
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    out[box] = ndimage.binary_fill_holes(mask)
    return out


def _opened(mask):
    """``mask`` (bool) opened by a 3 x 3 square: without its pieces and rims
    thinner than 3 px, whether or not they touch a thicker part."""
    return ndimage.binary_opening(mask, np.ones((3, 3), bool))


def rims_along(candidates, explained, min_area):
    """The pixels of ``candidates`` (bool) in rims thinner than 3 px
    (:func:`_opened`) that touch (8-neighbours) an ``explained`` region of at
    least ``min_area`` pixels: a structure's edge, blurred and sampled
    differently by the capture's optics, left beside a thicker candidate (a
    new object against it) in a component no one depth explains.  Smaller
    explained regions are chance (a few pixels inside a uniform new object)
    and make no rim."""
    out = np.zeros_like(candidates)
    touch = candidates & _dilate(explained, cv2.MORPH_RECT, 1)
    if not touch.any():
        return out
    # within the touching pixels' box and a margin that holds every pixel the
    # opening (2 px) and the size of a region reaching them (min_area px) look at
    rows, cols = np.nonzero(touch.any(axis=1))[0], np.nonzero(touch.any(axis=0))[0]
    m = int(min_area) + 2
    box = (slice(max(rows[0] - m, 0), rows[-1] + m + 1), slice(max(cols[0] - m, 0), cols[-1] + m + 1))
    structures = large_components(explained[box], min_area)
    out[box] = touch[box] & ~_opened(candidates[box]) & _dilate(structures, cv2.MORPH_RECT, 1)
    return out


def _dilate(mask, shape, radius):
    """``mask`` (bool) dilated by a ``shape`` (cv2.MORPH_CROSS or MORPH_RECT)
    of half side ``radius``, nothing beyond its border."""
    kernel = cv2.getStructuringElement(shape, (2 * radius + 1, 2 * radius + 1))
    return cv2.dilate(mask.astype(np.uint8), kernel) > 0


def _hull(frame, points):
    """The reference-window pixels in the convex hull of ``points`` (n, 2) (row, col)."""
    mask = np.zeros(frame.ref.shape, np.uint8)
    xy = _inside(frame, points)[:, ::-1].copy()
    if len(xy):
        cv2.fillConvexPoly(mask, cv2.convexHull(xy), 1)
    return mask > 0


def _lookup(mask, points):
    """``mask`` at the nearest pixel of each of ``points`` (n, 2) (row, col);
    False outside it."""
    r, c = np.round(points).astype(int).T
    ok = (r >= 0) & (c >= 0) & (r < mask.shape[0]) & (c < mask.shape[1])
    hit = np.zeros(len(r), bool)
    hit[ok] = mask[r[ok], c[ok]]
    return hit


def _to_reference(carry, box, pixels, q):
    """Reference-window (row, col) of the window ``pixels`` (bool in ``box``)
    carried by each row's centroid pose at inverse depth ``q`` (a number, or
    one per pixel of ``pixels``, in their order)."""
    rows, cols = np.nonzero(pixels)
    rows = rows + box[0].start
    cols = cols + box[1].start
    poses = carry.reg.trajectory[rows].copy()
    p6 = full_poses(poses, carry.reg.axes)
    p6[:, :3] *= np.reshape(np.asarray(q, np.float64), (-1, 1))
    window_rows = rows + carry.dy
    hom = pose_homographies(p6, carry.camera, origin_yx=carry.origin, inverse=True)
    pts = hom @ np.stack([cols + carry.dx, window_rows, np.ones(len(rows))])[None].transpose(2, 1, 0)
    pts = pts[..., 0]
    return np.stack([pts[:, 1] / pts[:, 2], pts[:, 0] / pts[:, 2]], 1)


def _mark(out, frame, box, component, found, lambda_chi):
    """Per pixel: the component's pixels explained at the layer's depth are
    re-rendered there and join ``parallax``, with the ground it hid
    (disoccluded: no evidence, ``chi`` 0); the rest of the component (a new
    object on or against the layer) keeps the registration's ``chi``."""
    depth, rendered, explained, disoccluded, footprint, on_layer = found
    if footprint.any():
        if out.footprint is None:
            out.footprint = np.zeros(footprint.shape, np.int32)
        out.footprint[footprint] = len(out.components) + 1
    out.parallax[box] |= explained | disoccluded
    g = frame.dist[box]
    reg, chi = out.registered[box], out.chi[box]
    reg[explained] = rendered[explained]
    chi[explained] = optimal_chi(g[explained] - rendered[explained], lambda_chi=lambda_chi)
    chi[disoccluded & ~explained] = 0.0
    reg[on_layer] = rendered[on_layer]  # judged against the layer it lies on
    out.on_layer[box] |= on_layer
    chi[on_layer] = optimal_chi(g[on_layer] - rendered[on_layer], lambda_chi=lambda_chi)
    out.kept[box] |= component & ~explained & ~disoccluded
    rows, cols = np.nonzero(component)
    residual = (g - rendered)[explained]
    out.components.append({"row": float(rows.mean() + box[0].start), "col": float(cols.mean() + box[1].start),
                           "pixels": int((explained | disoccluded).sum()), "depth": float(depth),
                           "explained": float(explained.sum() / component.sum()),
                           "rmse": float(np.sqrt(np.mean(residual ** 2)))})
