"""The fit of the slow out-of-plane path to a sampled optical flow
(:func:`._slow.estimate_slow`): a robust least-squares fit of the exact flow
of small rotations about the principal point, the in-plane motion (tx, ty,
rz) piecewise linear between knots every :data:`FIT_BAND` rows, rx and ry
low-order polynomials of the row time."""

from typing import NamedTuple

import numpy as np

__all__ = []

#: Rows between the knots of the in-plane motion in the fit.
FIT_BAND = 32
_AXES = ("rx", "ry")


def _time(rows, height):
    """Row times scaled to [-1, 1] over the window (the polynomials' variable)."""
    return (np.asarray(rows, np.float64) - 0.5 * (height - 1)) / max(0.5 * height, 1.0)


def _hats(rows, height):
    """Linear interpolation weights (n, K) of ``rows`` between knots every
    :data:`FIT_BAND` rows (the in-plane motion is piecewise linear in time)."""
    knots = int(np.ceil((height - 1) / FIT_BAND)) + 1
    position = np.clip(np.asarray(rows, np.float64) / FIT_BAND, 0, knots - 1)
    low = np.minimum(np.floor(position).astype(np.int64), knots - 2) if knots > 1 else np.zeros(position.shape, int)
    frac = position - low
    out = np.zeros((position.size, knots))
    out[np.arange(position.size), low] = 1.0 - frac
    if knots > 1:
        out[np.arange(position.size), low + 1] += frac
    return out


def _design(rows, x, y, focal, height, degree, axes):
    """Jacobian of the forward displacement at zero rotation: per knot (tx, ty,
    rz in rad), then per slow axis a polynomial of the row time (rad); rows
    of u then v."""
    hats = _hats(rows, height)
    t = _time(rows, height)
    cols_u, cols_v = [], []
    for k in range(hats.shape[1]):
        m = hats[:, k]
        cols_u += [m, 0 * m, -y * m]
        cols_v += [0 * m, m, x * m]
    for a in axes:
        for k in range(degree + 1):
            tk = t ** k
            if a == "ry":
                cols_u.append((focal + x * x / focal) * tk)
                cols_v.append(x * y / focal * tk)
            else:
                cols_u.append(x * y / focal * tk)
                cols_v.append((focal + y * y / focal) * tk)
    return np.concatenate([np.stack(cols_u, 1), np.stack(cols_v, 1)])


class _Model:
    """The exact flow of a path: the in-plane motion (tx, ty, rz) piecewise
    linear between knots, slow rx, ry polynomials of the row time; parameters
    in px and radians."""

    def __init__(self, sample, height, focal, axes, degree):
        self.rows, self.x, self.y, _, _ = sample
        self.height, self.focal, self.axes, self.degree = height, focal, axes, degree
        self.unique, self.row_index = np.unique(self.rows, return_inverse=True)
        self.hats = _hats(self.unique, height)
        self.knots = self.hats.shape[1]

    def rotations(self, params, rows):
        """Slow (rx, ry) in radians (n, 2) at ``rows``."""
        t = _time(rows, self.height)
        out = np.zeros((np.size(rows), 2))
        base = 3 * self.knots
        for q, a in enumerate(self.axes):
            coef = params[base + q * (self.degree + 1):base + (q + 1) * (self.degree + 1)]
            out[:, _AXES.index(a)] = sum(c * t ** k for k, c in enumerate(coef))
        return out

    def inplane(self, params, rows):
        """(tx, ty px, rz rad) (n, 3) at ``rows``."""
        return _hats(rows, self.height) @ params[:3 * self.knots].reshape(self.knots, 3)

    def flow(self, params):
        """Predicted capture -> reference offsets (u, v) of every sample."""
        from .._camera import Camera, pose_homographies

        inplane = self.hats @ params[:3 * self.knots].reshape(self.knots, 3)
        poses = np.zeros((self.unique.size, 6))
        poses[:, 0], poses[:, 1], poses[:, 5] = inplane[:, 0], inplane[:, 1], np.degrees(inplane[:, 2])
        poses[:, 3:5] = np.degrees(self.rotations(params, self.unique))
        # the sample coordinates are centred: a camera at the origin
        inv = pose_homographies(poses, Camera(self.focal, (0.0, 0.0)), inverse=True)[self.row_index]
        x, y = self.x, self.y
        den = inv[:, 2, 0] * x + inv[:, 2, 1] * y + inv[:, 2, 2]
        u = (inv[:, 0, 0] * x + inv[:, 0, 1] * y + inv[:, 0, 2]) / den - x
        v = (inv[:, 1, 0] * x + inv[:, 1, 1] * y + inv[:, 1, 2]) / den - y
        return u, v


