"""The depth-layer step (METHOD.md section 3, item 8; the paper's Algorithm 1).

The registration explains the ground.  Anything nearer to the camera than the
ground (a roof, a tree crown) moves more under the camera's translations and
is left in ``chi``.  Each candidate change component is tested against depth
layers: the rows' weights stay fixed, the translations of their poses (tx, ty
and s) are divided by a relative depth ``rho`` (rotations stay), the
reference is warped and blurred again at that depth inside the component, and
its pixels whose residual falls below the change threshold are *explained*.

A component is **parallax, not change** when at its best depth (the one that
explains most of its pixels):

- at least :data:`MIN_EXPLAINED` of its pixels are explained, and
- explained pixels plus the *disoccluded* ones, pixels whose ground point
  lies under the layer in the reference (the reference cannot show what the
  roof hid), make up at least :data:`MIN_COVERED` of it.

New objects are explained at no depth (the reference has nothing like them
there); the depth ``rho = 1`` is the ground itself and is not tried.
"""

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from .._camera import full_poses, pose_homographies
from .._oracle import optimal_chi
from .._warp import _build_row

__all__ = ["LayerParams", "LayerResult", "depth_layers"]

MIN_EXPLAINED = 0.25
MIN_COVERED = 0.6


@dataclass(frozen=True)
class LayerParams:
    """Tuning of :func:`depth_layers`.

    Attributes
    ----------
    depths : tuple of float
        Relative depths swept, evenly spaced (distance over the ground's;
        below 1 is nearer): every fourth first, then those within four steps
        of the best of them.
    min_area : int
        Smallest component tested, pixels.
    """

    depths: tuple = tuple(round(0.1 + 0.05 * k, 2) for k in range(29) if abs(0.1 + 0.05 * k - 1.0) > 1e-6)
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
    components : list of dict
        Per layer: ``row``, ``col`` (centroid, window pixels), ``pixels``,
        ``depth``, ``explained`` (fraction) and ``rmse`` (intensity units, over
        its explained pixels).
    """

    parallax: np.ndarray
    registered: np.ndarray
    chi: np.ndarray
    components: list = field(default_factory=list)


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
    candidates = (np.abs(registration.chi) > threshold) & registration.valid
    labels, count = ndimage.label(ndimage.binary_dilation(candidates), structure=np.ones((3, 3)))
    if count == 0:
        return out
    frame = _Frame(registration, reference, distorted, camera, reference_origin_yx, distorted_origin_yx)
    for index, box in enumerate(ndimage.find_objects(labels), start=1):
        component = (labels[box] == index) & candidates[box]
        if component.sum() < params.min_area:
            continue
        found = _test_component(frame, box, component, params.depths, threshold)
        if found is not None:
            _mark(out, frame, box, component, found, lambda_chi)
    return out


class _Frame:
    """What re-rendering a window at a depth needs: the reference window in its
    frame, the rows' weights and slow part, the camera."""

    def __init__(self, registration, reference, distorted, camera, reference_origin_yx, distorted_origin_yx):
        self.reg, self.ref, self.dist = registration, np.asarray(reference, np.float32), distorted
        self.focal = float(camera.focal)
        self.cx = camera.center_xy[0] - reference_origin_yx[1]
        self.cy = camera.center_xy[1] - reference_origin_yx[0]
        self.dy = int(distorted_origin_yx[0] - reference_origin_yx[0])
        self.dx = int(distorted_origin_yx[1] - reference_origin_yx[1])
        some = next((p for p, _ in registration.row_weights.values()), np.zeros((0, 1)))
        self.inplane = registration.axes[:some.shape[1]]  # the rows' own axes; the slow ones follow
        self.camera, self.origin = camera, reference_origin_yx

    def poses6(self, row, poses, depth):
        """Full poses (n, 6) of a row's weighted poses at ``depth``."""
        p6 = full_poses(poses, self.inplane)
        p6[:, :3] /= depth
        if self.reg.slow is not None:
            p6 = p6 + self.reg.slow.pose6(row)
        return p6

    def render(self, rows, cols, depth):
        """The registered window ``rows`` x ``cols`` re-rendered at ``depth``:
        float32, NaN where a row has no weights or a pose leaves the reference."""
        out = np.full((rows.stop - rows.start, cols.stop - cols.start), np.nan, np.float32)
        gain = 1.0 if self.reg.column_gain is None else self.reg.column_gain[cols]
        for q, row in enumerate(range(rows.start, rows.stop)):
            weights = self.reg.row_weights.get(row)
            if weights is None or not len(weights[1]):
                continue
            poses, w = weights
            buf = np.empty((len(w), out.shape[1]), np.float32)
            valid = _build_row(self.ref, float(row + self.dy), float(cols.start + self.dx),
                               self.poses6(row, poses, depth), self.focal, self.cx, self.cy, buf)
            out[q] = np.where(valid != 0, (w @ buf) * gain, np.nan)
        return out


