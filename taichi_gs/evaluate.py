"""Metrics: trajectory errors with evo's definitions, and image/depth quality against ground truth.

- ATE: RMSE of position differences after aligning the estimate to the reference with a rigid
  SE(3) Umeyama fit (``evo_ape tum REF EST -a``), metres.
- RPE: for consecutive frames i, i+1, E = (Q_i^-1 Q_{i+1})^-1 (P_i^-1 P_{i+1}) with Q the reference
  and P the estimate; translation error |t(E)| in metres and rotation angle of R(E) in degrees,
  reported as RMSE over pairs (``evo_rpe tum REF EST --delta 1 -r trans_part|angle_deg``).
- [ours] RPE rotation drift: the norm of the *mean* of the same pairs' rotation errors as vectors (log of R(E)),
  in degrees per pair: the systematic part of the RPE rotation, which accumulates along the trajectory, where
  zero-mean noise averages out (a trajectory turned 0.03 deg too little at every pair drifts 0.03 deg/pair).
- [ours] Rotation scale: how much of the reference's turning the estimate turns. For every span of
  ``ROTATION_SCALE_SPAN`` frames, the estimate's rotation over the span (log of P_i^-1 P_{i+span}) projected on
  the axis of the reference's (log of Q_i^-1 Q_{i+span}); the sum of those over the sum of the reference's angles.
  1: turns as much; 0.9: turns 10% too little at every span, long and short (as a focal length 10% long, or a
  reference that over-turns, makes it); noise averages out. Spans the reference turns less than
  ``ROTATION_SCALE_MIN_DEG`` through are left out.
- PSNR, SSIM (Gaussian window sigma 1.5, data range 1, as the 3DGS papers compute it), and RMSE of
  inverse depth (1/m) over pixels where both depths are valid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from .geometry import invert, so3_log

EVO_MAX_TIME_DIFFERENCE = 0.01  # seconds, evo's default for associating trajectories
ROTATION_SCALE_SPAN = 10  # frames per span of the rotation scale (module docstring)
ROTATION_SCALE_MIN_DEG = 0.5  # spans the reference turns less than this through carry no axis to project on


@dataclass(frozen=True)
class TrajectoryErrors:
    """ATE and RPE of an estimate against a reference (evo's definitions, RMSE statistics)."""

    ate_m: float
    rpe_trans_m: float
    rpe_rot_deg: float
    frames: int
    rpe_rot_drift_deg: float = float("nan")  # [ours] degrees per pair, see the module docstring
    rotation_scale: float = float("nan")  # [ours] the estimate's turning over the reference's, see the docstring

    def as_dict(self) -> dict[str, float | int]:
        return {"ate_m": self.ate_m, "rpe_trans_m": self.rpe_trans_m, "rpe_rot_deg": self.rpe_rot_deg,
                "rpe_rot_drift_deg": self.rpe_rot_drift_deg, "rotation_scale": self.rotation_scale,
                "frames": self.frames}


def umeyama_alignment(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising sum |R source_i + t - target_i|^2 (no scale)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    cov = (target - mu_t).T @ (source - mu_s) / len(source)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    return R, mu_t - R @ mu_s


def align_trajectory(est: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Estimated poses (N x 4 x 4) moved rigidly onto the reference by Umeyama on positions."""
    R, t = umeyama_alignment(est[:, :3, 3], ref[:, :3, 3])
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = R, t
    return A @ est


def ate(est: np.ndarray, ref: np.ndarray) -> float:
    """Absolute trajectory error (m): RMSE of positions after rigid alignment."""
    est, ref = _finite_pairs(est, ref)
    if len(est) < 3:
        return float("nan")
    aligned = align_trajectory(est, ref)
    errors = np.linalg.norm(aligned[:, :3, 3] - ref[:, :3, 3], axis=1)
    return float(np.sqrt(np.mean(errors**2)))


def _pair_errors(est: np.ndarray, ref: np.ndarray) -> list[np.ndarray]:
    """E of every consecutive pair whose four poses are finite (the module docstring's RPE)."""
    errors = []
    for i in range(len(est) - 1):
        pair = (est[i], est[i + 1], ref[i], ref[i + 1])
        if all(np.all(np.isfinite(T)) for T in pair):
            errors.append(invert(invert(ref[i]) @ ref[i + 1]) @ (invert(est[i]) @ est[i + 1]))
    return errors


def _rmse_of(errors: list[np.ndarray]) -> tuple[float, float]:
    """(translation RMSE m, rotation RMSE deg) of pair errors E."""
    if not errors:
        return float("nan"), float("nan")
    trans = [np.linalg.norm(E[:3, 3]) for E in errors]
    rot = [rotation_angle_deg(E[:3, :3]) for E in errors]
    return float(np.sqrt(np.mean(np.square(trans)))), float(np.sqrt(np.mean(np.square(rot))))


def _drift_of(errors: list[np.ndarray]) -> float:
    """|mean of log R(E)| of pair errors E, in degrees."""
    if not errors:
        return float("nan")
    return float(np.degrees(np.linalg.norm(np.mean([so3_log(E[:3, :3]) for E in errors], axis=0))))


def rpe(est: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """Relative pose error over consecutive frames: (translation RMSE m, rotation RMSE deg)."""
    return _rmse_of(_pair_errors(est, ref))


def rotation_drift_deg(est: np.ndarray, ref: np.ndarray) -> float:
    """[ours] Degrees per pair of systematic rotation error: |mean over consecutive pairs of log R(E)|, the
    part of the RPE rotation that does not average out along the trajectory."""
    return _drift_of(_pair_errors(est, ref))


def rotation_scale(est: np.ndarray, ref: np.ndarray, span: int = ROTATION_SCALE_SPAN,
                   min_deg: float = ROTATION_SCALE_MIN_DEG) -> float:
    """[ours] How much of the reference's turning the estimate turns over spans of ``span`` frames (the module
    docstring): 1 when it turns as much, below 1 when it turns too little. NaN without a span that the
    reference turns ``min_deg`` or more through with all four poses finite."""
    turned = reference = 0.0
    for i in range(len(est) - span):
        poses = (est[i], est[i + span], ref[i], ref[i + span])
        if not all(np.all(np.isfinite(T)) for T in poses):
            continue
        axis_angle = so3_log(ref[i][:3, :3].T @ ref[i + span][:3, :3])
        angle = float(np.linalg.norm(axis_angle))
        if np.degrees(angle) < min_deg:
            continue
        turned += float(so3_log(est[i][:3, :3].T @ est[i + span][:3, :3]) @ axis_angle) / angle
        reference += angle
    return turned / reference if reference > 0 else float("nan")


def rotation_angle_deg(R: np.ndarray) -> float:
    """Rotation angle of a rotation matrix in degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def trajectory_errors(est: np.ndarray, ref: np.ndarray) -> TrajectoryErrors:
    """ATE and RPE of matched pose lists (frames whose reference is NaN are skipped)."""
    if est.shape != ref.shape:
        raise ValueError(f"estimate has shape {est.shape}, reference {ref.shape}")
    errors = _pair_errors(est, ref)  # once for the RPE and the drift
    trans, rot = _rmse_of(errors)
    frames = len(_finite_pairs(est, ref)[0])
    return TrajectoryErrors(ate(est, ref), trans, rot, frames, _drift_of(errors), rotation_scale(est, ref))


def match_by_time(t_est: np.ndarray, t_ref: np.ndarray, max_difference: float = EVO_MAX_TIME_DIFFERENCE) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (est, ref) of nearest timestamps within ``max_difference``, each used once (evo's rule)."""
    est_idx, ref_idx = [], []
    used = set()
    for i, t in enumerate(t_est):
        j = int(np.argmin(np.abs(t_ref - t)))
        if abs(t_ref[j] - t) <= max_difference and j not in used:
            used.add(j)
            est_idx.append(i)
            ref_idx.append(j)
    return np.array(est_idx, dtype=int), np.array(ref_idx, dtype=int)


def _finite_pairs(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    keep = np.all(np.isfinite(ref.reshape(len(ref), -1)), axis=1) & np.all(np.isfinite(est.reshape(len(est), -1)), axis=1)
    return est[keep], ref[keep]


def psnr(image: np.ndarray, reference: np.ndarray) -> float:
    """Peak signal-to-noise ratio (dB) of images in [0, 1] (inf for identical images)."""
    image, reference = np.clip(image, 0, 1).astype(np.float64), reference.astype(np.float64)
    if np.array_equal(image, reference):
        return float("inf")
    return float(peak_signal_noise_ratio(reference, image, data_range=1.0))


def ssim(image: np.ndarray, reference: np.ndarray) -> float:
    """SSIM with an 11x11 Gaussian window (sigma 1.5), data range 1, mean over channels."""
    return float(structural_similarity(
        np.clip(image, 0, 1).astype(np.float64), reference.astype(np.float64),
        gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=2,
    ))


def inverse_depth_rmse(depth: np.ndarray, reference: np.ndarray) -> float:
    """RMSE of 1/depth (1/m) over pixels where both depths are positive."""
    valid = (depth > 0) & (reference > 0)
    if not np.any(valid):
        return float("nan")
    diff = 1.0 / depth[valid].astype(np.float64) - 1.0 / reference[valid].astype(np.float64)
    return float(np.sqrt(np.mean(diff**2)))
