"""Corner noise of QR detections as whitening matrices: W_i (z_i - h_i) has identity covariance,
so every solver minimises (and every covariance uses) the same weighted reprojection error."""

from __future__ import annotations

import math

import numpy as np

from fusion.qr.refine import FALLBACK_SIGMA_PX

DEFAULT_CORNER_SIGMA_PX = 0.15
"""Refined-corner error per pixel coordinate (DESIGN.md: about 0.13 px mean after refinement)."""
CORNER_COORDINATES = 8
"""Residuals per code: u, v of its four corners (TL, TR, BR, BL)."""
CORNER_CLASSES = ("refined", "decoder")
"""Corner classes with their own noise scale (fusion.estimate.variance.pnp_class_components):
corners refined with their own calibrated sigma, and the decoder's corners kept with
FALLBACK_SIGMA_PX (refinement failed its self-check or could not measure the code)."""


def corner_whitening(detections, default_sigma_px: float) -> np.ndarray:
    """(n, 8, 8) whitening matrices W_i = L_i^-1 of each detection's corner covariance
    C_i = L_i L_i^T (Cholesky; order TL u, TL v, TR u, ..., BL v), so that W_i (z_i - h_i) has
    identity covariance: `corner_cov_px2` when set and positive definite (the corners come from
    one homography fit, so their errors are correlated), else diag(1 / sigma) with sigma the
    detection's `corner_sigma_px` or `default_sigma_px` (`corner_sigmas`)."""
    n = CORNER_COORDINATES
    sig = corner_sigmas(detections, default_sigma_px).reshape(-1, n)
    out = np.zeros((len(sig), n, n))
    idx = np.arange(n)
    out[:, idx, idx] = 1.0 / sig
    with_cov: list[int] = []
    covs: list[np.ndarray] = []
    for i, d in enumerate(detections):
        cov = getattr(d, "corner_cov_px2", None)
        if cov is not None:
            cov = np.asarray(cov, dtype=float)
            if cov.shape == (n, n):
                with_cov.append(i)
                covs.append(cov)
    if covs:
        C = np.stack(covs)
        finite = np.isfinite(C).all(axis=(1, 2))
        with_cov, C = [i for i, f in zip(with_cov, finite) if f], C[finite]
        if with_cov:
            C = 0.5 * (C + np.swapaxes(C, 1, 2))
            try:
                out[with_cov] = np.linalg.inv(np.linalg.cholesky(C))
            except np.linalg.LinAlgError:  # one is not positive definite: one at a time
                for i, Ci in zip(with_cov, C):
                    try:
                        out[i] = np.linalg.inv(np.linalg.cholesky(Ci))
                    except np.linalg.LinAlgError:
                        pass  # keeps diag(1 / sigma)
    return out


def corner_sigmas(detections, default_sigma_px: float) -> np.ndarray:
    """Per-residual 1-sigma (8 per detection: u, v of its 4 corners), px: each detection's own
    `corner_sigma_px` when it has one (fusion.qr.refine's calibrated value), else the default."""
    out = []
    for d in detections:
        s = getattr(d, "corner_sigma_px", None)
        out.append(float(s) if s is not None and math.isfinite(s) and s > 0 else float(default_sigma_px))
    return np.repeat(np.asarray(out, dtype=float), CORNER_COORDINATES)


def corner_classes(detections) -> np.ndarray:
    """(n,) index into CORNER_CLASSES of each detection: "decoder" when its corner_sigma_px is
    FALLBACK_SIGMA_PX (fusion.qr.refine's fallback and detect's unrefined corners), else
    "refined" (a detection without a sigma gets the refined default, DEFAULT_CORNER_SIGMA_PX)."""
    out = np.zeros(len(detections), dtype=np.int64)
    for i, d in enumerate(detections):
        s = getattr(d, "corner_sigma_px", None)
        if s is not None and math.isclose(float(s), FALLBACK_SIGMA_PX):
            out[i] = CORNER_CLASSES.index("decoder")
    return out
