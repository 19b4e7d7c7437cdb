"""The fast per-row solver of eq. 13 (numba kernels, float32 data, float64 sums).

For a fixed pose weight vector ``w`` the best change term is the soft-threshold of
the residual (METHOD.md section 2), so eq. 13 is exactly

    minimise_{w >= 0}  sum_j rho(g_j - a_j . w) + lambda_w * sum_k w_k

with the Huber function ``rho(r) = r^2`` for ``|r| <= d`` and ``2 d |r| - d^2``
otherwise, ``d = lambda_chi / 2``.  The solver is a primal active-set Newton
method for this piecewise-quadratic problem:

1. fix the partition of pixels into inliers (``|r| <= d``) and outliers and the
   working set of poses (those with ``w > 0`` plus the worst KKT violators);
2. solve the resulting bound-constrained quadratic exactly (Lawson-Hanson active
   set with a Cholesky factor of the small Gram matrix, updated as poses enter
   and leave the free set);
3. take an exact line search on the true Huber objective towards that point;
4. stop when the KKT conditions of the full problem hold to ``tol``.

Every step decreases the objective and the partition of a convex piecewise
quadratic is finite, so the method terminates at the exact optimum up to
rounding.
"""

import math
from typing import NamedTuple

import numba
import numpy as np

from .._oracle import optimal_chi

#: The row solver's settings, one source for every caller (the registration's
#: rows, the depth re-solve, :func:`solve_row_fast`): relative KKT tolerance,
#: outer iterations, poses added to the working set per iteration.
TOL, MAX_OUTER, MAX_ADD = 1e-6, 100, 8

__all__ = []

#: Most steps of iterative refinement of a Newton system (:func:`_factor_solve`).
REFINE_STEPS = 8

#: How a row solve ended (:func:`_solve_huber_nn`): the optimality conditions
#: hold to the tolerance; no step decreases the objective any more while they
#: do not; the iteration limit.
SOLVED, STALLED, LIMIT = 0, 1, 2

_JIT = dict(nogil=True, cache=True)
# sums over the pixels of a row may be reassociated (vectorised); no other
# fast-math liberty is taken (NaN tests must keep working)
_SUMS = dict(nogil=True, cache=True, fastmath={"reassoc", "contract"})


@numba.njit(**_JIT)
def _huber_value(r, delta):
    a = abs(r)
    if a <= delta:
        return r * r
    return 2.0 * delta * a - delta * delta


class _Columns(NamedTuple):
    """The columns of ``F_i`` (one per pose) a solve reads.

    Pose k's pixel j is ``src[row_of[k], col_of[k] + j]`` (finite values);
    ``a`` (K, N) float32 holds the column with the invalid pixels (``valid``
    False) zeroed once ``have[k]``.  A pass of the gradient over every pose
    reads ``src`` straight; the poses a solve works with are copied into
    ``a`` on first use (:func:`_column`).  Rows of the propagation keep in
    ``src`` only the distinct pre-warped rows their poses shift
    (:func:`ops.registration._propagate_kernels._lattice_columns`); a dense
    ``a`` is its own ``src`` (:func:`_dense`)."""

    src: np.ndarray
    row_of: np.ndarray
    col_of: np.ndarray
    valid: np.ndarray
    a: np.ndarray
    have: np.ndarray


@numba.njit(**_JIT)
def _dense(a):
    """:class:`_Columns` of a dense ``a`` (K, N) float32, invalid pixels zeroed."""
    k_count, n = a.shape
    return _Columns(a, np.arange(k_count), np.zeros(k_count, np.int64), np.ones(n, np.bool_), a,
                    np.ones(k_count, np.bool_))


@numba.njit(**_JIT)
def _column(cols, k):
    """Pose ``k``'s column, invalid pixels zeroed (copied on first use)."""
    if not cols.have[k]:
        ak = cols.a[k]
        c = cols.col_of[k]
        row = cols.src[cols.row_of[k], c:c + ak.shape[0]]
        for j in range(ak.shape[0]):
            ak[j] = row[j] if cols.valid[j] else np.float32(0.0)
        cols.have[k] = True
    return cols.a[k]


