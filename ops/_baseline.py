"""Baseline for comparison: one global homography by ECC (OpenCV), as most
registration tools do; no rolling shutter, no blur model."""

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["EccResult", "ecc_homography"]


@dataclass(frozen=True)
class EccResult:
    """The reference warped by the ECC homography (NaN outside) and the matrix."""

    registered: np.ndarray
    homography: np.ndarray


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
