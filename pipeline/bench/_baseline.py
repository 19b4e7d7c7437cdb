"""Baselines for comparison, what a user would pick instead: one global
homography by ECC or by ORB features (OpenCV), as most registration tools do,
and dense optical flow (OpenCV DIS); no rolling-shutter or blur model.

A baseline is timed on as many cores as rsmb is given (:func:`opencv_threads`):
the ``rsmb`` command's process runs OpenCV on one thread (its tiles use the
cores), which would leave a parallel baseline such as DIS a single core.
"""

import contextlib
import os
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["EccResult", "ecc_homography", "orb_homography", "dis_flow", "opencv_threads"]


@contextlib.contextmanager
def opencv_threads(workers=None):
    """OpenCV on ``workers`` threads (default: every core) inside the block,
    which is given that count; its thread count as it was after.  The count
    is the process's: call it only while no rsmb run is under way in this
    process (its tasks set OpenCV to one thread and restore it,
    :mod:`pipeline._scheduler`)."""
    before, threads = cv2.getNumThreads(), int(workers or os.cpu_count() or 1)
    cv2.setNumThreads(threads)
    try:
        yield threads
    finally:
        cv2.setNumThreads(before)


@dataclass(frozen=True)
class EccResult:
    """The reference warped by a global homography (NaN outside) and the
    matrix, which maps a pixel (x, y, 1) of the distorted image to the
    reference (None when no homography was found)."""

    registered: np.ndarray
    homography: np.ndarray | None


def ecc_homography(reference, distorted, *, iterations=200, eps=1e-6, smoothing=5):
    """Register ``reference`` onto ``distorted`` with one homography (ECC).

    Parameters
    ----------
    reference, distorted : ndarray, shape (H, W), float32 in [0, 1]

    Returns
    -------
    EccResult
        ``registered`` has the shape of ``distorted``.
    """
    ref = np.nan_to_num(np.asarray(reference, dtype=np.float32))
    dist = np.nan_to_num(np.asarray(distorted, dtype=np.float32))
    warp = np.eye(3, dtype=np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, int(iterations), float(eps))
    _, warp = cv2.findTransformECC(dist, ref, warp, cv2.MOTION_HOMOGRAPHY, criteria, None, int(smoothing))
    registered = cv2.warpPerspective(ref, warp, (dist.shape[1], dist.shape[0]),
                                     flags=cv2.INTER_LINEAR + cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT,
                                     borderValue=float("nan"))
    return EccResult(registered, warp.astype(np.float64))


def orb_homography(reference, distorted, *, features=4000, ransac_px=2.0):
    """Register ``reference`` onto ``distorted`` with one homography from ORB
    feature matches (Lowe's ratio test) and MAGSAC++ (OpenCV), as
    feature-based tools do.

    Returns
    -------
    EccResult
        The warped reference (NaN outside, or everywhere when too few matches)
        and the matrix (None then).
    """
    ref8, dist8 = (_as_uint8(a) for a in (reference, distorted))
    orb = cv2.ORB_create(int(features))
    kr, dr = orb.detectAndCompute(ref8, None)
    kd, dd = orb.detectAndCompute(dist8, None)
    pairs = [] if dr is None or dd is None or len(dr) < 2 else \
        cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(dd, dr, k=2)
    matches = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.75 * p[1].distance]  # Lowe's ratio test
    if len(matches) < 8:
        return EccResult(np.full(np.shape(distorted), np.nan, np.float32), None)
    src = np.float32([kd[m.queryIdx].pt for m in matches])
    dst = np.float32([kr[m.trainIdx].pt for m in matches])
    hom, _ = cv2.findHomography(src, dst, cv2.USAC_MAGSAC, float(ransac_px))
    if hom is None:
        return EccResult(np.full(np.shape(distorted), np.nan, np.float32), None)
    ref = np.nan_to_num(np.asarray(reference, dtype=np.float32))
    registered = cv2.warpPerspective(ref, hom, (distorted.shape[1], distorted.shape[0]),
                                     flags=cv2.INTER_LINEAR + cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT,
                                     borderValue=float("nan"))
    return EccResult(registered, hom)


def dis_flow(reference, distorted):
    """Register ``reference`` onto ``distorted`` by dense optical flow (OpenCV
    DIS, medium preset): a free displacement per pixel, no camera model.

    Returns
    -------
    ndarray, shape (H, W), float32
        The reference sampled along the flow (NaN outside).
    """
    ref = np.nan_to_num(np.asarray(reference, dtype=np.float32))
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow = dis.calc(_as_uint8(distorted), _as_uint8(reference), None)  # distorted pixel -> reference offset
    h, w = flow.shape[:2]
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(ref, cols + flow[..., 0], rows + flow[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=float("nan"))


def _as_uint8(image):
    return np.clip(np.nan_to_num(np.asarray(image, dtype=np.float32)) * 255.0 + 0.5, 0, 255).astype(np.uint8)