@numba.njit(**_JIT)
def _residual(cols, g, w):
    """``g - a.T @ w`` over the poses with weight (float64, shape (n,))."""
    n = cols.a.shape[1]
    r = np.empty(n)
    for j in range(n):
        r[j] = g[j]
    for k in range(cols.a.shape[0]):
        if w[k] > 0.0:
            ak = _column(cols, k)
            for j in range(n):
                r[j] -= w[k] * ak[j]
    return r


@numba.njit(**_JIT)
def _psi(r, delta):
    if r > delta:
        return 2.0 * delta
    if r < -delta:
        return -2.0 * delta
    return 2.0 * r


@numba.njit(**_SUMS)
def _objective(r, w, lam, delta):
    total = 0.0
    for j in range(r.shape[0]):
        total += _huber_value(r[j], delta)
    return total + lam * np.sum(w)


@numba.njit(**_SUMS)
def _gradient(cols, r, lam, delta, out):
    """The gradient over every pose, read from ``cols.src``: where a pixel
    is invalid its residual, and so ``psi``, is 0.  Four poses share each
    pass over ``psi`` (its loads are a good part of a product's cost); each
    pose's sum is its own, as in :func:`_gradient_of`."""
    k_count, n = cols.a.shape
    psi = np.empty(n)
    for j in range(n):
        psi[j] = _psi(r[j], delta)
    src, row_of, col_of = cols.src, cols.row_of, cols.col_of
    k = 0
    while k + 4 <= k_count:
        r0 = src[row_of[k], col_of[k]:col_of[k] + n]
        r1 = src[row_of[k + 1], col_of[k + 1]:col_of[k + 1] + n]
        r2 = src[row_of[k + 2], col_of[k + 2]:col_of[k + 2] + n]
        r3 = src[row_of[k + 3], col_of[k + 3]:col_of[k + 3] + n]
        a0, a1, a2, a3 = 0.0, 0.0, 0.0, 0.0
        for j in range(n):
            p = psi[j]
            a0 += p * r0[j]
            a1 += p * r1[j]
            a2 += p * r2[j]
            a3 += p * r3[j]
        out[k], out[k + 1], out[k + 2], out[k + 3] = lam - a0, lam - a1, lam - a2, lam - a3
        k += 4
    for k in range(k, k_count):
        c = col_of[k]
        row = src[row_of[k], c:c + n]
        acc = 0.0
        for j in range(n):
            acc += psi[j] * row[j]
        out[k] = lam - acc


@numba.njit(**_SUMS)
def _gradient_of(cols, r, lam, delta, out, idx, m):
    """:func:`_gradient` for the poses ``idx[:m]`` only (the others untouched)."""
    n = cols.a.shape[1]
    psi = np.empty(n)
    for j in range(n):
        psi[j] = _psi(r[j], delta)
    for p in range(m):
        k = idx[p]
        ak = _column(cols, k)
        acc = 0.0
        for j in range(n):
            acc += psi[j] * ak[j]
        out[k] = lam - acc


@numba.njit(**_JIT)
def _violation(grad, w, seen, full):
    """Largest KKT violation over every pose (``full``) or those ``seen``."""
    viol = 0.0
    for k in range(grad.shape[0]):
        if full or seen[k]:
            v = abs(grad[k]) if w[k] > 0.0 else -grad[k]
            viol = max(viol, v)
    return viol


@numba.njit(**_JIT)
def _triangular_solve(lmat, rhs, m, z):
    """z[:m] = the solution of L L' z = rhs[:m] (L = ``lmat[:m, :m]``, lower)."""
    for p in range(m):
        acc = rhs[p]
        for t in range(p):
            acc -= lmat[p, t] * z[t]
        z[p] = acc / lmat[p, p]
    for p in range(m - 1, -1, -1):
        acc = z[p]
        for t in range(p + 1, m):
            acc -= lmat[t, p] * z[t]
        z[p] = acc / lmat[p, p]


@numba.njit(**_JIT)
def _factor_add(h, lmat, order, nf, p, ridge):
    """Pose ``p`` enters the free set: the Cholesky factor ``lmat[:nf, :nf]``
    of ``h[order, order] + ridge I`` (``order[:nf]``) gains a last row, the
    one a full factorisation in this order computes.  Returns nf + 1."""
    for t in range(nf):
        acc = h[p, order[t]]
        for s in range(t):
            acc -= lmat[nf, s] * lmat[t, s]
        lmat[nf, t] = acc / lmat[t, t]
    acc = h[p, p]
    for t in range(nf):
        acc -= lmat[nf, t] * lmat[nf, t]
    acc += ridge
    lmat[nf, nf] = math.sqrt(acc) if acc > 0.0 else math.sqrt(ridge)
    order[nf] = p
    return nf + 1


