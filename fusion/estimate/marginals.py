"""Marginal covariances of every pose and load of a linearised fusion graph, in bulk.

The fusion graph has a chain structure: every factor touches the states of one frame or of two
consecutive frames (X(k), V(k), B(k): s = 15 numbers per frame with an IMU, 9 without), plus at
most one load L(j).  Its Gauss-Newton Hessian is therefore block tridiagonal (A: diagonal blocks
D_k, off-diagonal E_k = H[k, k+1]) with a border to the loads (C: frame-load blocks, Dl: 3x3
load blocks):

    H = [[A, C], [C^T, Dl]],  Cov = H^-1.

Pose covariances (exact, same numbers as gtsam.Marginals on the same linearisation):

    block LDL^T of A (forward):   P_0 = D_0,  G_k = P_{k-1}^-1 E_{k-1},  P_k = D_k - E_{k-1}^T G_k
    diag(A^-1) (backward):        S_{N-1} = P_{N-1}^-1,  S_k = P_k^-1 + G_{k+1} S_{k+1} G_{k+1}^T
    loads (Schur complement):     W = A^-1 C,  Sc = Dl - C^T W,  Cov(L) = Sc^-1
    Cov(x_k) = S_k + W_k Sc^-1 W_k^T

(the block forms of the RTS / Takahashi recursions; e.g. Golub & Van Loan, Matrix Computations,
4th ed., Sec. 4.5 for block tridiagonal LDL^T, and the Schur complement of the load block).
gtsam.Marginals computes each of the N pose marginals separately from the Bayes tree
(~0.1-0.2 ms each here); the recursion above costs a few numpy calls per frame.
"""
from __future__ import annotations

import gtsam
import numpy as np
import scipy.sparse as sp

_CHR_SHIFT = 56
_IDX_MASK = (1 << _CHR_SHIFT) - 1
_X, _V, _B, _L = ord("x"), ord("v"), ord("b"), ord("l")

__all__ = ["chain_marginals"]


