"""Parameters of the registration: the pose axes, the row neighbourhood
``N(c, b, s)``, the wide start search, the solver and eq. 13's weights."""

import dataclasses
from dataclasses import dataclass

import numpy as np

from .._errors import ParameterError
from .._posespace import PoseSpace
from ._rowsolve import MAX_ADD, MAX_OUTER, TOL

__all__ = ["RegistrationParams", "SEARCH", "auto_step"]

#: Largest motion the wide initial search covers by default, per axis (+-, units
#: of :data:`ops.AXIS_UNITS`); ``RegistrationParams(search=None)`` takes it for its axes.
SEARCH = {"tx": 20.0, "ty": 20.0, "s": 0.0, "rx": 0.0, "ry": 0.0, "rz": 3.0}


@dataclass(frozen=True)
class RegistrationParams:
    """Tuning of :func:`register`; units are those of :data:`ops.AXIS_UNITS`.

    Attributes
    ----------
    axes : tuple of str
        Pose axes searched.
    half_width, step : tuple of float or None
        Row neighbourhood ``N(c, b, s)`` around the neighbour's centroid.  None
        means automatic: a step moves the farthest pixel by about one pixel
        (:func:`auto_step`) and the half-width is three steps, so tx, ty
        N(c, 3, 1) px as in the paper, and rz steps that shrink as images grow
        (the paper's rz N(c, 2, 0.5) deg suits its 256 x 384 images only).
    search : tuple of float or None
        Largest motion the wide initial search covers, per axis (+-); None:
        :data:`SEARCH` of each axis.
    shutter : {"rolling", "global"}
        "global" solves one weight vector for every row.
    solver : {"fast", "exact"}
        The active-set row solver, or the exact cvxpy formulation of eq. 13
        (the oracle; seconds per row).
    lambda_w, lambda_chi : float
        Weights of ``||w||_1`` and ``||chi||_1`` in eq. 13, intensities in [0, 1].
        ``lambda_chi / 2`` is the residual above which a pixel counts as change.
    block_rows : int
        Rows solved jointly to start the trajectory (one row alone is ambiguous).
    homogeneous : float
        A row whose mean absolute horizontal gradient is below this fraction of
        the median row's is homogeneous (its centroid is interpolated).
    adapt : bool
        Widen the row neighbourhood to the blur extent found in the start block.
    tol : float
        Relative KKT tolerance of the row solver.
    max_outer, max_add : int
        Row solver limits: outer iterations, poses added to the working set per
        iteration.
    slow_axes : tuple of str
        Out-of-plane rotations estimated as a slow part of the path on the whole
        window before the rows (:mod:`ops.registration._slow`), a subset of ("rx", "ry");
        axes also searched per row (in ``axes``) are left out.  Empty: none.
    slow_search : float
        Largest slow rotation (deg) the tile halo makes room for; a fit beyond
        twice this is not trusted.
    gain_slope : bool
        Also fit a linear illumination slope along the rows of the window
        (``1 + b (x - x_c)``, robustly, changes excluded): ``||w_i||_1`` gives each
        row its own gain, but a gain that varies across a row (vignetting, a
        slow illumination gradient over a wide-area mosaic) is otherwise left in
        the residual and read as change.  A local illumination term in the
        spirit of the authors' later work on local variations.
    """

    axes: tuple = ("tx", "ty", "rz")
    half_width: tuple = (None,)
    step: tuple = (None,)
    search: tuple | None = None
    shutter: str = "rolling"
    solver: str = "fast"
    lambda_w: float = 1e-3
    lambda_chi: float = 0.02
    block_rows: int = 7
    homogeneous: float = 0.2
    adapt: bool = True
    tol: float = TOL
    max_outer: int = MAX_OUTER
    max_add: int = MAX_ADD
    gain_slope: bool = True
    slow_axes: tuple = ("rx", "ry")
    slow_search: float = 3.0

    def __post_init__(self):
        axes = tuple(self.axes)
        slow = tuple(self.slow_axes)
        if any(a not in ("rx", "ry") for a in slow) or len(set(slow)) != len(slow):
            raise ParameterError(f"slow_axes: expected distinct names from ('rx', 'ry'), got {slow}")
        object.__setattr__(self, "slow_axes", tuple(a for a in slow if a not in axes))
        if not self.slow_search >= 0:
            raise ParameterError(f"slow_search: expected degrees >= 0, got {self.slow_search!r}")
        n = len(axes)
        hw = _per_axis(self.half_width, n, "half_width")
        st = _per_axis(self.step, n, "step")
        search = tuple(SEARCH.get(a, 0.0) for a in axes) if self.search is None else self.search
        search = _per_axis(search, n, "search")
        if None in search:
            raise ParameterError(f"search: expected a number per axis, got {self.search}")
        object.__setattr__(self, "axes", axes)
        object.__setattr__(self, "half_width", hw)
        object.__setattr__(self, "step", st)
        object.__setattr__(self, "search", search)
        PoseSpace(axes, [1.0 if v is None else v for v in hw], [1.0 if v is None else v for v in st])  # validates
        if self.solver not in ("fast", "exact"):
            raise ParameterError(f"solver: expected 'fast' or 'exact', got {self.solver!r}")
        if self.shutter not in ("rolling", "global"):
            raise ParameterError(f"shutter: expected 'rolling' or 'global', got {self.shutter!r}")
        if not (self.lambda_w >= 0 and self.lambda_chi > 0):
            raise ParameterError(f"lambda_w >= 0 and lambda_chi > 0 expected, got {self.lambda_w}, {self.lambda_chi}")

    @property
    def trajectory_axes(self):
        """Axes of the trajectory :func:`register` reports: ``axes`` then the slow ones."""
        return tuple(self.axes) + tuple(self.slow_axes)

    @property
    def is_resolved(self):
        return None not in self.half_width and None not in self.step

    def resolved(self, camera):
        """These parameters with every ``None`` step and half-width filled in for
        ``camera`` (see :func:`auto_step`); half-widths default to 3 steps."""
        step = tuple(auto_step(a, camera) if s is None else s for a, s in zip(self.axes, self.step))
        half = tuple(3.0 * s if b is None else b for b, s in zip(self.half_width, step))
        return dataclasses.replace(self, step=step, half_width=half)

    @property
    def space(self):
        if not self.is_resolved:
            raise ParameterError("RegistrationParams: steps are still 'auto'; call resolved(camera) first")
        return PoseSpace(self.axes, self.half_width, self.step)


def _per_axis(values, n, name):
    values = tuple(values) if isinstance(values, (tuple, list)) else (values,) * n
    if len(values) == 1:
        values = values * n
    if len(values) != n:
        raise ParameterError(f"{name}: expected one value per axis ({n}), got {values}")
    return tuple(None if v is None else float(v) for v in values)


def auto_step(axis, camera):
    """Grid step of ``axis`` that moves the farthest pixel of the image by about
    one pixel (METHOD.md: neighbouring warps one pixel apart).

    tx, ty: 1 px; rz: 1 / r rad with r the distance of the farthest corner from
    the principal point; rx, ry: 1 / f rad; s: 1 / r.
    """
    radius = float(np.hypot(camera.center_xy[0] + 0.5, camera.center_xy[1] + 0.5))
    if axis in ("tx", "ty"):
        return 1.0
    if axis == "rz":
        return float(np.degrees(1.0 / radius))
    if axis in ("rx", "ry"):
        return float(np.degrees(1.0 / camera.focal))
    return 1.0 / radius
