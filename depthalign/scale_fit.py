"""A depth map fitted to the layout's depth: RANSAC on minimal samples, least squares on the
inliers, then IRLS with Tukey's biweight. The depth model decides the unknowns: metric distance
d = s*v, affine depth d = s*v + t, affine inverse depth (Depth Anything) 1/d = s*v + t."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runfs.errors import PanoError


@dataclass
class ScaleFit:
    kind: str
    scale: float
    shift: float
    inlier_share: float
    residual_m: float
    num_pixels: int

    def apply(self, values: np.ndarray) -> np.ndarray:
        return values_to_depth(values, self.kind, self.scale, self.shift)

    def times(self, factor: float) -> tuple[float, float]:
        """(scale, shift) that give `factor` times the fitted depth through `values_to_depth`."""
        if self.kind == "disparity":
            return self.scale / factor, self.shift / factor
        return self.scale * factor, self.shift * factor


def values_to_depth(values: np.ndarray, kind: str, scale: float = 1.0, shift: float = 0.0) -> np.ndarray:
    """Metres along the ray from a depth stage map; NaN where invalid (or non-positive)."""
    v = np.asarray(values, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        if kind == "metric":
            d = scale * v
        elif kind == "relative":
            d = scale * v + shift
        elif kind == "disparity":
            d = 1.0 / (scale * v + shift)
        else:
            raise ValueError(f"unknown depth kind {kind!r}")
    return np.where(np.isfinite(d) & (d > 0), d, np.nan)


def _design(v: np.ndarray, target: np.ndarray, kind: str):
    """Linear model x @ beta ~ y with weights w that make w * residual a relative depth error."""
    if kind == "metric":
        return v[:, None], target, 1.0 / target
    if kind == "relative":
        return np.stack([v, np.ones_like(v)], 1), target, 1.0 / target
    if kind == "disparity":  # 1/D ~ s v + t; D * (s v + t - 1/D) ~ the relative depth error
        return np.stack([v, np.ones_like(v)], 1), 1.0 / target, target
    raise ValueError(f"unknown depth kind {kind!r}")


TUKEY_C = 4.685  # Tukey biweight tuning constant: 95 % efficiency under Gaussian noise


def _irls_tukey(x, y, w, beta, threshold: float, m: int, iterations: int = 50) -> np.ndarray:
    """Iteratively reweighted least squares with Tukey's biweight on the relative residuals
    w*(x@beta - y), from `beta`. The residual scale is 1.4826*MAD of the residuals within
    `threshold`, re-estimated each iteration; the cut-off c = 4.685*scale never exceeds `threshold`.
    Pixels beyond c get weight 0 (furniture, clutter), those near 0 weight ~1."""
    for _ in range(iterations):
        r = w * (x @ beta - y)
        near = np.abs(r) < threshold
        if near.sum() <= 10 * m:
            break
        sigma = 1.4826 * float(np.median(np.abs(r[near])))
        c = min(threshold, max(TUKEY_C * sigma, 1e-6))
        u = r / c
        tw = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
        sw = w * np.sqrt(tw)
        if (tw > 0).sum() <= 10 * m:
            break
        new, *_ = np.linalg.lstsq(x * sw[:, None], y * sw, rcond=None)
        done = np.all(np.abs(new - beta) <= 1e-10 + 1e-8 * np.abs(beta))
        beta = new
        if done:
            break
    return beta


def fit_scale(
    values: np.ndarray,
    layout: np.ndarray,
    kind: str,
    *,
    inlier_threshold: float,
    min_inlier_share: float,
    min_pixels: int,
    ransac_iterations: int,
    max_pixels: int,
    seed: int,
    where: str | Path | None = "align",
) -> ScaleFit:
    """Robustly fit depth/disparity `values` to `layout` depth (metres) on pixels where both are valid.

    RANSAC over minimal samples scores hypotheses by the share of pixels whose
    relative depth error is below `inlier_threshold`; the best is refined by
    weighted least squares on its inliers until the inlier set settles, then
    by IRLS with Tukey's biweight (`_irls_tukey`). Metric: d = s*v; relative:
    d = s*v + t; disparity: 1/d = s*v + t (scale and shift in inverse depth).
    Raises PanoError when too few pixels exist or agree. The settings' defaults are the align
    stage's (`stages.align.fit_settings`).
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    D = np.asarray(layout, dtype=np.float64).reshape(-1)
    ok = np.isfinite(v) & np.isfinite(D) & (D > 0)
    if kind != "relative":
        ok &= v > 0  # metric depth and disparity are positive where valid
    v, D = v[ok], D[ok]
    n = len(v)
    if n < min_pixels:
        raise PanoError(
            where, f"only {n} valid depth pixels on the layout's walls/floor/ceiling (need {min_pixels})"
        )
    rng = np.random.default_rng(seed)
    if n > max_pixels:
        sel = rng.choice(n, max_pixels, replace=False)
        v, D = v[sel], D[sel]
        n = max_pixels
    x, y, w = _design(v, D, kind)
    m = x.shape[1]

    # RANSAC: hypotheses from minimal samples, scored on a fixed subset.
    score_idx = rng.choice(n, min(n, 20_000), replace=False)
    xs, ys, ws = x[score_idx], y[score_idx], w[score_idx]
    samples = rng.integers(0, n, size=(ransac_iterations, m))
    A = x[samples]  # [I,m,m]
    b = y[samples]  # [I,m]
    if m == 1:
        beta = (b / A[..., 0])[:, :1]
    else:
        det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
        good = np.abs(det) > 1e-12 * (np.abs(A[:, :, 0]).max(1) + 1e-30)
        det = np.where(good, det, 1.0)
        s = (b[:, 0] * A[:, 1, 1] - b[:, 1] * A[:, 0, 1]) / det
        t = (A[:, 0, 0] * b[:, 1] - A[:, 1, 0] * b[:, 0]) / det
        beta = np.stack([np.where(good, s, np.nan), np.where(good, t, np.nan)], 1)
    err = np.abs(ws[None] * (beta @ xs.T - ys[None]))  # [I,S]
    counts = np.where(np.isfinite(err), err < inlier_threshold, False).sum(1)
    best = beta[int(np.argmax(counts))]

    # Refinement: weighted least squares on the inliers until they stop changing.
    inl = np.abs(w * (x @ best - y)) < inlier_threshold
    for _ in range(30):
        if inl.sum() < m:
            break
        sw = w[inl][:, None]
        best_new, *_ = np.linalg.lstsq(x[inl] * sw, y[inl] * w[inl], rcond=None)
        inl_new = np.abs(w * (x @ best_new - y)) < inlier_threshold
        best = best_new
        if np.array_equal(inl_new, inl):
            break
        inl = inl_new
    share = float(inl.mean()) if n else 0.0
    # Then Tukey's biweight by IRLS from there: clutter within the user threshold (furniture against
    # a wall) weighs less the further it lies, and clean pixels are not cut off at a hard edge.
    best = _irls_tukey(x, y, w, best, inlier_threshold, m)
    inl = np.abs(w * (x @ best - y)) < inlier_threshold
    share = float(inl.mean()) if n else 0.0
    scale = float(best[0])
    shift = float(best[1]) if m == 2 else 0.0
    if share < min_inlier_share or not np.isfinite(scale):
        raise PanoError(
            where,
            f"depth does not agree with the layout: {share:.0%} of {n} pixels within "
            f"{inlier_threshold:.0%} after fitting ({kind}), need {min_inlier_share:.0%}",
        )
    pred = values_to_depth(v[inl], kind, scale, shift)
    residual = float(np.nanmedian(np.abs(pred - D[inl]))) if inl.any() else float("nan")
    return ScaleFit(kind, scale, shift, share, residual, n)