def chain_marginals(lin: gtsam.GaussianFactorGraph, n_frames: int, has_bias: bool, n_loads: int,
                    work_mb: float = 64.0) -> tuple[np.ndarray, np.ndarray] | None:
    """Marginal covariances of X(0..n_frames-1) ((N, 6, 6), Pose3 order, body frame) and of
    L(0..n_loads-1) ((n_loads, 3, 3), world) from a linearised graph whose factors are
    unconstrained Gaussian factors on X/V/B of one or two consecutive frames and at most one L.
    Returns None when the graph does not have that structure (the caller then falls back to
    gtsam).  `work_mb` bounds the dense frame-by-load work array (loads are processed in column
    chunks that fit)."""
    slot = {_X: (0, 6), _V: (6, 3)}
    if has_bias:
        slot[_B] = (9, 6)
    s = 15 if has_bias else 9
    n, m = n_frames, 3 * n_loads
    D = np.zeros((n, s, s))
    E = np.zeros((max(n - 1, 0), s, s))
    Dl = np.zeros((n_loads, 3, 3))
    dims = {_X: 6, _V: 3, _B: 6, _L: 3}
    c_rows, c_cols, c_vals = [], [], []

    def flush(sig: tuple, items: list) -> None:
        """Add the Hessian blocks A^T A of factors with one key signature to D, E, C, Dl."""
        cols, off = [], 0
        for c, rel in sig:
            cols.append((c, rel, off, dims[c]))
            off += dims[c]
        base = np.array([it[0] for it in items])
        lid = np.array([it[1] for it in items])
        A = np.stack([it[2] for it in items])
        H = np.matmul(A.transpose(0, 2, 1), A)
        unique = len(np.unique(base)) == len(base)
        for ca, ra, oa, da in cols:
            for cb, rb, ob, db in cols:
                blk = H[:, oa:oa + da, ob:ob + db]
                if ca == _L and cb == _L:
                    np.add.at(Dl, lid, blk)
                elif ca == _L or (cb != _L and ra > rb):
                    continue                      # the transposed pair adds it
                elif cb == _L:
                    r = (base + ra)[:, None, None] * s + slot[ca][0] + np.arange(da)[None, :, None]
                    cc = 3 * lid[:, None, None] + np.arange(3)[None, None, :]
                    r, cc = np.broadcast_arrays(r, cc)
                    c_rows.append(r.ravel())
                    c_cols.append(cc.ravel())
                    c_vals.append(blk.ravel())
                else:
                    sa, sb = slot[ca][0], slot[cb][0]
                    target, k = (D, base + ra) if ra == rb else (E, base)
                    if unique:
                        target[k, sa:sa + da, sb:sb + db] += blk
                    else:
                        np.add.at(target, (k[:, None, None], np.arange(sa, sa + da)[None, :, None],
                                           np.arange(sb, sb + db)[None, None, :]), blk)

    groups: dict[tuple, list] = {}
    batch = 2048                                 # factors per Hessian batch (bounds memory)
    for i in range(lin.size()):
        f = lin.at(i)
        if f is None:
            continue
        if isinstance(f, gtsam.JacobianFactor) and f.isConstrained():
            return None
        keys = f.keys()
        chrs = [key >> _CHR_SHIFT for key in keys]
        idxs = [key & _IDX_MASK for key in keys]
        frames = [ix for c, ix in zip(chrs, idxs) if c != _L]
        base = min(frames) if frames else 0
        n_l = chrs.count(_L)
        if (frames and max(frames) - base > 1) or n_l > 1 \
                or any(c not in slot and c != _L for c in chrs):
            return None
        lidx = idxs[chrs.index(_L)] if n_l else -1
        sig = tuple((c, 0 if c == _L else ix - base) for c, ix in zip(chrs, idxs))
        A = f.jacobian()[0]                      # whitened (robust weights included)
        items = groups.setdefault((sig, A.shape[0]), [])
        items.append((base, lidx, A))
        if len(items) == batch:
            flush(sig, items)
            items.clear()
    for (sig, _), items in groups.items():
        if items:
            flush(sig, items)
    del groups
    # ---- block LDL^T of A, forward
    Pinv = np.empty((n, s, s))
    G = np.empty((n, s, s))                      # G[k] = P_{k-1}^-1 E_{k-1}, k >= 1
    inv = np.linalg.inv
    Pinv[0] = inv(D[0])
    for k in range(1, n):
        G[k] = Pinv[k - 1] @ E[k - 1]
        Pinv[k] = inv(D[k] - E[k - 1].T @ G[k])
    # ---- diagonal blocks of A^-1, backward
    cov = np.empty((n, 6, 6))
    Sk = Pinv[n - 1]
    cov[n - 1] = Sk[:6, :6]
    for k in range(n - 2, -1, -1):
        Gk = G[k + 1]
        Sk = Pinv[k] + Gk @ Sk @ Gk.T
        cov[k] = Sk[:6, :6]
    if m == 0:
        return _sym(cov), np.zeros((0, 3, 3))
    # ---- loads: W = A^-1 C by column chunks; keep the pose rows of W
    C = sp.csc_matrix((np.concatenate(c_vals), (np.concatenate(c_rows), np.concatenate(c_cols))),
                      shape=(n * s, m)) if c_vals else sp.csc_matrix((n * s, m))
    chunk = int(max(3, (work_mb * 2 ** 20 // (8 * n * s)) // 3 * 3))
    del D, E
    # pose rows of W; float32 when float64 would pass work_mb * 4 (relative error ~1e-7 on the
    # load term of the pose covariance, far below anything it is used for)
    WX = np.empty((n, 6, m), np.float64 if n * 6 * m * 8 <= work_mb * 4 * 2 ** 20 else np.float32)
    CtW = np.empty((m, m))
    buf = np.empty(n * s * min(chunk, m))
    for c0 in range(0, m, chunk):
        c1 = min(m, c0 + chunk)
        Y = buf[:n * s * (c1 - c0)].reshape(n * s, c1 - c0)
        C[:, c0:c1].toarray(out=Y)
        Y = Y.reshape(n, s, c1 - c0)                         # forward: L Y = C
        for k in range(1, n):                                # (Y_k = C_k - G_k^T Y_{k-1})
            Y[k] -= G[k].T @ Y[k - 1]
        Wk = Pinv[n - 1] @ Y[n - 1]            # backward: W_k = P_k^-1 Y_k - G_{k+1} W_{k+1}
        Y[n - 1] = Wk
        for k in range(n - 2, -1, -1):
            Wk = Pinv[k] @ Y[k] - G[k + 1] @ Wk
            Y[k] = Wk
        WX[:, :, c0:c1] = Y[:, :6, :]
        CtW[:, c0:c1] = C.T @ Y.reshape(n * s, c1 - c0)
    Dl_full = np.zeros((m, m))
    for j in range(n_loads):
        Dl_full[3 * j:3 * j + 3, 3 * j:3 * j + 3] = Dl[j]
    Sc_inv = _spd_inv(Dl_full - 0.5 * (CtW + CtW.T))
    for a in range(0, n, 4096):         # in frame blocks: WX @ Sc^-1 would be another WX
        w = WX[a:a + 4096].astype(np.float64)
        cov[a:a + 4096] += np.matmul(np.matmul(w, Sc_inv), w.transpose(0, 2, 1))
    lcov = np.stack([Sc_inv[3 * j:3 * j + 3, 3 * j:3 * j + 3] for j in range(n_loads)])
    return _sym(cov), _sym(lcov)


def _spd_inv(M: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix through its Cholesky factor."""
    Li = np.linalg.inv(np.linalg.cholesky(0.5 * (M + M.T)))
    return Li.T @ Li


def _sym(M: np.ndarray) -> np.ndarray:
    return 0.5 * (M + np.swapaxes(M, -1, -2))