@numba.njit(**_JIT)
def _factor_remove(lmat, order, where, nf, q):
    """The pose at position ``q`` of the factor leaves the free set.  Without
    its row, ``L`` still factors the smaller matrix (``L L'`` is made of the
    rows' products) but has one entry above the diagonal in each row below
    ``q``; Givens rotations of neighbouring columns, which leave ``L L'``
    unchanged, zero them.  ``where`` (pose -> position) follows.  Returns
    nf - 1."""
    where[order[q]] = -1
    for i in range(q, nf - 1):
        for t in range(i + 2):
            lmat[i, t] = lmat[i + 1, t]
        order[i] = order[i + 1]
        where[order[i]] = i
    for i in range(q, nf - 1):
        a, c = lmat[i, i], lmat[i, i + 1]
        if c != 0.0:
            r = math.hypot(a, c)
            cos, sin = a / r, c / r
            for k in range(i, nf - 1):
                li, lj = lmat[k, i], lmat[k, i + 1]
                lmat[k, i] = cos * li + sin * lj
                lmat[k, i + 1] = cos * lj - sin * li
        lmat[i, i + 1] = 0.0
    return nf - 1


@numba.njit(**_JIT)
def _factor_solve(h, b, lmat, order, nf, z, rhs, dz):
    """z[:nf] = the solution of ``h[order, order] z = b[order]`` (first
    ``nf`` of ``order``) from the ridged factor (the Gram matrices of
    neighbouring poses are nearly singular), refined (:func:`_refine`)."""
    _ridged_solve(b, lmat, order, nf, z, rhs)
    _refine(h, b, lmat, order, nf, z, rhs, dz)


@numba.njit(**_JIT)
def _ridged_solve(b, lmat, order, nf, z, rhs):
    """z[:nf] = the solution of the ridged system ``L L' z = b[order]``,
    not refined."""
    for p in range(nf):
        rhs[p] = b[order[p]]
    _triangular_solve(lmat, rhs, nf, z)


@numba.njit(**_JIT)
def _refine(h, b, lmat, order, nf, z, rhs, dz):
    """Steps of iterative refinement of ``z[:nf]`` against the unridged
    matrix ``h[order, order]``, which remove the ridge's bias (several when
    an offset common to every pose, such as intensities far from 0, makes the
    ridge large against the small eigenvalues).  The steps stop once a
    correction is below rounding, or small and no longer shrinking (what is
    left is the rounding of the residual: further steps only move ``z``
    within it)."""
    before = np.inf
    for _ in range(REFINE_STEPS):
        for p in range(nf):
            hp = order[p]
            acc = b[hp]
            for q in range(nf):
                acc -= h[hp, order[q]] * z[q]
            rhs[p] = acc
        _triangular_solve(lmat, rhs, nf, dz)
        change, size = 0.0, 0.0
        for p in range(nf):
            z[p] += dz[p]
            change = max(change, abs(dz[p]))
            size = max(size, abs(z[p]))
        if change <= 1e-13 * size or (change <= 1e-9 * size and change > 0.5 * before):
            break
        before = change


