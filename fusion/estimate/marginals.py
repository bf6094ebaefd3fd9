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

_CHR_SHIFT = 56
_IDX_MASK = (1 << _CHR_SHIFT) - 1
_X, _V, _B, _L, _F, _D = ord("x"), ord("v"), ord("b"), ord("l"), ord("f"), ord("d")
_BORDER_DIMS = {_L: 3, _F: 6}  # variables outside the chain: loads (Point3), floor codes (Pose3)
BORDER_BLOCK_FRAMES = 512
"""Frames per block of the border variables' term of the pose covariances (W Sc^-1 W^T): each
block holds two (frames, 6, m) temporaries; 4096 frames were 2 x 46 MB on a 180 s window with
34 as-built codes, the window's peak."""

__all__ = ["chain_marginals", "chain_marginals_with_codes"]


def chain_marginals(
    lin: gtsam.GaussianFactorGraph,
    n_frames: int,
    has_bias: bool,
    n_loads: int,
    work_mb: float = 64.0,
    group: int = 1,
    row_weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """See _chain_marginals (no floor-code variables)."""
    out = _chain_marginals(lin, n_frames, has_bias, n_loads, 0, work_mb, group, row_weights)
    return None if out is None else (out[0], out[1])


def chain_marginals_with_codes(
    lin: gtsam.GaussianFactorGraph,
    n_frames: int,
    has_bias: bool,
    n_loads: int,
    n_codes: int,
    work_mb: float = 64.0,
    group: int = 1,
    row_weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """chain_marginals plus the (n_codes, 6, 6) marginals of the as-built floor codes F(c)
    (Pose3 order, code frame): like the loads, border variables of the chain
    (fusion.estimate.asbuilt)."""
    return _chain_marginals(lin, n_frames, has_bias, n_loads, n_codes, work_mb, group, row_weights)


def _chain_marginals(
    lin: gtsam.GaussianFactorGraph,
    n_frames: int,
    has_bias: bool,
    n_loads: int,
    n_codes: int,
    work_mb: float = 64.0,
    group: int = 1,
    row_weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Marginal covariances of X(0..n_frames-1) ((N, 6, 6), Pose3 order, body frame) and of
    L(0..n_loads-1) ((n_loads, 3, 3), world) from a linearised graph whose factors are
    unconstrained Gaussian factors on X/V/B of one or two consecutive frames and at most one L
    or F (a floor code's Pose3, n_codes of them: border variables like the loads, 6 columns).
    Returns None when the graph does not have that structure (the caller then falls back to
    gtsam).  The pose rows of W = A^-1 C (N x 6 x 3 n_loads) are kept in float64 below
    4 * `work_mb` MB, else in float32; `group` frames form one block of the recursions (same
    result, fewer but larger numpy steps).  `row_weights` (lin.size(),): factor i's whitened
    rows times row_weights[i] (1 / sqrt(s) gives the marginals of the same linearisation with
    that factor's covariance times s: its Hessian block A^T A / s)."""
    if row_weights is not None and len(row_weights) != lin.size():
        raise ValueError(f"{len(row_weights)} row weights for {lin.size()} linearised factors")
    slot = {_X: (0, 6), _V: (6, 3)}
    if has_bias:
        slot[_B] = (9, 6)
    s = 15 if has_bias else 9
    n = n_frames
    D = np.zeros((n, s, s))
    E = np.zeros((max(n - 1, 0), s, s))
    dims = {_X: 6, _V: 3, _B: 6, **_BORDER_DIMS}
    border_first = {_L: 0, _F: 3 * n_loads}  # first border column of each kind
    c_rows: list[np.ndarray] = []
    c_cols: list[np.ndarray] = []
    c_vals: list[np.ndarray] = []

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
                blk = H[:, oa : oa + da, ob : ob + db]
                a_border, b_border = ca in _BORDER_DIMS, cb in _BORDER_DIMS
                if a_border and b_border:
                    ii = lid[:, None, None] + np.arange(da)[None, :, None]
                    jj = lid[:, None, None] + np.arange(db)[None, None, :]
                    np.add.at(Dl_full, (ii, jj), blk)
                elif a_border or (not b_border and ra > rb):
                    continue  # the transposed pair adds it
                elif b_border:
                    r = (base + ra)[:, None, None] * s + slot[ca][0] + np.arange(da)[None, :, None]
                    cc = lid[:, None, None] + np.arange(db)[None, None, :]
                    r, cc = np.broadcast_arrays(r, cc)
                    c_rows.append(r.ravel())
                    c_cols.append(cc.ravel())
                    c_vals.append(blk.ravel())
                else:
                    sa, sb = slot[ca][0], slot[cb][0]
                    target, k = (D, base + ra) if ra == rb else (E, base)
                    if unique:
                        target[k, sa : sa + da, sb : sb + db] += blk
                    else:
                        np.add.at(
                            target,
                            (
                                k[:, None, None],
                                np.arange(sa, sa + da)[None, :, None],
                                np.arange(sb, sb + db)[None, None, :],
                            ),
                            blk,
                        )

    keys_of, jac_of = [], []
    # a merged map's common shift D (fusion.estimate.asbuilt.SHIFT_KEY): a border variable after
    # the codes, on factors with no chain key (its prior, and each map code's own part about it)
    shift_of = []
    for i in range(lin.size()):
        f = lin.at(i)
        if f is None:
            continue
        if isinstance(f, gtsam.JacobianFactor) and f.isConstrained():
            return None
        jac = f.jacobian()[0]  # whitened (robust weights included)
        if row_weights is not None and row_weights[i] != 1.0:
            jac = jac * float(row_weights[i])
        keys = f.keys()
        if any(k >> _CHR_SHIFT == _D for k in keys):
            shift_of.append((keys, jac))
            continue
        keys_of.append(keys)
        jac_of.append(jac)
    m = 3 * n_loads + 6 * n_codes + (6 if shift_of else 0)
    Dl_full = np.zeros((m, m))
    d0 = 3 * n_loads + 6 * n_codes  # D's first border column
    for keys, jac in shift_of:
        dcols: list[int] = []
        for k in keys:
            sym = gtsam.Symbol(k)
            if sym.chr() == _D and sym.index() == 0:
                dcols += range(d0, d0 + 6)
            elif sym.chr() == _F:
                dcols += range(border_first[_F] + 6 * sym.index(), border_first[_F] + 6 * sym.index() + 6)
            else:
                return None  # D beside a chain variable or a load: not this structure
        Dl_full[np.ix_(dcols, dcols)] += jac.T @ jac
    if not keys_of:
        return None
    # key signatures, vectorised: (chr, frame offset from the factor's first frame) per key
    lens = np.array([len(k) for k in keys_of])
    if lens.min() < 1 or lens.max() > 8:
        return None
    flat = np.array([key for k in keys_of for key in k], dtype=np.uint64)
    chrs = (flat >> np.uint64(_CHR_SHIFT)).astype(np.int64)
    idxs = (flat & np.uint64(_IDX_MASK)).astype(np.int64)
    is_l = np.isin(chrs, list(_BORDER_DIMS))
    if not np.all(is_l | np.isin(chrs, list(slot))):
        return None
    starts = np.r_[0, np.cumsum(lens)[:-1]]
    big = np.iinfo(np.int64).max
    base = np.minimum.reduceat(np.where(is_l, big, idxs), starts)
    top = np.maximum.reduceat(np.where(is_l, -1, idxs), starts)
    n_l = np.add.reduceat(is_l.astype(np.int64), starts)
    no_frame = base == big
    base = np.where(no_frame, 0, base)
    if np.any(n_l > 1) or np.any(~no_frame & (top - base > 1)):
        return None
    lidx = np.full(len(lens), -1)  # first border column of the factor's L or F
    first_col = np.where(chrs == _F, border_first[_F] + 6 * idxs, 3 * idxs)
    lidx[np.repeat(np.arange(len(lens)), lens)[is_l]] = first_col[is_l]
    rel = np.where(is_l, 0, idxs - np.repeat(base, lens))
    code = np.full((len(lens), 9), -1, dtype=np.int64)
    pos = np.arange(len(flat)) - np.repeat(starts, lens)
    code[np.repeat(np.arange(len(lens)), lens), pos] = chrs * 2 + rel
    code[:, 8] = [a.shape[0] for a in jac_of]
    sigs, group_of = np.unique(code, axis=0, return_inverse=True)
    order = np.argsort(group_of.ravel(), kind="stable")
    bounds = np.searchsorted(group_of.ravel()[order], np.arange(len(sigs) + 1))
    batch = 2048  # factors per Hessian batch (bounds memory)
    for gi, row in enumerate(sigs):
        sig = tuple((int(c) // 2, int(c) % 2) for c in row[:8] if c >= 0)
        members = order[bounds[gi] : bounds[gi + 1]]
        for b0 in range(0, len(members), batch):
            part = members[b0 : b0 + batch]
            flush(sig, [(int(base[i]), int(lidx[i]), jac_of[i]) for i in part])
    del keys_of, jac_of
    # ---- group `group` consecutive frames per block (fewer, larger numpy steps; the matrix
    # stays block tridiagonal), padding with decoupled identity frames
    g = max(1, int(group))
    ng = -(-n // g)
    S = g * s
    Dp = np.zeros((ng * g, s, s))
    Dp[:n] = D
    Dp[n:] = np.eye(s)
    Ep = np.zeros((ng * g, s, s))
    Ep[: n - 1] = E
    D = E = np.empty((0, s, s))  # release the blocks (flush, above, is done with them)
    Dg = np.zeros((ng, S, S))
    for i in range(g):
        Dg[:, i * s : (i + 1) * s, i * s : (i + 1) * s] = Dp[i::g]
        if i < g - 1:
            Dg[:, i * s : (i + 1) * s, (i + 1) * s : (i + 2) * s] = Ep[i::g]
            Dg[:, (i + 1) * s : (i + 2) * s, i * s : (i + 1) * s] = Ep[i::g].transpose(0, 2, 1)
    Eg = np.zeros((max(ng - 1, 0), S, S))
    Eg[:, (g - 1) * s :, :s] = Ep[g - 1 :: g][: ng - 1]
    del Dp, Ep
    xrows = (np.arange(g)[:, None] * s + np.arange(6)[None, :]).ravel()  # pose rows in a block
    # ---- block LDL^T of A, forward
    Pinv = np.empty((ng, S, S))
    G = np.empty((ng, S, S))  # G[b] = P_{b-1}^-1 E_{b-1}, b >= 1
    inv = np.linalg.inv
    Pinv[0] = inv(Dg[0])
    for b in range(1, ng):
        G[b] = Pinv[b - 1] @ Eg[b - 1]
        Pinv[b] = inv(Dg[b] - Eg[b - 1].T @ G[b])
    del Dg, Eg
    # ---- diagonal blocks of A^-1, backward
    cov = np.empty((ng * g, 6, 6))
    Sk = Pinv[ng - 1]
    for b in range(ng - 1, -1, -1):
        if b < ng - 1:
            Gb = G[b + 1]
            Sk = Pinv[b] + Gb @ Sk @ Gb.T
        for i in range(g):
            cov[b * g + i] = Sk[i * s : i * s + 6, i * s : i * s + 6]
    cov = cov[:n].copy()
    if m == 0:
        return _sym(cov), np.zeros((0, 3, 3)), np.zeros((0, 6, 6))
    # ---- loads: W = A^-1 C, all load columns at once.  C is kept as, per block row with
    # entries, (its load columns, the dense S x k block); the forward sweep (Y = L^-1 C) keeps
    # every K-th Y only and the backward sweep recomputes each segment from its checkpoint
    # (memory ~2 sqrt(N) S m instead of N S m, one extra forward sweep)
    rows = np.concatenate(c_rows) if c_rows else np.zeros(0, np.int64)
    cols = np.concatenate(c_cols) if c_cols else np.zeros(0, np.int64)
    vals = np.concatenate(c_vals) if c_vals else np.zeros(0)
    blk, loc = rows // S, rows % S
    pair, pair_of = np.unique(blk * m + cols, return_inverse=True)
    dense = np.zeros((len(pair), S))
    np.add.at(dense, (pair_of.ravel(), loc), vals)
    pblk, pcol = pair // m, pair % m
    cut = np.flatnonzero(np.diff(pblk)) + 1
    # (no entries at all: every load factor was removed and weak priors hold the loads)
    c_blocks = (
        {int(pblk[a]): (pcol[a:e], dense[a:e].T.copy()) for a, e in zip(np.r_[0, cut], np.r_[cut, len(pair)])}
        if len(pair)
        else {}
    )
    del rows, cols, vals, blk, loc, pair, pair_of, dense
    K = max(1, int(np.ceil(np.sqrt(ng))))
    ck = np.empty((-(-ng // K), S, m))
    Y = np.zeros((S, m))
    for b in range(ng):  # forward: Y_b = C_b - G_b^T Y_{b-1}
        if b > 0:
            Y = -(G[b].T @ Y)
        if b in c_blocks:
            cb, db = c_blocks[b]
            Y[:, cb] += db
        if b % K == 0:
            ck[b // K] = Y
    # pose rows of W; float32 when float64 would pass work_mb * 4 (relative error ~1e-7 on the
    # load term of the pose covariance, far below anything it is used for)
    WX = np.empty((ng, 6 * g, m), np.float64 if n * 6 * m * 8 <= work_mb * 4 * 2**20 else np.float32)
    CtW = np.zeros((m, m))
    seg = np.empty((K, S, m))
    W_next = None
    for a in range(((ng - 1) // K) * K, -1, -K):
        e = min(a + K, ng)
        Y = ck[a // K]
        seg[0] = Y
        for b in range(a + 1, e):
            Y = -(G[b].T @ Y)
            if b in c_blocks:
                cb, db = c_blocks[b]
                Y[:, cb] += db
            seg[b - a] = Y
        for b in range(e - 1, a - 1, -1):  # backward: W_b = P_b^-1 Y_b - G_{b+1} W_{b+1}
            W = Pinv[b] @ seg[b - a]
            if W_next is not None:
                W -= G[b + 1] @ W_next
            WX[b] = W[xrows]
            if b in c_blocks:
                cb, db = c_blocks[b]
                CtW[cb] += db.T @ W
            W_next = W
    WX = WX.reshape(ng * g, 6, m)[:n]
    Sc_inv = _spd_inv(Dl_full - 0.5 * (CtW + CtW.T))
    for a in range(0, n, BORDER_BLOCK_FRAMES):  # in frame blocks: WX @ Sc^-1 would be another WX
        w = np.asarray(WX[a : a + BORDER_BLOCK_FRAMES], np.float64)
        cov[a : a + BORDER_BLOCK_FRAMES] += np.matmul(np.matmul(w, Sc_inv), w.transpose(0, 2, 1))
    lcov = np.array([Sc_inv[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] for j in range(n_loads)]).reshape(-1, 3, 3)
    f0 = border_first[_F]
    ccov = np.array(
        [Sc_inv[f0 + 6 * c : f0 + 6 * c + 6, f0 + 6 * c : f0 + 6 * c + 6] for c in range(n_codes)]
    ).reshape(-1, 6, 6)
    return _sym(cov), _sym(lcov), _sym(ccov)


def _spd_inv(M: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix through its Cholesky factor."""
    Li = np.linalg.inv(np.linalg.cholesky(0.5 * (M + M.T)))
    return Li.T @ Li


def _sym(M: np.ndarray) -> np.ndarray:
    return 0.5 * (M + np.swapaxes(M, -1, -2))
