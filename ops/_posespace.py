"""Pose spaces ``N(c, b, s)``: grids of poses on named axes (METHOD.md section 3)."""

import functools
from dataclasses import dataclass

import numpy as np

from ._camera import POSE_AXES
from ._errors import ParameterError

__all__ = ["PoseSpace"]


@functools.lru_cache(maxsize=64)
def _offsets(counts):
    ranges = [np.arange(-(n // 2), n // 2 + 1) for n in counts]
    mesh = np.meshgrid(*ranges, indexing="ij")
    out = np.stack([m.ravel() for m in mesh], axis=-1)
    out.setflags(write=False)
    return out


@dataclass(frozen=True)
class PoseSpace:
    """The grid ``c - b, c - b + s, ..., c + b`` on each named axis.

    Centres are snapped to the lattice of multiples of ``step`` so that every row
    of an image (and every tile) works on one global lattice: weights of two rows
    can be compared and carried over by index.

    Parameters
    ----------
    axes : tuple of str
        Axis names from :data:`ops.POSE_AXES`.
    half_width : tuple of float
        ``b`` per axis, in the axis unit (px, 1 or degrees).
    step : tuple of float
        ``s`` per axis, in the axis unit.
    """

    axes: tuple
    half_width: tuple
    step: tuple

    def __post_init__(self):
        axes = tuple(self.axes)
        if not axes or any(a not in POSE_AXES for a in axes) or len(set(axes)) != len(axes):
            raise ParameterError(f"axes: expected distinct names from {POSE_AXES}, got {axes}")
        hw = tuple(float(v) for v in np.broadcast_to(self.half_width, len(axes)))
        st = tuple(float(v) for v in np.broadcast_to(self.step, len(axes)))
        for a, b, s in zip(axes, hw, st):
            if not s > 0 or b < 0:
                raise ParameterError(f"pose space axis {a}: expected step > 0 and half-width >= 0, got step={s}, half-width={b}")
        object.__setattr__(self, "axes", axes)
        object.__setattr__(self, "half_width", hw)
        object.__setattr__(self, "step", st)

    @property
    def counts(self):
        """Number of grid values per axis."""
        return tuple(2 * int(round(b / s)) + 1 for b, s in zip(self.half_width, self.step))

    @property
    def size(self):
        """Number of poses ``|S|``."""
        return int(np.prod(self.counts))

    def offsets(self):
        """Lattice offsets of the grid from its centre: int array (|S|, D)
        (shared and read-only: the same for every row)."""
        return _offsets(self.counts)

    def snap(self, center):
        """Lattice index (int array, shape (D,)) of the lattice point nearest ``center``."""
        center = np.asarray(center, dtype=np.float64)
        return np.round(center / np.asarray(self.step)).astype(np.int64)

    def lattice_poses(self, index):
        """Poses (float64, (..., D)) of integer lattice indices (..., D)."""
        return np.asarray(index, dtype=np.float64) * np.asarray(self.step)

    def grid(self, center):
        """Lattice indices (|S|, D) and poses (|S|, D) of ``N(snap(center), b, s)``."""
        index = self.snap(center)[None, :] + self.offsets()
        return index, self.lattice_poses(index)

    def widened(self, half_width):
        """The same axes and steps with another half-width."""
        return PoseSpace(self.axes, half_width, self.step)