@numba.njit(**_JIT)
def _nnqp(h, b, x, tol):
    """Lawson-Hanson active set for min x'Hx - 2b'x, x >= 0; x (feasible) is
    updated in place.  The Cholesky factor of the free set's system is
    updated as poses enter (a row appended) and leave (a row removed,
    :func:`_factor_remove`) instead of computed afresh; its ridge is
    relative to the largest diagonal entry of ``h``.  The solves of the free
    set are not refined (:func:`_refine`) until they reach an optimum: from
    there on each is, as :func:`_factor_solve` does, and the optimum is
    solved and checked again that way; what is returned is always that of
    refined solves."""
    m = b.shape[0]
    free = np.zeros(m, dtype=np.bool_)
    lmat = np.empty((m, m))
    order = np.empty(m, dtype=np.int64)
    where = np.full(m, -1, dtype=np.int64)  # pose -> position in order
    z, rhs, dz = np.empty(m), np.empty(m), np.empty(m)
    scale = 0.0
    for p in range(m):
        scale = max(scale, h[p, p])
    ridge = 1e-10 * scale + 1e-30
    nf = 0
    for p in range(m):
        if x[p] > 0.0:
            free[p] = True
            where[p] = nf
            nf = _factor_add(h, lmat, order, nf, p, ridge)
    precise = False  # solves refined
    for _outer in range(3 * m + 11):
        for _inner in range(3 * m + 10):
            if nf == 0:
                break
            _ridged_solve(b, lmat, order, nf, z, rhs)
            if precise:
                _refine(h, b, lmat, order, nf, z, rhs, dz)
            alpha = 1.0
            blocked = -1
            for p in range(m):  # in pose order: ties go to the lower pose
                if free[p] and z[where[p]] <= 0.0:
                    step = x[p] / (x[p] - z[where[p]])
                    if step < alpha:
                        alpha = step
                        blocked = p
            for p in range(m):
                if free[p]:
                    x[p] += alpha * (z[where[p]] - x[p])
            if blocked < 0:
                break
            x[blocked] = 0.0
            for p in range(m):
                if free[p] and x[p] <= 0.0:
                    x[p] = 0.0
                    free[p] = False
                    nf = _factor_remove(lmat, order, where, nf, where[p])
        best, best_p = -tol, -1
        for p in range(m):
            if not free[p]:
                g = -b[p]
                for q in range(m):
                    g += h[p, q] * x[q]
                if g < best:
                    best, best_p = g, p
        if best_p < 0:
            if precise or nf == 0:
                return
            precise = True  # the optimum of unrefined solves: solved and checked again, refined
            continue
        free[best_p] = True
        where[best_p] = nf
        nf = _factor_add(h, lmat, order, nf, best_p, ridge)


@numba.njit(**_SUMS)
def _line_search(r, e, slope_w, delta, cross):
    """Exact minimiser over t in [0, 1] of sum rho(r - t e) + t * slope_w
    (``cross`` (n,) int64: work space, the solve's own).

    One pass over the pixels gives the derivative at both ends; a pixel
    that keeps its side of the Huber kinks over the whole step adds a term
    linear in t, so the search for the derivative's root (safeguarded
    Newton on a piecewise-linear, increasing function) then runs over the
    pixels that cross a kink only."""
    n = r.shape[0]
    lin0 = slope_w  # derivative of the pixels that keep their side: lin0 + t * lin1
    lin1 = 0.0
    d0 = slope_w
    d1 = slope_w
    nc = 0
    for j in range(n):
        ej = e[j]
        if ej == 0.0:
            continue
        r0 = r[j]
        r1 = r0 - ej
        p0 = _psi(r0, delta) * ej
        p1 = _psi(r1, delta) * ej
        d0 -= p0
        d1 -= p1
        if abs(r0) <= delta and abs(r1) <= delta:
            lin0 -= 2.0 * r0 * ej
            lin1 += 2.0 * ej * ej
        elif r0 > delta and r1 > delta or r0 < -delta and r1 < -delta:
            lin0 -= p0
        else:
            cross[nc] = j
            nc += 1
    if d1 <= 0.0:
        return 1.0
    if d0 >= 0.0:
        return 0.0
    lo, hi = 0.0, 1.0
    t, d = 0.0, d0
    c = lin1
    for q in range(nc):
        j = cross[q]
        if abs(r[j]) <= delta:
            c += 2.0 * e[j] * e[j]
    for _ in range(60):
        if d < 0.0:
            lo = t
        else:
            hi = t
        nt = t - d / c if c > 0.0 else 0.5 * (lo + hi)
        if not (lo < nt < hi):
            nt = 0.5 * (lo + hi)
        if hi - lo < 1e-14:
            break
        t = nt
        d = lin0 + t * lin1
        c = lin1
        for q in range(nc):
            j = cross[q]
            rj = r[j] - t * e[j]
            d -= _psi(rj, delta) * e[j]
            if abs(rj) <= delta:
                c += 2.0 * e[j] * e[j]
        if d == 0.0:
            break
    return t


#: Most products of pose columns a solve keeps between its iterations
#: (:class:`_GramCache`): the working set of a few iterations.
GRAM_POOL = 128


