"""Synthetic test pairs with known truth: trajectory, changes in both grids, gain.

A scene larger than the reference is drawn (:func:`ops.aerial_scene`); the
reference is its centre; new objects are pasted into a copy of the scene
(:func:`ops.paste_changes`), and the copy is seen by a moving camera through the
forward model (:func:`ops.render`).  The truth change mask in the distorted grid
is the pasted mask seen through the same camera, thresholded at one half.
"""

from dataclasses import dataclass

import numpy as np

from .._camera import POSE_AXES, Camera, pose_homographies
from .._errors import ParameterError
from .._forward import CameraPath, render
from ._layered import raise_structures, render_layered, with_roofs
from ._scene import aerial_scene, paste_changes

__all__ = ["MOTIONS", "SyntheticPair", "motion_path", "synthesize_pair"]

#: Motion types, mirroring the papers' experiments.  Amplitudes: px for tx, ty,
#: degrees for rotations; each axis is ``offset + amp * sin(2 pi (f t / T) + phase)``.
MOTIONS = {
    # supplement Fig. 15: non-uniform translation, tx in [-15, 15], ty in [0, 10] px
    "translation": {"tx": (0.0, 15.0), "ty": (5.0, 5.0)},
    # TPAMI: in-plane translations and rotation
    "inplane": {"tx": (0.0, 10.0), "ty": (4.0, 6.0), "rz": (0.0, 2.0)},
    # yaw: rotation about the camera's vertical axis bends straight lines
    "yaw": {"ry": (0.0, 1.5), "tx": (0.0, 3.0), "ty": (2.0, 2.0)},
    # pure rolling shutter wobble without rotation
    "wobble": {"tx": (0.0, 6.0), "ty": (0.0, 3.0)},
}


@dataclass(frozen=True)
class SyntheticPair:
    """A reference, its distorted capture and the truth.

    Attributes
    ----------
    reference, distorted : ndarray, shape (H, W), float32
    change_mask : ndarray of bool, shape (H, W)
        Truth in the distorted grid.
    change_mask_reference : ndarray of bool, shape (H, W)
        Truth in the reference grid.
    trajectory : ndarray, shape (H, 6)
        Per-row centroid pose over all axes of :data:`ops.POSE_AXES`.
    gain : ndarray, shape (H, W), float32
        Illumination gain of every captured pixel.
    valid : ndarray of bool, shape (H, W)
        Distorted pixels rendered from inside the scene.
    camera : Camera
    path : CameraPath
    parallax_mask : ndarray of bool, shape (H, W), or None
        With raised structures: where the capture sees a roof, or the ground
        a roof hid in the reference (parallax, not change).
    depths : tuple of float
        Relative depth of each raised structure.
    """

    reference: np.ndarray
    distorted: np.ndarray
    change_mask: np.ndarray
    change_mask_reference: np.ndarray
    trajectory: np.ndarray
    gain: np.ndarray
    valid: np.ndarray
    camera: Camera
    path: CameraPath
    parallax_mask: np.ndarray | None = None
    depths: tuple = ()


