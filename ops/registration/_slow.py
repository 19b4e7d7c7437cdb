"""The slow out-of-plane part of the camera path (METHOD.md section 7).

A yaw (ry) moves a row almost as tx does and a pitch (rx) almost as ty does;
what tells them apart is second order across the image (a yaw bends rows, a
pitch stretches them by an amount that changes sign at the principal point).
One row cannot see that, so the rows never search rx and ry: their slow part
is estimated first, on the whole window, and the rows solve the fast in-plane
part (tx, ty, rz) on a reference pre-warped by it (:class:`SlowPath`).

The estimate (:func:`estimate_slow`): a dense optical flow (OpenCV DIS) from
the capture to the reference, and a robust least-squares fit of the flow of
small rotations about the principal point, with the in-plane motion free per
band of rows and rx, ry smooth over the rows (a low-order polynomial of the
row).  It is kept only where it matters: when the displacement it adds beyond
the best in-plane fit reaches :data:`SLOW_MIN_PX` somewhere in the window.
"""

from dataclasses import dataclass

import numpy as np

from ._slowfit import _AXES, _NEGLIGIBLE, FIT_BAND, _Fit, _fit

__all__ = []

#: Flow vectors are sampled every this many pixels.
FIT_STRIDE = 6
#: The slow part is used when it moves some pixel of the window this far (px)
#: beyond the in-plane fit of the same flow.
SLOW_MIN_PX = 0.75
#: ... and eq. 13 on :data:`SLOW_BLOCKS` blocks of rows spread over the window
#: costs this much less with it (relative).
SLOW_EQ13_GAIN = 0.02
SLOW_BLOCKS = 4


@dataclass(frozen=True)
class SlowPath:
    """Slow rotations per capture row and the ty shift of each row's content.

    Attributes
    ----------
    rotation : ndarray, shape (H, 2), float64
        (rx, ry) in degrees for every row of the capture window.
    ty : ndarray, shape (H,), float64
        The in-plane ty (px) of each row, to find which capture row a
        pre-translation row of the pre-warped reference serves.
    """

    rotation: np.ndarray
    ty: np.ndarray

    def at_rows(self, rows, *, factor=1.0, offset=0.0):
        """This path (found on an image ``factor`` times coarser whose row ``j``
        covers rows from ``j * factor + offset``) at the rows ``rows`` of the
        finer image: rotations interpolated, ty scaled."""
        rows = np.asarray(rows, dtype=np.float64)
        coarse = (rows - offset - 0.5 * (factor - 1.0)) / factor
        index = np.arange(self.ty.shape[0], dtype=np.float64)
        rotation = np.stack([np.interp(coarse, index, self.rotation[:, q]) for q in (0, 1)], 1)
        return SlowPath(rotation, np.interp(coarse, index, self.ty) * factor)

    def pose6(self, rows):
        """Full poses (n, 6) of the slow part at capture rows ``rows`` (float ok)."""
        rows = np.atleast_1d(np.asarray(rows, dtype=np.float64))
        index = np.arange(self.rotation.shape[0], dtype=np.float64)
        out = np.zeros((rows.size, 6))
        out[:, 3] = np.interp(rows, index, self.rotation[:, 0])
        out[:, 4] = np.interp(rows, index, self.rotation[:, 1])
        return out

    def prewarp_pose6(self, rows):
        """Full poses (n, 6) for pre-translation rows ``rows``: the row ``r`` of a
        reference warped by rotation only serves capture row ``i = r + ty(i)``."""
        rows = np.atleast_1d(np.asarray(rows, dtype=np.float64))
        index = np.arange(self.ty.shape[0], dtype=np.float64)
        capture = rows
        for _ in range(3):
            capture = rows + np.interp(capture, index, self.ty)
        return self.pose6(capture)


def slow_from_trajectory(trajectory, axes):
    """The :class:`SlowPath` of a trajectory (H, D) over ``axes`` whose rx, ry
    columns are the slow part (None when it has none or they are all zero)."""
    columns = [axes.index(a) if a in axes else None for a in _AXES]
    if all(c is None for c in columns):
        return None
    rotation = np.stack([trajectory[:, c] if c is not None else np.zeros(len(trajectory)) for c in columns], 1)
    if not np.any(rotation):
        return None
    ty = trajectory[:, axes.index("ty")] if "ty" in axes else np.zeros(len(trajectory))
    return SlowPath(np.asarray(rotation, np.float64), np.asarray(ty, np.float64))