class _GramCache(NamedTuple):
    """Products of pose columns that the Newton models of one partition share.

    ``slot_of`` (K,) maps a pose to its place in the pool (-1: none),
    ``poses`` (P,) the other way; ``h`` (P, P) and ``b`` (P,) hold the
    weighted products of the current model where ``h_done`` and ``b_done``
    say so; ``state`` (2,) = (poses in the pool, 1 when the last model built
    was a Newton model).  Valid while the pixel weights stay the same (see
    :func:`_huber_nn_iterate`), so each product is computed once, by the
    same loop as a fresh one, and reused bit for bit."""

    slot_of: np.ndarray
    poses: np.ndarray
    h: np.ndarray
    h_done: np.ndarray
    b: np.ndarray
    b_done: np.ndarray
    state: np.ndarray


@numba.njit(**_JIT)
def _gram_cache(k_count, pool):
    return _GramCache(np.full(k_count, -1, np.int64), np.empty(pool, np.int64), np.empty((pool, pool)),
                      np.zeros((pool, pool), np.bool_), np.empty(pool), np.zeros(pool, np.bool_),
                      np.zeros(2, np.int64))


@numba.njit(**_JIT)
def _gram_clear(cache):
    size = cache.state[0]
    for q in range(size):
        cache.slot_of[cache.poses[q]] = -1
        cache.b_done[q] = False
        for t in range(size):
            cache.h_done[q, t] = False
    cache.state[0] = 0


@numba.njit(**_SUMS)
def _dot_lin(ap, lin):
    acc = 0.0
    for j in range(ap.shape[0]):
        acc += ap[j] * lin[j]
    return acc


@numba.njit(**_SUMS)
def _weighted(ap, weight, out):
    """out (N,) float64 = weight * ap: a product of pose columns is then
    one multiply-add per pixel (:func:`_dot_lin`)."""
    for j in range(ap.shape[0]):
        out[j] = weight[j] * ap[j]


@numba.njit(**_SUMS)
def _gram_model(cache, cols, idx, m, weight, lin, lam, h, b):
    """``h`` (m, m) = the weighted Gram matrix of the poses ``idx[:m]``,
    ``b`` (m,) = their products with ``lin`` less ``lam / 2``: from the
    cache where it holds them, computed (and kept) where not."""
    pool = cache.poses.shape[0]
    wp = np.empty(weight.shape[0])  # weight * column p, made once for all of p's missing products
    if m > pool:  # a working set larger than the pool: computed afresh
        _gram_clear(cache)
        for p in range(m):
            ap = _column(cols, idx[p])
            b[p] = _dot_lin(ap, lin) - 0.5 * lam
            _weighted(ap, weight, wp)
            for q in range(p + 1):
                h[p, q] = _dot_lin(_column(cols, idx[q]), wp)
                h[q, p] = h[p, q]
        return
    missing = 0
    for p in range(m):
        if cache.slot_of[idx[p]] < 0:
            missing += 1
    if cache.state[0] + missing > pool:
        _gram_clear(cache)
    for p in range(m):
        k = idx[p]
        if cache.slot_of[k] < 0:
            cache.slot_of[k] = cache.state[0]
            cache.poses[cache.state[0]] = k
            cache.state[0] += 1
    for p in range(m):
        sp = cache.slot_of[idx[p]]
        ap = _column(cols, idx[p])
        if not cache.b_done[sp]:
            cache.b[sp] = _dot_lin(ap, lin) - 0.5 * lam
            cache.b_done[sp] = True
        b[p] = cache.b[sp]
        made = False
        for q in range(p + 1):
            sq = cache.slot_of[idx[q]]
            if not cache.h_done[sp, sq]:
                if not made:
                    _weighted(ap, weight, wp)
                    made = True
                value = _dot_lin(_column(cols, idx[q]), wp)
                cache.h[sp, sq] = value
                cache.h[sq, sp] = value
                cache.h_done[sp, sq] = True
                cache.h_done[sq, sp] = True
            h[p, q] = cache.h[sp, sq]
            h[q, p] = cache.h[sp, sq]