def _test_component(frame, box, component, depths, threshold):
    """(depth, rendered window, explained, disoccluded) of the depth that
    makes the component parallax, or None."""
    g = frame.dist[box]
    pixels = int(component.sum())
    tried = {}

    def explain(depth):
        if depth not in tried:
            rendered = frame.render(box[0], box[1], depth)
            explained = component & (np.abs(g - rendered) < threshold)
            tried[depth] = (int(explained.sum()), depth, rendered, explained)
        return tried[depth]

    # every fourth depth first, then the depths around the best of them
    coarse = max((explain(d) for d in depths[::4]), key=lambda t: t[0])
    if coarse[0] < 0.5 * MIN_EXPLAINED * pixels:
        return None  # nothing like a layer: a change
    step = 4 * (depths[1] - depths[0]) if len(depths) > 1 else 0.0
    near = [d for d in depths if abs(d - coarse[1]) <= step + 1e-9]
    count, depth, rendered, explained = max((explain(d) for d in near), key=lambda t: t[0])
    if count < MIN_EXPLAINED * pixels:
        return None
    disoccluded = _disoccluded(frame, box, component & ~explained, explained, depth)
    if count + disoccluded.sum() < MIN_COVERED * pixels:
        return None
    return depth, rendered, explained, disoccluded


def _disoccluded(frame, box, pixels, explained, depth):
    """Which of ``pixels`` (window box) see, on the ground, a point that the
    layer at ``depth`` (its footprint: where the ``explained`` pixels come
    from) covered in the reference."""
    if not pixels.any():
        return pixels
    footprint = _to_reference(frame, box, explained, depth)
    shape = frame.ref.shape
    mask = np.zeros(shape, np.uint8)
    inside = (footprint[:, 0] >= 0) & (footprint[:, 1] >= 0) & (footprint[:, 0] < shape[0] - 1) & \
             (footprint[:, 1] < shape[1] - 1)
    r, c = np.round(footprint[inside]).astype(int).T
    mask[r, c] = 1
    mask = cv2.dilate(mask, np.ones((5, 5), np.uint8)) > 0
    ground = _to_reference(frame, box, pixels, 1.0)
    r, c = np.round(ground).astype(int).T
    ok = (r >= 0) & (c >= 0) & (r < shape[0]) & (c < shape[1])
    hit = np.zeros(len(r), bool)
    hit[ok] = mask[r[ok], c[ok]]
    out = np.zeros_like(pixels)
    out[pixels] = hit
    return out


def _to_reference(frame, box, pixels, depth):
    """Reference-window (row, col) of the window ``pixels`` (bool in ``box``)
    carried by each row's centroid pose at ``depth``."""
    rows, cols = np.nonzero(pixels)
    rows = rows + box[0].start
    cols = cols + box[1].start
    poses = frame.reg.trajectory[rows].copy()
    p6 = full_poses(poses, frame.reg.axes)
    p6[:, :3] /= depth
    window_rows = rows + frame.dy
    hom = pose_homographies(p6, frame.camera, origin_yx=frame.origin, inverse=True)
    pts = hom @ np.stack([cols + frame.dx, window_rows, np.ones(len(rows))])[None].transpose(2, 1, 0)
    pts = pts[..., 0]
    return np.stack([pts[:, 1] / pts[:, 2], pts[:, 0] / pts[:, 2]], 1)


def _mark(out, frame, box, component, found, lambda_chi):
    depth, rendered, explained, disoccluded = found
    out.parallax[box] |= component
    g = frame.dist[box]
    reg, chi = out.registered[box], out.chi[box]
    reg[explained] = rendered[explained]
    chi[explained] = optimal_chi(g[explained] - rendered[explained], lambda_chi=lambda_chi)
    chi[component & ~explained] = 0.0
    rows, cols = np.nonzero(component)
    residual = (g - rendered)[explained]
    out.components.append({"row": float(rows.mean() + box[0].start), "col": float(cols.mean() + box[1].start),
                           "pixels": int(component.sum()), "depth": float(depth),
                           "explained": float(explained.sum() / component.sum()),
                           "rmse": float(np.sqrt(np.mean(residual ** 2)))})
