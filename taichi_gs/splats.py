"""Splats: the Gaussian scene as plain NumPy parameter arrays, and its initialisation from points."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SH_C0 = 0.28209479177387814  # degree-0 spherical-harmonic constant


@dataclass
class Splats:
    """Gaussian parameters in 3DGS's raw form.

    means (N, 3); quats (N, 4) as w x y z, not necessarily unit; log_scales (N, 3);
    opacity_logits (N,); sh (N, M, 3) spherical-harmonic colour coefficients, M in {1, 4, 9, 16},
    the first being the DC term (colour = SH_C0 * dc + 0.5).
    """

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.means)
        shapes = {
            "means": (self.means.shape, (n, 3)),
            "quats": (self.quats.shape, (n, 4)),
            "log_scales": (self.log_scales.shape, (n, 3)),
            "opacity_logits": (self.opacity_logits.shape, (n,)),
        }
        for name, (got, want) in shapes.items():
            if got != want:
                raise ValueError(f"{name} has shape {got}, expected {want}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3 or self.sh.shape[1] not in (1, 4, 9, 16):
            raise ValueError(f"sh has shape {self.sh.shape}, expected ({n}, 1|4|9|16, 3)")

    def __len__(self) -> int:
        return len(self.means)

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    @property
    def opacities(self) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-self.opacity_logits))

    def subset(self, keep: np.ndarray) -> "Splats":
        """The Gaussians selected by a boolean mask or index array."""
        return Splats(self.means[keep], self.quats[keep], self.log_scales[keep], self.opacity_logits[keep], self.sh[keep])


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """DC coefficient that renders as ``rgb`` (inverse of colour = SH_C0 * dc + 0.5)."""
    return (np.asarray(rgb, dtype=np.float32) - 0.5) / SH_C0


def logit(p: np.ndarray | float) -> np.ndarray:
    """Inverse sigmoid."""
    p = np.asarray(p, dtype=np.float64)
    return np.log(p / (1.0 - p))


def splats_from_points(points: np.ndarray, colors: np.ndarray, scale: float, opacity: float = 0.5, sh_degree: int = 0) -> Splats:
    """Isotropic Gaussians, one per point, all with the given scale (metres) and opacity."""
    n = len(points)
    sh = np.zeros((n, (sh_degree + 1) ** 2, 3), dtype=np.float32)
    sh[:, 0] = rgb_to_sh_dc(colors)
    quats = np.zeros((n, 4), dtype=np.float32)
    quats[:, 0] = 1.0
    return Splats(
        means=np.asarray(points, dtype=np.float32),
        quats=quats,
        log_scales=np.full((n, 3), np.log(scale), dtype=np.float32),
        opacity_logits=np.full(n, logit(opacity), dtype=np.float32),
        sh=sh,
    )