@numba.njit(**_JIT)
def _admit_worst(grad, work, seen, full, max_add, pick):
    """Mark in ``work`` the ``max_add`` poses with the most negative gradient
    among those outside it whose gradient is current (every pose when
    ``full``, else those ``seen``); ties go to the lower index.  ``pick``
    (>= max_add,) is work space."""
    count = 0
    for k in range(grad.shape[0]):
        if work[k] or not (full or seen[k]):
            continue
        gk = grad[k]
        if not gk < 0.0:
            continue
        if count < max_add:
            pos = count
            count += 1
        elif count > 0 and gk < grad[pick[count - 1]]:
            pos = count - 1
        else:
            continue
        while pos > 0 and grad[pick[pos - 1]] > gk:
            pick[pos] = pick[pos - 1]
            pos -= 1
        pick[pos] = k
    for q in range(count):
        work[pick[q]] = True


@numba.njit(**_SUMS)
def _huber_nn_iterate(a, g, w, lam, delta, tol_rel, max_outer, max_add, restricted=True):
    """:func:`_iterate` on a dense ``a`` (K, N) float32, invalid pixels zeroed."""
    return _iterate(_dense(a), g, w, lam, delta, tol_rel, max_outer, max_add, restricted)


@numba.njit(**_SUMS)
def _iterate(cols, g, w, lam, delta, tol_rel, max_outer, max_add, restricted=True):
    """The active-set Newton iterations of :func:`_solve_huber_nn` from ``w``
    (in place).  Returns (objective, outer iterations, how they ended:
    :data:`SOLVED` the KKT conditions hold to ``tol_rel``, :data:`STALLED` no
    step decreases the objective any more, :data:`LIMIT` ``max_outer``
    iterations; the KKT violation, at ``w`` when SOLVED, else at an earlier
    iterate).

    ``restricted``: after a pass of the gradient over every pose, the
    iterations look at the working set's poses only, until the conditions
    hold there; then one pass over every pose confirms them or admits its
    worst violators.  The poses that end with zero weight (most of a row's
    neighbourhood) are then checked a few times per solve instead of at every
    iteration; a warm start is first solved on its own support, so that a
    row whose optimum keeps its neighbour's support passes over every pose
    once, to confirm it.  False: every iteration passes over every pose."""
    k_count, n = cols.a.shape
    r = _residual(cols, g, w)
    grad = np.empty(k_count)
    work = np.zeros(k_count, dtype=np.bool_)
    part = np.full(n, 2, dtype=np.int8)
    weight = np.empty(n)
    lin = np.empty(n)
    e = np.empty(n)
    w_old = np.empty(k_count)
    r_old = np.empty(n)
    cross = np.empty(n, dtype=np.int64)  # the line search's pixels that cross a kink
    viol = np.inf
    it = 0
    newton_ok = True
    obj = _objective(r, w, lam, delta)
    full = True  # the next gradient pass covers every pose
    seen = np.ones(k_count, dtype=np.bool_)  # poses whose gradient is current
    idx = np.empty(k_count, dtype=np.int64)
    pick = np.empty(max(max_add, 1), dtype=np.int64)
    cache = _gram_cache(k_count, min(k_count, GRAM_POOL))
    m = 0
    if restricted:
        # a warm start is first solved on its own support: a row whose
        # support is its neighbour's (most rows) then needs one pass over
        # every pose, the one that confirms it
        for k in range(k_count):
            if w[k] > 0.0:
                idx[m] = k
                m += 1
        if m > 0:
            full = False
            for k in range(k_count):
                seen[k] = w[k] > 0.0
    for it in range(max_outer):
        if full:
            _gradient(cols, r, lam, delta, grad)
        else:
            _gradient_of(cols, r, lam, delta, grad, idx, m)
        viol = _violation(grad, w, seen, full)
        if viol <= tol_rel * max(obj, 1e-30):
            if full:
                return obj, it, SOLVED, viol
            # optimal on the working set: one pass over every pose confirms it
            full = True
            _gradient(cols, r, lam, delta, grad)
            viol = _violation(grad, w, seen, full)
            if viol <= tol_rel * max(obj, 1e-30):
                return obj, it, SOLVED, viol
        # working set: support plus the worst violators among the poses seen
        for k in range(k_count):
            work[k] = w[k] > 0.0
        _admit_worst(grad, work, seen, full, max_add, pick)
        m = 0
        for k in range(k_count):
            if work[k]:
                idx[m] = k
                m += 1
        checked = full  # this working set was chosen after a pass over every pose
        if restricted:
            full = False
            for k in range(k_count):
                seen[k] = work[k]
        # quadratic model of the current partition: its Newton model (the
        # objective's own second-order model, exact while no pixel changes
        # side), unless the last Newton step failed to descend; then the
        # half-quadratic majoriser (outlier curvature delta/|r|), which is
        # bounded below whatever the partition
        stable = True
        for j in range(n):
            side = 0
            if r[j] > delta:
                side = 1
            elif r[j] < -delta:
                side = -1
            if side != part[j]:
                stable = False
                part[j] = side
        inliers = 0
        for j in range(n):
            if part[j] == 0:
                inliers += 1
        # the Newton model is bounded only with enough inliers to fix every pose
        newton = newton_ok and inliers >= m
        # the Newton model's pixel weights depend on the partition only: its
        # products from the last iteration still hold when that was a Newton
        # model of the same partition
        if not (newton and stable and cache.state[1] == 1):
            _gram_clear(cache)
        cache.state[1] = 1 if newton else 0
        for j in range(n):
            if part[j] == 0:
                weight[j] = 1.0
                lin[j] = g[j]
            elif newton:
                weight[j] = 0.0
                lin[j] = delta * part[j]
            else:
                weight[j] = delta / abs(r[j])
                # majoriser delta r^2/|r0| about the current residual r0
                lin[j] = weight[j] * g[j]
        h = np.empty((m, m))
        b = np.empty(m)
        _gram_model(cache, cols, idx, m, weight, lin, lam, h, b)
        x = np.empty(m)
        for p in range(m):
            x[p] = w[idx[p]]
        _nnqp(h, b, x, 1e-3 * tol_rel * max(obj, 1e-30))
        # direction and exact line search on the true objective
        for j in range(n):
            e[j] = 0.0
        slope = 0.0
        for p in range(m):
            d = x[p] - w[idx[p]]
            slope += lam * d
            if d != 0.0:
                ap = _column(cols, idx[p])
                for j in range(n):
                    e[j] += d * ap[j]
        t = _line_search(r, e, slope, delta, cross)
        if t <= 0.0:
            if newton:  # the partition's Newton model misled: the majoriser's step descends
                newton_ok = False
                continue
            if not checked:  # stuck on the working set: look at every pose first
                full = True
                continue
            return obj, it, STALLED, viol
        w_old[:] = w
        r_old[:] = r
        for p in range(m):
            k = idx[p]
            w[k] += t * (x[p] - w[k])
            if w[k] < 0.0:
                w[k] = 0.0
        for j in range(n):
            r[j] -= t * e[j]
        new_obj = _objective(r, w, lam, delta)
        if new_obj > obj * (1.0 + 1e-12):
            # rounding defeated the step: undo it; after a Newton step retry
            # with the majoriser, otherwise this is as good as it gets
            w[:] = w_old
            r[:] = r_old
            if not newton:
                if not checked:
                    full = True
                    continue
                return obj, it, STALLED, viol
            newton_ok = False
            continue
        newton_ok = True
        if obj - new_obj <= 1e-14 * obj:
            # no progress left: the remaining KKT residual is rounding (the
            # Cholesky ridge), not a better point, once every pose was seen
            if not checked:
                obj = new_obj
                full = True
                continue
            return new_obj, it, STALLED, viol
        obj = new_obj
    return obj, max_outer, LIMIT, viol