def motion_path(motion, *, duration, seed, scale=1.0):
    """A smooth random camera path of one of :data:`MOTIONS`.

    Parameters
    ----------
    motion : str
        Key of :data:`MOTIONS`.
    duration : float
        Time span to cover, in row periods.
    seed : int
    scale : float
        Multiplies every amplitude.

    Returns
    -------
    CameraPath
    """
    if motion not in MOTIONS:
        raise ParameterError(f"motion: expected one of {sorted(MOTIONS)}, got {motion!r}")
    rng = np.random.default_rng(seed)
    times = np.linspace(0.0, duration, max(int(duration // 2), 8))
    poses = np.zeros((times.size, 6))
    for axis, (offset, amp) in MOTIONS[motion].items():
        freq = rng.uniform(0.4, 0.9)
        phase = rng.uniform(0, 2 * np.pi)
        poses[:, POSE_AXES.index(axis)] = scale * (offset + amp * np.sin(2 * np.pi * freq * times / duration + phase))
    return CameraPath(times, poses)


def readout_path(height, exposure, *, phase=0.3, **axes):
    """A camera path over one readout of ``height`` rows.

    Parameters
    ----------
    height : int
        Rows of the capture.
    exposure : float
        Row exposure, in row periods: the path covers ``height + exposure + 1``
        row periods.
    phase : float
        Radians between the wobbles of successive pose axes.
    **axes : tuple of float
        Per axis of :data:`POSE_AXES` (px or degrees): ``(start, end)``, linear
        in time, or ``(start, end, amplitude)`` with a sine wobble of that
        amplitude (0.7 periods over the readout) on top.  Other axes are zero.

    Returns
    -------
    CameraPath
    """
    duration = height + exposure + 1.0
    t = np.linspace(0.0, duration, 64)
    poses = np.zeros((t.size, 6))
    for name, value in axes.items():
        k = POSE_AXES.index(name)
        poses[:, k] = value[0] + (value[1] - value[0]) * t / duration
        if len(value) > 2:
            poses[:, k] += value[2] * np.sin(2 * np.pi * 0.7 * t / duration + phase * k)
    return CameraPath(t, poses)


def _margin(path, camera, shape):
    """Pixels by which the path moves the frame's corners, at most."""
    h, w = shape
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], dtype=np.float64).T
    hom = pose_homographies(path.poses, camera, inverse=True)
    pts = hom @ corners
    pts = pts[:, :2] / pts[:, 2:3]
    return int(np.ceil(np.abs(pts - corners[None, :2]).max())) + 4


def synthesize_pair(shape=(256, 256), *, motion="inplane", shutter="rolling", exposure=None, gain=1.0,
                    changes=6, change_size=(14, 36), noise=0.0, scale=1.0, focal=None, seed=0, path=None,
                    scene=None, interpolation="bilinear", structures=0, depths=(0.4, 0.8)):
    """Make a reference and a distorted capture of it with known truth.

    Parameters
    ----------
    shape : tuple of int
        (H, W) of both images.
    motion : str
        Key of :data:`MOTIONS`.
    shutter : {"rolling", "global"}
    exposure : float, optional
        Row exposure in row periods; default ``H / 16`` (visible blur).  For a
        global shutter the whole frame is exposed for this long.
    gain : float or tuple of float
        Illumination gain of the capture against the reference; a pair
        ``(left, right)`` makes it vary linearly across the columns.
    changes : int
        Number of pasted objects.
    change_size : tuple of float
        Long side range of pasted objects, px.
    noise : float
        Standard deviation of Gaussian noise added to the capture, in [0, 1] units.
    scale : float
        Multiplies every motion amplitude.
    focal : float, optional
        Focal length in pixels (default 1.2 x the larger side).
    seed : int
    path : CameraPath, optional
        The camera path (time in row periods), instead of a random one of ``motion``.
    scene : ndarray, shape (Hs, Ws), optional
        The scene (intensities in [0, 1]; e.g. a real aerial photograph) instead of
        :func:`ops.aerial_scene`: the reference is its centre, and it must hold the
        frame plus the path's reach on every side.
    interpolation : {"bilinear", "cubic"}
        How the capture is rendered (:func:`ops.render`): "cubic" is independent of
        the solver's warp kernel, for accuracy measured out of sample.
    structures : int
        Raised structures (flat roofs, 20 to 44 px) nearer to the camera than the
        ground (:mod:`ops.synthetic._layered`), away from the changes: parallax, not change.
    depths : tuple of float
        Range of their relative depths (distance over the ground's).

    Returns
    -------
    SyntheticPair
    """
    height, width = int(shape[0]), int(shape[1])
    if height < 32 or width < 32:
        raise ParameterError(f"shape: expected at least 32 x 32, got {shape}")
    exposure = height / 16.0 if exposure is None else float(exposure)
    camera = Camera.for_shape(shape, focal=focal)
    # a global shutter sees a short piece of a path as slow as a rolling frame's
    duration = height + exposure + 1.0 if shutter == "rolling" else 4.0 * (exposure + 1.0)
    if path is None:
        path = motion_path(motion, duration=duration, seed=seed, scale=scale)
    margin = _margin(path, camera, shape)
    if scene is None:
        scene = aerial_scene((height + 2 * margin, width + 2 * margin), seed=seed)
        scene = (0.05 + 0.7 * scene).astype(np.float32)  # headroom for gains up to 1.3
    else:
        scene = np.asarray(scene, dtype=np.float32)
        top, left = (scene.shape[0] - height) // 2 - margin, (scene.shape[1] - width) // 2 - margin
        if min(top, left) < 0:
            raise ParameterError(f"scene: expected at least {height + 2 * margin} x {width + 2 * margin} pixels for "
                                 f"this frame and path, got {scene.shape[0]} x {scene.shape[1]}")
        scene = scene[top:top + height + 2 * margin, left:left + width + 2 * margin]
    origin = (margin, margin)
    changed, pasted = paste_changes(scene, count=changes, size_range=change_size, seed=seed + 1,
                                    margin=margin + 12)
    raised = raise_structures(scene, count=structures, depths=depths, size_range=(20, 44), seed=seed + 3,
                              margin=margin + 24, avoid=pasted) if structures else []
    reference = np.ascontiguousarray(with_roofs(scene, raised)[origin[0]:origin[0] + height,
                                                               origin[1]:origin[1] + width])
    kw = dict(shape=shape, camera=camera, shutter=shutter, row_delay=1.0, exposure=exposure, source_origin_yx=origin,
              interpolation=interpolation)
    gain_map = _gain_map(gain, shape)
    image, seen, parallax = render_layered(changed, raised, path, **kw)
    seen_image = image * gain_map
    truth = render(pasted.astype(np.float32), path, **kw)
    distorted = seen_image
    if noise > 0:
        distorted = distorted + np.random.default_rng(seed + 2).normal(0, noise, distorted.shape).astype(np.float32)
    mask_ref = np.ascontiguousarray(pasted[origin[0]:origin[0] + height, origin[1]:origin[1] + width])
    return SyntheticPair(reference, distorted.astype(np.float32), truth.image > 0.5, mask_ref, seen.centroid,
                         gain_map, seen.valid, camera, path, parallax if raised else None,
                         tuple(s.depth for s in raised))


def _gain_map(gain, shape):
    """Per-pixel gain (H, W) float32 of a scalar or a (left, right) pair."""
    values = np.atleast_1d(np.asarray(gain, dtype=np.float64))
    if values.size == 1:
        return np.full(shape, values[0], dtype=np.float32)
    if values.size != 2 or not (values > 0).all():
        raise ParameterError(f"gain: expected a positive number or a (left, right) pair, got {gain!r}")
    ramp = np.linspace(values[0], values[1], shape[1], dtype=np.float32)
    return np.broadcast_to(ramp, shape).copy()