def _robust_fit(model, design, u, v, knee=0.5, iterations=7):
    """Parameters of ``model`` that fit the flow (u, v): Gauss-Newton steps
    with the zero-rotation Jacobian (the flow of the capture -> reference map
    is about minus the forward displacement), each a weighted least squares
    with Huber weights first (convex: the start does not matter), then Cauchy
    weights, so flow caught in a wrong match weighs next to nothing.  Returns
    the parameters and the samples' weights."""
    params = np.zeros(design.shape[1])
    weight = np.ones(u.size)
    for it in range(iterations):
        pu, pv = model.flow(params)
        ru, rv = u - pu, v - pv
        r = np.hypot(ru, rv)
        weight = np.minimum(1.0, knee / np.maximum(r, 1e-9)) if it < 3 else 1.0 / (1.0 + (r / knee) ** 2)
        step = _weighted_lstsq(-design, np.concatenate([ru, rv]), np.concatenate([weight, weight]))
        params += step
        if np.abs(step[3 * model.knots:]).max(initial=0.0) < 1e-6 and it >= 3:
            break
    return params, weight


def _weighted_lstsq(design, target, weight):
    """argmin_p sum weight (design p - target)^2 by the normal equations (a few
    dozen unknowns), with a tiny ridge for bands without samples."""
    gram = design.T @ (design * weight[:, None])
    rhs = design.T @ (target * weight)
    gram[np.diag_indices_from(gram)] += 1e-9 * (np.trace(gram) / len(gram) + 1e-12)
    return np.linalg.solve(gram, rhs)


_NEGLIGIBLE, _UNTRUSTED = "negligible", "untrusted"


class _Fit(NamedTuple):
    """A slow path fitted to the flow (rx, ry deg per row (H, 2), and the ty px
    of each row: a :class:`~._slow.SlowPath`), with the in-plane motion (tx,
    ty px, rz deg; (H, 3)) that goes with it and the one that fits the flow
    without it."""

    rotation: np.ndarray
    ty: np.ndarray
    inplane: np.ndarray | None
    inplane_alone: np.ndarray | None


def _fit(sample, height, focal, axes, limit, min_px, alone=True):
    """The slow path of the sampled flow (a :class:`_Fit`; its in-plane motion
    alone only when ``alone``), or :data:`_NEGLIGIBLE`: the displacement that
    only the slow axes explain stays below ``min_px`` everywhere, or
    :data:`_UNTRUSTED`: a rotation beyond ``limit``."""
    rows, x, y, u, v = sample
    degree = 2 if height >= 8 * FIT_BAND else (1 if height >= 4 * FIT_BAND else 0)
    model = _Model(sample, height, focal, axes, degree)
    design = _design(rows, x, y, focal, height, degree, axes)
    params, weight = _robust_fit(model, design, -u, -v)
    n_inplane = 3 * model.knots
    # what the in-plane motion alone makes of the slow part's displacement:
    # the part that only the slow axes explain decides whether it matters
    slow_part = design[:, n_inplane:] @ params[n_inplane:]
    inplane_only = design[:, :n_inplane]
    absorbed = inplane_only @ _weighted_lstsq(inplane_only, slow_part, np.concatenate([weight, weight]))
    if np.percentile(np.abs(slow_part - absorbed), 99) < min_px:
        return _NEGLIGIBLE
    every = np.arange(height)
    rotation = np.degrees(model.rotations(params, every))
    if np.abs(rotation).max() > limit:
        return _UNTRUSTED
    inplane = model.inplane(params, every)
    if not alone:
        return _Fit(rotation, inplane[:, 1], None, None)
    without = _Model(sample, height, focal, (), 0)
    without_params, _ = _robust_fit(without, inplane_only, -u, -v)
    return _Fit(rotation, inplane[:, 1], _degrees(inplane), _degrees(without.inplane(without_params, every)))


def _degrees(inplane):
    out = inplane.copy()
    out[:, 2] = np.degrees(out[:, 2])
    return out
