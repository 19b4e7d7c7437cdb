"""Camera model: 6-DoF poses to homographies about the principal point.

A pose moves image *content*: the scene point seen at reference pixel ``p``
appears at ``H p`` in the observed image, so an observed image is sampled as
``observed(x) = reference(H^-1 x)``.  Poses are vectors over the axes of
:data:`POSE_AXES`:

========  ======  =====================================================
axis      unit    meaning
========  ======  =====================================================
``tx``    px      content shift to the right (+x)
``ty``    px      content shift down (+y)
``s``     1       relative scale change (z translation), factor ``1 + s``
``rx``    deg     tilt, moves content at the centre towards +y
``ry``    deg     yaw of the camera, moves content at the centre towards +x
``rz``    deg     in-plane rotation, +x turns towards +y
========  ======  =====================================================

In centred coordinates ``q = p - c`` (``c`` the principal point of the *whole*
image) the homography is ``T(t) S(1 + s) K R K^-1`` with ``K = diag(f, f, 1)``
and ``R = Rz Ry Rx`` (METHOD.md section 1, a fronto-parallel plane).  A tile of a
large image uses the same poses: only the principal point moves into the tile's
own coordinates, ``H_tile = T(-origin) H T(origin)``.
"""

from dataclasses import dataclass

import numpy as np

from ._errors import ParameterError

__all__ = ["POSE_AXES", "AXIS_UNITS", "Camera", "pose_homographies", "full_poses"]

POSE_AXES = ("tx", "ty", "s", "rx", "ry", "rz")
AXIS_UNITS = {"tx": "px", "ty": "px", "s": "1", "rx": "deg", "ry": "deg", "rz": "deg"}
FOCAL_FACTOR = 1.2


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics of the whole image.

    Parameters
    ----------
    focal : float
        Focal length in pixels.
    center_xy : tuple of float
        Principal point ``(cx, cy)`` in pixels of the whole image.
    """

    focal: float
    center_xy: tuple

    @classmethod
    def for_shape(cls, shape, *, focal=None):
        """Camera of an image of ``shape`` (H, W): principal point at the image
        centre and, when ``focal`` is None, a focal length of 1.2 x the larger
        side (METHOD.md's default for unknown intrinsics)."""
        height, width = int(shape[0]), int(shape[1])
        if focal is None:
            focal = FOCAL_FACTOR * max(height, width)
        if not focal > 0:
            raise ParameterError(f"focal: expected a positive length in pixels, got {focal!r}")
        return cls(float(focal), ((width - 1) / 2.0, (height - 1) / 2.0))


def full_poses(poses, axes):
    """Expand poses over ``axes`` (shape (..., len(axes))) to all six axes of
    :data:`POSE_AXES` (shape (..., 6)), the missing ones set to zero."""
    poses = np.asarray(poses, dtype=np.float64)
    unknown = [a for a in axes if a not in POSE_AXES]
    if unknown or len(set(axes)) != len(axes):
        raise ParameterError(f"axes: expected distinct names from {POSE_AXES}, got {tuple(axes)}")
    if poses.shape[-1] != len(axes):
        raise ParameterError(f"poses: expected last dimension {len(axes)} for axes {tuple(axes)}, got shape {poses.shape}")
    out = np.zeros(poses.shape[:-1] + (6,))
    for i, a in enumerate(axes):
        out[..., POSE_AXES.index(a)] = poses[..., i]
    return out


def _rotations(rx, ry, rz):
    """Rotation matrices R = Rz Ry Rx, angles in radians, shape (..., 3, 3)."""
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    one, zero = np.ones_like(rx), np.zeros_like(rx)
    r_x = np.stack([one, zero, zero, zero, cx, sx, zero, -sx, cx], -1).reshape(rx.shape + (3, 3))
    r_y = np.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], -1).reshape(rx.shape + (3, 3))
    r_z = np.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one], -1).reshape(rx.shape + (3, 3))
    return r_z @ r_y @ r_x


def pose_homographies(poses, camera, *, axes=POSE_AXES, origin_yx=(0.0, 0.0), inverse=False):
    """Homographies of poses, in the pixel frame of a window at ``origin_yx``.

    Parameters
    ----------
    poses : array_like, shape (..., D)
        Poses over ``axes`` (px, 1 or degrees, see the module docstring).
    camera : Camera
        Intrinsics of the whole image.
    axes : sequence of str
        Names of the D pose axes.
    origin_yx : tuple of float
        Row and column of the window's top-left pixel in the whole image.
    inverse : bool
        Return ``H^-1`` (observed pixel -> reference pixel), the sampling map.

    Returns
    -------
    ndarray, shape (..., 3, 3), float64
    """
    p = full_poses(poses, axes)
    tx, ty, s, rx, ry, rz = np.moveaxis(p, -1, 0)
    rot = _rotations(*np.deg2rad([rx, ry, rz]))
    f = float(camera.focal)
    k = np.diag([f, f, 1.0])
    k_inv = np.diag([1.0 / f, 1.0 / f, 1.0])
    h = k @ rot @ k_inv
    scale = 1.0 + s
    h[..., :2, :] *= scale[..., None, None]
    h[..., 0, :] += tx[..., None] * h[..., 2, :]
    h[..., 1, :] += ty[..., None] * h[..., 2, :]
    cx = camera.center_xy[0] - origin_yx[1]
    cy = camera.center_xy[1] - origin_yx[0]
    shift = np.array([[1.0, 0, cx], [0, 1.0, cy], [0, 0, 1.0]])
    unshift = np.array([[1.0, 0, -cx], [0, 1.0, -cy], [0, 0, 1.0]])
    h = shift @ h @ unshift
    if inverse:
        h = np.linalg.inv(h)
    return h / h[..., 2:3, 2:3]