@numba.njit(**_SUMS)
def _kkt(a, g, w, lam, delta):
    """:func:`_kkt_of` a dense ``a`` (K, N) float32."""
    return _kkt_of(_dense(a), g, w, lam, delta)


@numba.njit(**_SUMS)
def _kkt_of(cols, g, w, lam, delta):
    """At ``w``: (objective, KKT violation, bound on the objective's excess
    over the optimum).  The violation is the largest ``|grad_k|`` over the
    support and ``-grad_k`` off it; the bound is convexity's
    ``grad . (w - w*) <= grad . w + max(-grad)+ sum(w*)`` with
    ``lam sum(w*) <= objective`` (inf when ``lam`` is 0)."""
    k_count, n = cols.a.shape
    r = _residual(cols, g, w)
    obj = _objective(r, w, lam, delta)
    grad = np.empty(k_count)
    _gradient(cols, r, lam, delta, grad)
    viol, along, most = 0.0, 0.0, 0.0
    for k in range(k_count):
        if w[k] > 0.0:
            viol = max(viol, abs(grad[k]))
            along += grad[k] * w[k]
        most = max(most, -grad[k])
    viol = max(viol, most)
    gap = along + most * obj / lam if lam > 0.0 else (along if most <= 0.0 else np.inf)
    return obj, viol, max(gap, 0.0)


