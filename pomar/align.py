"""Similarity alignment of point sets (Umeyama 1991): dst ~ s * R @ src + t."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Similarity:
    scale: float
    R: np.ndarray
    t: np.ndarray

    def apply(self, x: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(x) @ self.R.T + self.t


IDENTITY = Similarity(1.0, np.eye(3), np.zeros(3))


def compose(a: Similarity, b: Similarity) -> Similarity:
    """a after b: x -> a(b(x))."""
    return Similarity(a.scale * b.scale, a.R @ b.R, a.scale * a.R @ b.t + a.t)


def inverse(a: Similarity) -> Similarity:
    Rt = a.R.T
    return Similarity(1.0 / a.scale, Rt, -Rt @ a.t / a.scale)


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Similarity:
    """Least-squares similarity taking src (N, 3) onto dst (N, 3); N >= 3 non-collinear points."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or len(src) < 3:
        raise ValueError(f"need two (N>=3, d) arrays of equal shape, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(src.shape[1])
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[-1, -1] = -1
    R = U @ S @ Vt
    var_s = (xs**2).sum() / len(src)
    scale = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0
    return Similarity(scale, R, mu_d - scale * R @ mu_s)