def estimate_slow(reference, distorted, valid, *, camera, reference_origin_yx, distorted_origin_yx, axes=_AXES,
                  limit=6.0, scale=1):
    """The slow rotations of a capture window against its reference.

    Parameters
    ----------
    reference : ndarray, shape (Hr, Wr), float32
        Reference window (NaN for nodata), at least as large as the capture's.
    distorted : ndarray, shape (H, W), float32
    valid : ndarray of bool, shape (H, W)
    camera : Camera
        Intrinsics of the whole image.
    reference_origin_yx, distorted_origin_yx : tuple of int
        The windows' positions in the whole image.
    axes : tuple of str
        The slow axes to estimate, a subset of ("rx", "ry").
    limit : float
        A fit reaching this rotation (deg) anywhere is not trusted.
    scale : int
        These images are ``scale`` times coarser than the capture the path is
        for (an overview): :data:`SLOW_MIN_PX` is in the capture's pixels.

    Returns
    -------
    SlowPath or None
        None when the slow part is negligible (see :data:`SLOW_MIN_PX`), the
        window too small or the fit not trustworthy.
    """
    height, width = distorted.shape
    if height < 2 * FIT_BAND or width < 64 or not axes:
        return None
    dy = int(distorted_origin_yx[0] - reference_origin_yx[0])
    dx = int(distorted_origin_yx[1] - reference_origin_yx[1])
    # the flow starts from the window's bulk shift, so that it only has to
    # find the few pixels around it (DIS loses displacements of ~100 px)
    shifts = _bulk_shifts(reference, distorted, valid, dy, dx)
    under = _sheared_crop(reference, dy, dx, shifts, width)
    cx = camera.center_xy[0] - distorted_origin_yx[1]
    cy = camera.center_xy[1] - distorted_origin_yx[0]
    ok = valid & np.isfinite(under)
    fit = None
    # a quick flow on the images at half size decides whether there is a slow
    # part; when there may be, a flow at full resolution measures it
    for reduce, finest, stride in ((2, 1, 2 * FIT_STRIDE), (1, 0, FIT_STRIDE)):
        flow = _flow(distorted, valid, under, finest, reduce)
        sample = None if flow is None else _sample(flow, ok, cx, cy, shifts, reduce, stride)
        if sample is None:
            return None
        # SLOW_MIN_PX is in the capture's pixels; the quick pass is lenient
        fit = _fit(sample, height, float(camera.focal), axes, limit, SLOW_MIN_PX / (scale * reduce),
                   alone=reduce == 1)
        if fit is _NEGLIGIBLE:
            return None
    if not isinstance(fit, _Fit):
        return None
    ref = np.where(np.isfinite(reference), reference, np.nan).astype(np.float32)
    if not _eq13_prefers(ref, distorted.astype(np.float32), valid, camera, reference_origin_yx,
                         distorted_origin_yx, fit):
        return None
    return SlowPath(fit.rotation, fit.ty)


#: Least normalised cross correlation of a band's gradients with the reference
#: for its bulk shift to count.
BULK_MIN_SCORE = 0.3