@numba.njit(**_SUMS)
def _solve_huber_nn(a, g, w, lam, delta, tol_rel, max_outer, max_add):
    """:func:`_solve` on a dense ``a`` (K, N) float32, invalid pixels zeroed."""
    return _solve(_dense(a), g, w, lam, delta, tol_rel, max_outer, max_add)


@numba.njit(**_SUMS)
def _solve(cols, g, w, lam, delta, tol_rel, max_outer, max_add):
    """Minimise sum rho(g - a' w) + lam sum w over w >= 0 (in place).

    ``a`` (K, N) float32 with zero columns for invalid pixels, ``g`` (N,) with
    zeros there.  A solve that ends short of the optimality conditions is
    solved again from where it stopped with four times the iterations and every
    violating pose admitted at once.  Returns (objective, outer iterations,
    final KKT violation, status): :data:`SOLVED` when the KKT violation is at
    most ``tol_rel`` times the objective or the objective provably within
    ``tol_rel`` of the optimum (:func:`_kkt`), else :data:`LIMIT` or
    :data:`STALLED` by how the last attempt ended.
    """
    obj, it, how, viol = _iterate(cols, g, w, lam, delta, tol_rel, max_outer, max_add)
    if how == SOLVED:
        return obj, it, viol, SOLVED
    obj, more, how, viol = _iterate(cols, g, w, lam, delta, tol_rel, 4 * max_outer, cols.a.shape[0])
    it += more
    if how == SOLVED:
        return obj, it, viol, SOLVED
    obj, viol, gap = _kkt_of(cols, g, w, lam, delta)
    bound = tol_rel * max(obj, 1e-30)
    if viol <= bound or gap <= bound:
        return obj, it, viol, SOLVED
    return obj, it, viol, how


@numba.njit(**_SUMS)
def _synthesize(a, w, out):
    """out (N,) = a' w, the registered (warped and blurred) row."""
    k_count, n = a.shape
    for j in range(n):
        out[j] = 0.0
    for k in range(k_count):
        if w[k] > 0.0:
            for j in range(n):
                out[j] += w[k] * a[k, j]


def solve_row_fast(F, g, *, lambda_w, lambda_chi, w0=None, tol=TOL, max_outer=MAX_OUTER, max_add=MAX_ADD):
    """Fast exact solve of eq. 13 for one row (or a stacked block of rows).

    Parameters
    ----------
    F : ndarray, shape (N, K)
        Row of the reference warped by each of K poses (METHOD.md's ``F_i``).
    g : ndarray, shape (N,)
        Observed row, intensities in [0, 1].
    lambda_w, lambda_chi : float
        Weights of ``||w||_1`` and ``||chi||_1`` in eq. 13.
    w0 : ndarray, shape (K,), optional
        Warm start (non-negative).
    tol, max_outer, max_add : float, int, int
        Relative KKT tolerance, outer iterations, poses added per iteration
        (defaults :data:`TOL`, :data:`MAX_OUTER`, :data:`MAX_ADD`).

    Returns
    -------
    w : ndarray, shape (K,), float64
    chi : ndarray, shape (N,), float64
        Optimal change term for ``w`` (soft-threshold of the residual).
    objective : float
        Value of eq. 13.
    """
    a = np.ascontiguousarray(np.asarray(F, dtype=np.float32).T)
    g64 = np.asarray(g, dtype=np.float64)
    w = np.zeros(a.shape[0]) if w0 is None else np.maximum(np.asarray(w0, dtype=np.float64), 0.0).copy()
    delta = 0.5 * float(lambda_chi)
    obj, _, _, _ = _solve_huber_nn(a, g64, w, float(lambda_w), delta, float(tol), int(max_outer), int(max_add))
    chi = optimal_chi(g64 - a.T.astype(np.float64) @ w, lambda_chi=lambda_chi)
    return w, chi, float(obj)
