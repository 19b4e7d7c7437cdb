"""The RSMB forward model: render what a moving CMOS camera sees (METHOD.md section 1).

Time is measured in row periods: row ``i`` of a rolling-shutter capture starts
its exposure at ``t = i * row_delay`` and integrates the scene, warped by the
camera pose of each instant, for ``exposure`` time units.  ``row_delay = 1`` and
``exposure = 0`` is a pure rolling shutter (RS); ``row_delay = 0`` a global
shutter (GS, or GSMB with ``exposure > 0``); both non-zero is RSMB.
"""

from dataclasses import dataclass

import numpy as np

from ._camera import Camera
from ._errors import ParameterError
from ._warp import _remap_rows

__all__ = ["CameraPath", "RenderResult", "render"]

SHUTTERS = ("rolling", "global")
INTERPOLATIONS = ("bilinear", "cubic")
#: Sub-pixel offsets of the cubic renderer's 2 x 2 area samples.
_AREA_OFFSETS = (-0.25, 0.25)


@dataclass(frozen=True)
class CameraPath:
    """A camera path p(t), linear between knots.

    Parameters
    ----------
    times : ndarray, shape (T,)
        Increasing knot times in row periods.
    poses : ndarray, shape (T, 6)
        Poses over all axes of :data:`ops.POSE_AXES` at the knots.
    """

    times: np.ndarray
    poses: np.ndarray

    def __post_init__(self):
        times = np.asarray(self.times, dtype=np.float64)
        poses = np.asarray(self.poses, dtype=np.float64)
        if times.ndim != 1 or poses.shape != (times.size, 6) or np.any(np.diff(times) <= 0):
            raise ParameterError(f"CameraPath: expected increasing times (T,) and poses (T, 6), got {times.shape} and {poses.shape}")
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "poses", poses)

    def __call__(self, t):
        """Poses (..., 6) at times ``t`` (...,)."""
        t = np.asarray(t, dtype=np.float64)
        out = np.stack([np.interp(t.ravel(), self.times, self.poses[:, a]) for a in range(6)], -1)
        return out.reshape(t.shape + (6,))


@dataclass(frozen=True)
class RenderResult:
    """A rendered capture and its truth.

    Attributes
    ----------
    image : ndarray, shape (H, W), float32
    centroid : ndarray, shape (H, 6)
        Mean pose of each row's exposure (the trajectory the method estimates).
    valid : ndarray, shape (H, W), bool
        Pixels whose every sample fell inside the source.
    """

    image: np.ndarray
    centroid: np.ndarray
    valid: np.ndarray


def _exposure_times(shape, shutter, row_delay, exposure, samples):
    rows = np.arange(shape[0], dtype=np.float64)
    start = rows * row_delay if shutter == "rolling" else np.zeros_like(rows)
    frac = (np.arange(samples) + 0.5) / samples if exposure > 0 else np.zeros(1)
    return start[:, None] + exposure * frac[None, :]


def render(source, path, *, shape, camera=None, shutter="rolling", row_delay=1.0, exposure=0.0,
           samples=24, source_origin_yx=(0, 0), gain=1.0, interpolation="bilinear"):
    """Render a capture of ``source`` seen along ``path``.

    Parameters
    ----------
    source : ndarray, shape (Hs, Ws), float32
        Scene intensities; may extend beyond the captured frame.
    path : CameraPath
        Camera path in the captured frame's pose coordinates.
    shape : tuple of int
        (H, W) of the captured frame.
    camera : Camera, optional
        Intrinsics of the frame, default ``Camera.for_shape(shape)``.
    shutter : {"rolling", "global"}
    row_delay : float
        Start-time step between rows (rolling shutter), in the path's time unit.
    exposure : float
        Exposure duration of each row; 0 means no motion blur.
    samples : int
        Sub-exposure samples that approximate the integral.
    source_origin_yx : tuple of int
        Position of the frame's pixel (0, 0) in ``source``.
    gain : float
        Global illumination gain applied to the rendered intensities.
    interpolation : {"bilinear", "cubic"}
        "bilinear" samples the source with the registration's own warp kernel
        (:mod:`ops._warp`); "cubic" is an independent renderer for measuring
        accuracy out of sample: OpenCV's bicubic remapping, each pixel the mean
        of 2 x 2 sub-pixel samples (its area), never the solver's kernel.

    Returns
    -------
    RenderResult
    """
    if shutter not in SHUTTERS:
        raise ParameterError(f"shutter: expected one of {SHUTTERS}, got {shutter!r}")
    if exposure < 0 or row_delay < 0:
        raise ParameterError(f"exposure and row_delay: expected >= 0, got {exposure}, {row_delay}")
    if interpolation not in INTERPOLATIONS:
        raise ParameterError(f"interpolation: expected one of {INTERPOLATIONS}, got {interpolation!r}")
    camera = camera or Camera.for_shape(shape)
    times = _exposure_times(shape, shutter, row_delay, exposure, int(samples))
    poses = path(times)  # (H, S, 6)
    src = np.ascontiguousarray(source, dtype=np.float32)
    if interpolation == "cubic":
        image, valid = _render_cubic(src, poses, camera, shape, source_origin_yx)
        return RenderResult((image * np.float32(gain)).astype(np.float32), poses.mean(axis=1), valid)
    image, valid = _remap_rows(src, poses, float(camera.focal), camera.center_xy[0] + source_origin_yx[1],
                               camera.center_xy[1] + source_origin_yx[0], int(shape[1]),
                               float(source_origin_yx[0]), float(source_origin_yx[1]))
    return RenderResult((image * np.float32(gain)).astype(np.float32), poses.mean(axis=1), valid.astype(bool))


def _render_cubic(src, poses, camera, shape, origin_yx):
    """Mean over exposure samples and 2 x 2 sub-pixel positions of the source
    remapped bicubically (OpenCV) by each row's pose: (image (H, W) float32,
    valid (H, W) bool)."""
    import cv2

    from ._camera import pose_homographies

    height, width = int(shape[0]), int(shape[1])
    acc = np.zeros((height, width), np.float64)
    valid = np.ones((height, width), bool)
    inside = np.isfinite(src)
    filled = np.where(inside, src, 0.0).astype(np.float32)
    hs, ws = src.shape
    count = 0
    for s in range(poses.shape[1]):
        inv = pose_homographies(poses[:, s], camera, inverse=True)  # (H, 3, 3), frame pixels
        for dy in _AREA_OFFSETS:
            for dx in _AREA_OFFSETS:
                x = np.arange(width, dtype=np.float64)[None, :] + dx
                y = np.arange(height, dtype=np.float64)[:, None] + dy
                den = inv[:, 2, 0, None] * x + inv[:, 2, 1, None] * y + inv[:, 2, 2, None]
                u = (inv[:, 0, 0, None] * x + inv[:, 0, 1, None] * y + inv[:, 0, 2, None]) / den + origin_yx[1]
                v = (inv[:, 1, 0, None] * x + inv[:, 1, 1, None] * y + inv[:, 1, 2, None]) / den + origin_yx[0]
                mx, my = u.astype(np.float32), v.astype(np.float32)
                acc += cv2.remap(filled, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
                valid &= (u >= 1) & (v >= 1) & (u <= ws - 3) & (v <= hs - 3)
                if not inside.all():
                    hit = cv2.remap(inside.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
                    valid &= hit > 0.999
                count += 1
    return (acc / count).astype(np.float32), valid