def _bulk_shifts(reference, distorted, valid, dy, dx, band=64, reach=24):
    """Whole-pixel (row, col) offsets (H, 2) of each capture row's content in
    the reference window beyond its nominal position (``dy``, ``dx``).

    Normalised cross correlation of smoothed x and y gradients (signed:
    repetitive texture such as city blocks fools their magnitude): first the
    capture's central part across the whole reference window, at a scale where
    the capture is about 128 px wide; then bands of ``band`` rows from the
    middle outwards at twice that scale, each sought within ``reach`` px of
    the band before it (a rolling shutter shears the window by tens of pixels
    over its rows, a few from one band to the next).  Matches below
    :data:`BULK_MIN_SCORE` (no texture) keep the offset of the band before;
    rows between band centres are interpolated."""
    height, width = distorted.shape
    coarse = max(1, int(width // 128))
    start = _match(reference, distorted, valid, coarse, (height // 8, height - height // 8), None, 0)
    expected = np.array((dy, dx) if start is None else start[:2], np.float64)  # capture -> window offset
    # the bands are sought near the start: only that part of the window is needed
    factor = max(1, int(width // 256))
    pad = 2 * reach + band + 2 * factor
    top = max(int(expected[0]) - pad, 0) // factor * factor
    left = max(int(expected[1]) - pad, 0) // factor * factor
    part = reference[top:int(expected[0]) + height + pad, left:int(expected[1]) + width + pad]
    ref_g = _gradients(np.nan_to_num(part), np.isfinite(part), factor)
    dist_g = _gradients(distorted, valid, factor)
    expected -= (top, left)
    dy, dx = dy - top, dx - left
    tops = list(range(0, max(height - band, 0) + 1, band))
    middle = len(tops) // 2
    found = {}
    for order in (tops[middle:], tops[:middle][::-1]):
        guess = expected.copy()
        for top in order:
            match = _match(ref_g, dist_g, None, factor, (top, min(top + band, height)), guess, reach)
            if match is not None:
                guess = np.array(match[:2], np.float64)
            found[top] = guess - (dy, dx)
    centres = np.array(sorted(found)) + 0.5 * band
    shifts = np.array([found[t] for t in sorted(found)])
    rows = np.arange(height)
    return np.stack([np.interp(rows, centres, shifts[:, q]) for q in (0, 1)], 1).round().astype(np.int64)


def _gradients(image, ok, factor):
    """Smoothed x and y derivatives of ``image`` reduced ``factor`` times."""
    import cv2

    image = np.where(ok, image, float(np.median(image[ok][::7])) if ok.any() else 0.0).astype(np.float32)
    if factor > 1:
        image = cv2.resize(image, (max(image.shape[1] // factor, 1), max(image.shape[0] // factor, 1)),
                           interpolation=cv2.INTER_AREA)
    image = cv2.GaussianBlur(image, (0, 0), 1.0)
    return cv2.Sobel(image, cv2.CV_32F, 1, 0), cv2.Sobel(image, cv2.CV_32F, 0, 1)


def _match(reference, distorted, valid, factor, rows, around, reach):
    """Offset (row, col, score) of the capture rows ``rows`` (their central
    three quarters of columns) in the reference window: capture pixel (r, c)
    shows reference window pixel (r + row, c + col).  ``around`` None: sought
    anywhere in the window (``reference`` and ``distorted`` are images);
    else within ``reach`` px of the offset ``around`` (they are gradients at
    ``factor``, :func:`_gradients`).  None below :data:`BULK_MIN_SCORE`."""
    import cv2

    if around is None:
        ref_g = _gradients(np.nan_to_num(reference), np.isfinite(reference), factor)
        dist_g = _gradients(distorted, valid, factor)
        offset = (0, 0)
    else:
        ref_g, dist_g = reference, distorted
    r0, r1 = rows[0] // factor, max(rows[1] // factor, rows[0] // factor + 2)
    cols = dist_g[0].shape[1]
    c0, c1 = cols // 8, cols - cols // 8
    templates = [g[r0:r1, c0:c1] for g in dist_g]
    if min(t.std() for t in templates) == 0:
        return None
    if around is not None:  # search only near the expected position
        top = int(round(r0 + around[0] / factor)) - reach // factor
        left = int(round(c0 + around[1] / factor)) - reach // factor
        bottom, right = top + (r1 - r0) + 2 * (reach // factor), left + (c1 - c0) + 2 * (reach // factor)
        top, left = max(top, 0), max(left, 0)
        bottom, right = min(bottom, ref_g[0].shape[0]), min(right, ref_g[0].shape[1])
        if bottom - top < r1 - r0 or right - left < c1 - c0:
            return None
        ref_g = [g[top:bottom, left:right] for g in ref_g]
        offset = (top, left)
    elif templates[0].shape[0] > ref_g[0].shape[0] or templates[0].shape[1] > ref_g[0].shape[1]:
        return None
    score = sum(cv2.matchTemplate(r, t, cv2.TM_CCOEFF_NORMED) for r, t in zip(ref_g, templates)) / 2
    _, peak, _, (x, y) = cv2.minMaxLoc(score)
    if not peak >= BULK_MIN_SCORE:
        return None
    return (y + offset[0] - r0) * factor, (x + offset[1] - c0) * factor, peak


def _sheared_crop(image, top, left, shifts, width):
    """Rows ``top + i + shifts[i, 0]`` of ``image``, columns from ``left +
    shifts[i, 1]`` (``width`` of them), NaN beyond its edges."""
    height = shifts.shape[0]
    out = np.full((height, width), np.nan, dtype=np.float32)
    for i in range(height):
        r = top + i + shifts[i, 0]
        if 0 <= r < image.shape[0]:
            c = left + shifts[i, 1]
            c0, c1 = max(c, 0), min(c + width, image.shape[1])
            if c1 > c0:
                out[i, c0 - c:c1 - c] = image[r, c0:c1]
    return out


def _flow(distorted, valid, under, finest, scale=1):
    """DIS optical flow from the capture to the reference under it,
    ``reference(x + flow(x)) ~ capture(x)``, of both images reduced ``scale``
    times, refined down to pyramid level ``finest`` (0: that resolution):
    (H // scale, W // scale, 2) in full-resolution pixels, and where flow can
    be measured there (:func:`_textured`); None without texture."""
    import cv2

    def prep(image, ok):
        fill = float(np.median(image[ok][::7])) if ok.any() else 0.0
        image = np.where(ok, image, fill).astype(np.float32)
        if scale > 1:
            image = cv2.resize(image, (image.shape[1] // scale, image.shape[0] // scale),
                               interpolation=cv2.INTER_AREA)
        image = cv2.GaussianBlur(image, (0, 0), 1.0)
        lo, hi = np.percentile(image[::3, ::3], [0.5, 99.5])
        if not hi > lo:
            return None
        return np.clip((image - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)

    a, b = prep(distorted, valid), prep(np.nan_to_num(under), np.isfinite(under))
    if a is None or b is None:
        return None
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    dis.setFinestScale(int(finest))
    flow = dis.calc(a, b, None) * np.float32(scale)
    return flow, _textured(a)


def _textured(image, block=7, fraction=0.05):
    """Pixels where flow can be measured: the smaller eigenvalue of the local
    structure tensor (``block`` px) at least ``fraction`` of its 95th
    percentile over the window (flat water, snow or roofs give flow noise)."""
    import cv2

    eig = cv2.cornerMinEigenVal(image, block)
    return eig >= fraction * max(float(np.percentile(eig[::3, ::3], 95)), 1e-12)


def _sample(flow, ok, cx, cy, shifts, scale=1, stride=FIT_STRIDE):
    """Flow vectors (plus the per-row bulk ``shifts`` (H, 2) they started from)
    on a grid of every ``stride`` capture pixels (the flow's grid is ``scale``
    times coarser than the capture's) where both images are valid and flow can
    be measured: (rows, x, y centred on the principal point, forward u, v)."""
    flow, textured = flow
    s = max(stride // scale, 2)
    small_rows, small_cols = np.mgrid[s // 2:flow.shape[0]:s, s // 2:flow.shape[1]:s]
    rows, cols = small_rows * scale + scale // 2, small_cols * scale + scale // 2
    keep = ok[rows, cols] & textured[small_rows, small_cols]
    if keep.sum() < 256:
        return None
    small_rows, small_cols, rows, cols = small_rows[keep], small_cols[keep], rows[keep], cols[keep]
    # the flow maps capture to reference: the content moved by about its negative
    u = -(flow[small_rows, small_cols, 0].astype(np.float64) + shifts[rows, 1])
    v = -(flow[small_rows, small_cols, 1].astype(np.float64) + shifts[rows, 0])
    return rows, cols - cx, rows - cy, u, v


def _eq13_prefers(reference, distorted, valid, camera, reference_origin_yx, distorted_origin_yx, fit):
    """Whether eq. 13 prefers the slow path: blocks of rows spread over the
    window are solved jointly (as the start block is) around the fitted
    in-plane motion, on the reference pre-warped by the slow path and on the
    reference alone; the slow path wins when its summed cost per pixel is
    lower by :data:`SLOW_EQ13_GAIN`."""
    from ._params import RegistrationParams
    from ._rowproblem import _RowProblem, _Solver
    from ._start import _refine_start

    params = RegistrationParams(slow_axes=()).resolved(camera)
    height = distorted.shape[0]
    centres = [int((k + 0.5) * height / SLOW_BLOCKS) for k in range(SLOW_BLOCKS)]
    half = params.block_rows // 2
    steps = np.asarray(params.step)
    cost = []
    for slow, inplane in ((SlowPath(fit.rotation, fit.ty), fit.inplane), (None, fit.inplane_alone)):
        margin = int(np.ceil(np.abs(inplane[:, :2]).max() + 4 * max(params.half_width[:2]))) + 8
        problem = _RowProblem(reference, distorted, valid, camera, reference_origin_yx, distorted_origin_yx,
                              params.axes, params.step, margin, 2 * half + 12, slow)
        solver = _Solver(problem, params)
        total = 0.0
        for r in centres:
            block = np.arange(max(r - half, 0), min(r + half + 1, height))
            total += _refine_start(solver, inplane[r], block, steps, iterations=1)[2]
        cost.append(total)
    return bool(cost[0] < (1.0 - SLOW_EQ13_GAIN) * cost[1])
