"""Gappy POD: low-rank completion of masked snapshots, gappy projection and coarse → fine interpolation.

What a POD-based baseline (e.g. :mod:`lnf.baselines.operator_inference`) needs to learn from lnf's own data,
the sparse observations: each trajectory observes a fixed subset of the coarse points (``masks`` (n, Nc)).

* :func:`complete_snapshots`: the missing entries of the snapshot matrix from an iterated rank-r model (Everson &
  Sirovich 1995, "Karhunen–Loève procedure for gappy data", J. Opt. Soc. Am. A 12(8)); :func:`select_rank`: r.
* :func:`gappy_encode`: a basis' coefficients fitted by (weighted) least squares to the observed entries only.
* :func:`interpolation_matrix`: piecewise-linear interpolation weights from scattered points to others
  (barycentric on a Delaunay triangulation, 1-D: linear between neighbours; nearest point outside the hull).
"""
from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree


def _svd(X: np.ndarray, rank: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The `rank` leading singular triplets of X (dense; `svds`, seeded, when X is large and rank small)."""
    if min(X.shape) > 500 and rank < min(X.shape) // 4:
        from scipy.sparse.linalg import svds

        U, s, Vt = svds(X, k=rank, v0=np.random.default_rng(0).standard_normal(min(X.shape)))
        return U[:, ::-1], s[::-1], Vt[::-1]  # svds: ascending
    U, s, Vt = np.linalg.svd(X, full_matrices=False)
    return U[:, :rank], s[:rank], Vt[:rank]


def _ridge_solve(G: np.ndarray, b: np.ndarray, ridge: float) -> np.ndarray:
    """Batched solutions x of (G + ridge · mean(diag G) · I) x = b, G (..., k, k) symmetric positive semi-definite,
    b (..., k, m); at ridge 0 the least-squares solution through the pseudo-inverse."""
    if ridge <= 0:
        return np.linalg.pinv(G) @ b
    k = G.shape[-1]
    scale = np.maximum(np.trace(G, axis1=-2, axis2=-1)[..., None, None] / k, 1e-300)
    return np.linalg.solve(G + ridge * scale * np.eye(k), b)


def complete_snapshots(values: np.ndarray, masks: np.ndarray, rank: int, iterations: int = 500,
                       tol: float = 1e-6, points: Optional[np.ndarray] = None,
                       method: str = "als", ridge: float = 1e-5) -> tuple[np.ndarray, dict[str, Any]]:
    """Fill the unobserved points of masked trajectories from a rank-`rank` model of all their snapshots.

    Args:
        values: (n, T, Nc, A); only the points with ``masks[i]`` True are read for trajectory i (the mask is fixed
            along a trajectory; the others may hold anything, NaN included).
        masks: (n, Nc) bool, the observed points of each trajectory.
        rank: r ≥ 1 of the model, at most min(Nc·A, n·T) (the snapshot matrix's size). A rank above the data's
            lets the missing entries drift: choose it with :func:`select_rank`.
        iterations, tol: stop after `iterations` sweeps or when a sweep changes the filled entries by less than
            `tol` relative to the norm of the observed ones.
        points: (Nc, dim) positions of the points, or None. A point that no trajectory observes is a row of the
            snapshot matrix without data, which no low-rank model determines: it is interpolated linearly
            (:func:`interpolation_matrix`) from the completed values at the observed points when `points` are
            given, else left at 0.
        method: how each sweep (on the points some trajectory observes) refits X ≈ x̄ 1ᵀ + U Vᵀ (Nc·A, n·T),
            from each point's mean observed value, before the missing entries take the model's values: "svd" as
            Everson & Sirovich, the rank-r truncated SVD of the filled, centred X; "als" (default) alternating
            least squares on the observed entries only (each trajectory's V from U at its points, then each row's
            x̄ and U): the same fixed point, in tens of sweeps where "svd" needs thousands with fixed masks.
        ridge: "als" adds ridge · mean(diag G) · I to each least-squares Gram matrix G: a row of U (or a
            trajectory's V) that too few observations determine (a rank above what the overlapping masks identify)
            stays near 0 instead of drifting; the bias on well-determined data is ~ridge (0: none, the pseudo-inverse).

    Returns the completed values (n, T, Nc, A) float64 (observed entries unchanged) and info: iterations, change
    (the last relative change), converged, unobserved_points (never observed), basis (Nc·A, r) and mean (Nc·A,) of
    the completed X (rows ordered point-major: index p·A + a).
    """
    values, masks = np.asarray(values, dtype=np.float64), np.asarray(masks)
    if values.ndim != 4:
        raise ValueError(f"values must be (n, T, Nc, A), got shape {values.shape}")
    n, T, Nc, A = values.shape
    if masks.shape != (n, Nc) or masks.dtype != bool:
        raise ValueError(f"masks must be (n, Nc) = ({n}, {Nc}) bool, got shape {masks.shape} dtype {masks.dtype}")
    D, cols = Nc * A, n * T
    if isinstance(rank, bool) or not isinstance(rank, (int, np.integer)) or not 1 <= rank <= min(D, cols):
        raise ValueError(f"rank must be an integer in [1, {min(D, cols)}] (the snapshot matrix is {D} values × "
                         f"{cols} snapshots), got {rank!r}")
    if points is not None and (np.ndim(points) not in (1, 2) or len(points) != Nc):
        raise ValueError(f"points must be (Nc, dim) with Nc = {Nc}, got shape {np.shape(points)}")
    if method not in ("als", "svd"):
        raise ValueError(f"method must be 'als' or 'svd', got {method!r}")
    if not masks.any():
        raise ValueError("masks: no trajectory observes any point")
    seen = masks.any(0)
    rows = np.repeat(seen, A)
    X = values.transpose(2, 3, 0, 1).reshape(D, cols)
    observed = np.repeat(np.repeat(masks.T, A, axis=0), T, axis=1)[rows]  # (D_seen, n·T)
    Y = np.where(observed, X[rows], 0.0)
    Y, missing = np.where(observed, Y, (Y.sum(1) / observed.sum(1))[:, None]), ~observed
    scale = float(np.linalg.norm(Y[observed])) or 1.0
    by_traj = np.repeat(masks.T, A, axis=0)[rows].astype(np.float64)  # (D_seen, n): who observes each row
    mean = Y.mean(1)
    U, change, it = _svd(Y - mean[:, None], rank)[0], 0.0, 0
    while it < iterations and missing.any() and min(Y.shape) > rank and not (it and change <= tol):
        if method == "svd":  # Everson & Sirovich: the rank-r SVD of the filled, centred matrix
            mean = Y.mean(1)
            U, s, Vt = _svd(Y - mean[:, None], rank)
            fill = (U * s) @ Vt + mean[:, None]
        else:  # least squares on the observed entries: each trajectory's coefficients, then each row's (mean, U)
            W = by_traj[:, :, None] * (Y - mean[:, None]).reshape(-1, n, T)  # observed, centred entries (d, n, T)
            G = np.einsum("dn,da,db->nab", by_traj, U, U, optimize=True)
            V = _ridge_solve(G, (U.T @ W.reshape(len(U), -1)).reshape(rank, n, T).transpose(1, 0, 2), ridge)
            V = V.transpose(0, 2, 1).reshape(cols, rank)  # (n·T, r)
            F = np.concatenate([np.ones((cols, 1)), V], 1)
            G = (by_traj @ np.einsum("nta,ntb->nab", *[F.reshape(n, T, rank + 1)] * 2).reshape(n, -1))
            b = (by_traj[:, :, None] * Y.reshape(-1, n, T)).reshape(len(Y), -1) @ F  # (d, r + 1)
            sol = _ridge_solve(G.reshape(-1, rank + 1, rank + 1), b[..., None], ridge)[..., 0]
            mean, U = sol[:, 0], sol[:, 1:]
            fill = U @ V.T + mean[:, None]
        change = float(np.linalg.norm(fill[missing] - Y[missing])) / scale
        Y[missing] = fill[missing]
        it += 1
    X = np.zeros((D, cols))
    X[rows] = Y
    if points is not None and not seen.all():
        P = interpolation_matrix(np.asarray(points)[seen], np.asarray(points)[~seen])
        X[~rows] = (P @ Y.reshape(int(seen.sum()), -1)).reshape(-1, cols)
    mean = X.mean(1)
    info = {"iterations": it, "change": change, "converged": bool(change <= tol),
            "unobserved_points": int((~seen).sum()), "basis": _svd(X - mean[:, None], rank)[0], "mean": mean}
    return X.reshape(Nc, A, n, T).transpose(2, 3, 0, 1), info


def select_rank(values: np.ndarray, masks: np.ndarray, ranks: Sequence[int], holdout: float = 0.1, folds: int = 3,
                seed: int = 0, **kwargs: Any) -> tuple[int, dict[int, float]]:
    """The completion rank among `ranks` with the smallest held-out error: in each of `folds` draws, a random
    `holdout` fraction of the observed (trajectory, point) pairs is hidden from :func:`complete_snapshots`
    (`kwargs`: its options) and scored (relative L²) where another trajectory still observes the point; a rank's
    error is the median over the folds (a draw can leave the true rank unidentifiable). values (n, T, Nc, A),
    masks (n, Nc) bool. Returns (rank, {rank: error}). Every candidate is tried: with sparse overlaps between the
    trajectories' masks, ranks below the data's extrapolate wildly too, so the errors are not unimodal."""
    masks, values = np.asarray(masks, dtype=bool), np.asarray(values, dtype=np.float64)
    pairs, rng = np.argwhere(masks), np.random.default_rng(seed)
    errors: dict[int, list[float]] = {int(r): [] for r in ranks}
    for _ in range(folds):
        hide = pairs[rng.random(len(pairs)) < holdout]
        if len(hide) == 0:
            raise ValueError(f"select_rank: holdout = {holdout} hides none of the {len(pairs)} observed pairs")
        kept = masks.copy()
        kept[hide[:, 0], hide[:, 1]] = False
        still = kept[:, hide[:, 1]].any(0)  # the low-rank model's error, not the interpolation's
        hide = hide[still] if still.any() else hide
        true = values[hide[:, 0], :, hide[:, 1]]  # (h, T, A)
        for r in errors:
            done = complete_snapshots(values, kept, r, **kwargs)[0]
            errors[r].append(float(np.linalg.norm(done[hide[:, 0], :, hide[:, 1]] - true) / np.linalg.norm(true)))
    median = {r: float(np.median(e)) for r, e in errors.items()}
    return min(median, key=median.get), median


def gappy_encode(basis: np.ndarray, mean: np.ndarray, values: np.ndarray, observed: np.ndarray,
                 weights: Optional[np.ndarray] = None) -> np.ndarray:
    """Coefficients c minimising Σ_{i observed} w_i (values_i − mean_i − (basis c)_i)²: the gappy projection.

    basis (D, r); mean (D,); values (D,) or (m, D) (unobserved entries ignored); observed (D,) bool (at least r
    True); weights (D,) > 0 or None (equal). Returns c (r,) or (m, r).
    """
    basis, mean, values = (np.asarray(x, dtype=np.float64) for x in (basis, mean, values))
    if basis.ndim != 2:
        raise ValueError(f"basis must be (D, r), got shape {basis.shape}")
    D, r = basis.shape
    if mean.shape != (D,):
        raise ValueError(f"mean must be (D,) = ({D},), got shape {mean.shape}")
    if values.shape[-1:] != (D,) or values.ndim > 2:
        raise ValueError(f"values must be (D,) or (m, D) with D = {D}, got shape {values.shape}")
    observed = np.asarray(observed)
    if observed.shape != (D,) or observed.dtype != bool:
        raise ValueError(f"observed must be (D,) = ({D},) bool, got shape {observed.shape} dtype {observed.dtype}")
    if observed.sum() < r:
        raise ValueError(f"gappy_encode needs at least r = {r} observed entries, got {int(observed.sum())}")
    w = np.ones(D) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (D,) or not np.all(w > 0):
        raise ValueError(f"weights must be (D,) = ({D},) and > 0, got shape {w.shape}")
    root = np.sqrt(w[observed])[:, None]
    rhs = (np.atleast_2d(values)[:, observed] - mean[observed]).T * root  # (D_obs, m)
    coef = np.linalg.lstsq(basis[observed] * root, rhs, rcond=None)[0].T
    return coef[0] if values.ndim == 1 else coef


def interpolation_matrix(source_points: np.ndarray, target_points: np.ndarray) -> sp.csr_matrix:
    """Sparse (Nf, Nc) weights W with (W f)(y_j) the piecewise-linear interpolant of values f at the source points
    (Nc, dim) evaluated at the target points (Nf, dim); each row sums to 1. dim 1: between the neighbouring
    sources; dim ≥ 2: barycentric in the Delaunay simplex holding the target; outside the sources' hull (or for a
    degenerate set of sources): the nearest source point."""
    src, tgt = (np.asarray(x, dtype=np.float64) for x in (source_points, target_points))
    src, tgt = (src[:, None] if src.ndim == 1 else src), (tgt[:, None] if tgt.ndim == 1 else tgt)
    if src.ndim != 2 or len(src) < 1:
        raise ValueError(f"source_points must be (Nc, dim) with Nc ≥ 1, got shape {np.shape(source_points)}")
    if tgt.ndim != 2 or tgt.shape[1] != src.shape[1]:
        raise ValueError(f"target_points must be (Nf, {src.shape[1]}) like the source points, got shape "
                         f"{np.shape(target_points)}")
    (Nc, dim), Nf = src.shape, len(tgt)
    rows, cols, vals, inside = [], [], [], np.zeros(len(tgt), dtype=bool)
    if dim == 1 and Nc >= 2:
        order = np.argsort(src[:, 0])
        xs, x = src[order, 0], tgt[:, 0]
        inside = (x >= xs[0]) & (x <= xs[-1])
        j = np.clip(np.searchsorted(xs, x[inside], side="right") - 1, 0, Nc - 2)
        t = (x[inside] - xs[j]) / np.where(xs[j + 1] > xs[j], xs[j + 1] - xs[j], 1.0)
        rows, cols, vals = [np.flatnonzero(inside)] * 2, [order[j], order[j + 1]], [1.0 - t, t]
    elif dim >= 2 and Nc > dim:
        from scipy.spatial import Delaunay, QhullError

        try:
            tri = Delaunay(src)
            simplex = tri.find_simplex(tgt)
            inside = simplex >= 0
            T = tri.transform[simplex[inside]]  # (m, dim + 1, dim)
            b = np.einsum("mij,mj->mi", T[:, :dim], tgt[inside] - T[:, dim])
            rows, cols = [np.repeat(np.flatnonzero(inside), dim + 1)], [tri.simplices[simplex[inside]].ravel()]
            vals = [np.concatenate([b, 1.0 - b.sum(1, keepdims=True)], axis=1).ravel()]
        except QhullError:  # flat or duplicated sources: nearest neighbour everywhere
            inside[:] = False
    outside = np.flatnonzero(~inside)
    if len(outside):
        rows, cols = rows + [outside], cols + [cKDTree(src).query(tgt[outside])[1]]
        vals = vals + [np.ones(len(outside))]
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(Nf, Nc))
