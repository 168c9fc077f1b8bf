"""The three loss terms of stage 1 as residuals with analytic Jacobians, for robust Gauss-Newton.

The unknown is T, the 4x4 transform from camera t to camera t+1. Jacobians are taken with respect to
a left perturbation ``T' = se3_exp(delta) @ T``, ``delta = [rho, phi]`` (the package's convention).
Each term returns per-point residual vectors; the stage minimises the sum of their L2 norms
(flow: 2-vectors; photometric and depth consistency: scalars, i.e. L1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..sampling import bilinear, bilinear_depth, nearest_pixel

_TINY = 1e-12


@dataclass(frozen=True)
class PairSamples:
    """What the terms need from a frame pair: sampled source pixels and the target's images.

    ``points`` are the back-projected source pixels P_i (camera t), ``pixels`` their image
    coordinates p_i, ``flow`` the optical flow F(p_i) and ``intensity`` I_t(p_i); ``target_*`` are
    the grey image, its gradients and the depth of frame t+1 (H x W).
    """

    points: np.ndarray
    pixels: np.ndarray
    flow: np.ndarray
    intensity: np.ndarray
    K: np.ndarray
    target_gray: np.ndarray
    target_gradient: np.ndarray
    target_depth: np.ndarray
    target_normals: np.ndarray | None = None  # H x W x 3 unit normals of frame t+1 (NaN: none), for L_P


@dataclass(frozen=True)
class Warp:
    """Source points moved into camera t+1 and projected: Q = T P_i, p_j = pi(K, Q).

    ``valid`` is the mask M_t+1(p_j): Q in front of the camera, p_j inside the image with valid
    target depth at all four bilinear neighbours. ``target_depth`` is D_t+1(p_j), bilinear, with its
    image gradient ``target_depth_gradient`` (N x 2). ``pixel_jacobian`` is d p_j / d delta (N x 2 x 6);
    d Q / d delta is [I | -[Q]x].
    """

    T: np.ndarray
    Q: np.ndarray
    pixels: np.ndarray
    pixel_jacobian: np.ndarray
    valid: np.ndarray
    target_depth: np.ndarray
    target_depth_gradient: np.ndarray


@dataclass(frozen=True)
class Residuals:
    """Per-point residual vectors (N x k) and their Jacobians (N x k x 6)."""

    values: np.ndarray
    jacobian: np.ndarray

    def norms(self) -> np.ndarray:
        return np.linalg.norm(self.values, axis=1)


def image_gradient(gray: np.ndarray) -> np.ndarray:
    """Central-difference gradient (d/du, d/dv) of a grey image, H x W x 2."""
    gv, gu = np.gradient(gray.astype(np.float64))
    return np.stack([gu, gv], axis=-1)


def cross_matrices(vectors: np.ndarray) -> np.ndarray:
    """Skew (cross-product) matrices of N 3-vectors, N x 3 x 3."""
    x, y, z = vectors[:, 0], vectors[:, 1], vectors[:, 2]
    zero = np.zeros_like(x)
    return np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], axis=1)


def pixel_jacobian(Q: np.ndarray, K: np.ndarray) -> np.ndarray:
    """d pi(K, Q') / d delta at delta = 0 for Q' = Q + rho + phi x Q (N x 2 x 6): the projection's
    derivative [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] times dQ'/d delta = [I | -[Q]x], written out."""
    x, y, z = Q[:, 0], Q[:, 1], Q[:, 2]
    inv_z = 1.0 / z
    xz, yz = x * inv_z, y * inv_z
    fx, fy = K[0, 0], K[1, 1]
    J = np.zeros((len(Q), 2, 6))
    J[:, 0, 0] = fx * inv_z
    J[:, 0, 2] = -fx * xz * inv_z
    J[:, 0, 3] = -fx * xz * yz
    J[:, 0, 4] = fx * (1.0 + xz * xz)
    J[:, 0, 5] = -fx * yz
    J[:, 1, 1] = fy * inv_z
    J[:, 1, 2] = -fy * yz * inv_z
    J[:, 1, 3] = -fy * (1.0 + yz * yz)
    J[:, 1, 4] = fy * xz * yz
    J[:, 1, 5] = fy * xz
    return J


def chain(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """The chain rule per point: (N x a) d f / d x times (N x a x b) d x / d y, giving d f / d y (N x b)."""
    return np.sum(outer[:, :, None] * inner, axis=1)


def warp(T: np.ndarray, samples: PairSamples, min_depth: float = 1e-3) -> Warp:
    """Move the source points by T, project them into frame t+1 and look up its depth."""
    Q = samples.points @ T[:3, :3].T + T[:3, 3]
    front = Q[:, 2] > min_depth
    Q_safe = np.where(front[:, None], Q, np.array([0.0, 0.0, 1.0]))
    K = samples.K
    pixels = np.stack([K[0, 0] * Q_safe[:, 0] / Q_safe[:, 2] + K[0, 2], K[1, 1] * Q_safe[:, 1] / Q_safe[:, 2] + K[1, 2]], -1)
    depth, depth_gradient, depth_valid = bilinear_depth(samples.target_depth, pixels)
    return Warp(T, Q, pixels, pixel_jacobian(Q_safe, K), front & depth_valid, depth, depth_gradient)


def flow_residuals(w: Warp, samples: PairSamples) -> Residuals:
    """L_F: e_i = F(p_i) - (p_j - p_i), pixels; minimised as sum |e_i|_2."""
    values = samples.flow - (w.pixels - samples.pixels)
    return Residuals(values, -w.pixel_jacobian)


def photometric_residuals(w: Warp, samples: PairSamples) -> Residuals:
    """L_I: r_i = I_t(p_i) - I_t+1(p_j) on grey values in [0, 1]; minimised as sum |r_i|."""
    target, _ = bilinear(samples.target_gray, w.pixels)
    gradient, _ = bilinear(samples.target_gradient, w.pixels)
    values = (samples.intensity - target)[:, None]
    jacobian = -chain(gradient, w.pixel_jacobian)[:, None, :]
    return Residuals(values, jacobian)


def baseline_distance(points: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """h = |P| sin(angle(P, c)) = |P x c| / |c|, with dh/dP and dh/dc (each N x 3)."""
    c_norm = np.linalg.norm(direction)
    u = np.cross(points, direction)
    u_norm = np.linalg.norm(u, axis=1)
    u_hat = u / np.maximum(u_norm, _TINY)[:, None]
    d_points = np.cross(direction, u_hat) / c_norm  # u_hat^T (-[c]x) = c x u_hat
    d_direction = np.cross(u_hat, points) / c_norm - u_norm[:, None] * direction / c_norm**3
    return u_norm / c_norm, d_points, d_direction


def target_points(w: Warp, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frame t+1's surface points P_j = D_t+1(p_j) K^-1 [p_j, 1] where the warp lands, and dP_j / dp_j (N x 3 x 2)."""
    rays = np.stack([(w.pixels[:, 0] - K[0, 2]) / K[0, 0], (w.pixels[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(w.pixels))], -1)
    dP_dpixel = rays[:, :, None] * w.target_depth_gradient[:, None, :]
    dP_dpixel[:, 0, 0] += w.target_depth / K[0, 0]
    dP_dpixel[:, 1, 1] += w.target_depth / K[1, 1]
    return w.target_depth[:, None] * rays, dP_dpixel


def depth_consistency_residuals(w: Warp, samples: PairSamples, min_baseline: float) -> Residuals | None:
    """L_C: r_i = h_i - h_j, metres; minimised as sum |r_i|. None when the baseline is too short.

    Written as the paper writes it, with (R_p, x) the pose of camera t+1 in camera t, i.e. the
    inverse of T: x = -R^T t is the centre of camera t+1 seen from camera t, and -R_p^T x = t the
    centre of camera t seen from camera t+1. h_i = |P_i| sin(angle(P_i, x)) measures P_i's distance
    from the baseline in camera t; h_j = |P_j| sin(angle(P_j, t)) that of P_j = D_t+1(p_j) K^-1 [p_j, 1]
    in camera t+1. Both are the same number at the true pose for a static scene.
    """
    R, t = w.T[:3, :3], w.T[:3, 3]
    if np.linalg.norm(t) < min_baseline:
        return None
    x = -R.T @ t
    h_i, _, dh_i_dx = baseline_distance(samples.points, x)
    dx_ddelta = np.hstack([-R.T, np.zeros((3, 3))])  # x' = -R^T (t + rho): rotation drops out

    P_j, dP_dpixel = target_points(w, samples.K)
    h_j, dh_j_dP, dh_j_dt = baseline_distance(P_j, t)
    dt_ddelta = np.hstack([np.eye(3), -cross_matrices(t[None])[0]])  # t' = t + rho + phi x t
    dh_j = dh_j_dt @ dt_ddelta + chain(chain(dh_j_dP, dP_dpixel), w.pixel_jacobian)
    jacobian = (dh_i_dx @ dx_ddelta - dh_j)[:, None, :]
    return Residuals((h_i - h_j)[:, None], jacobian)


def point_to_plane_residuals(w: Warp, samples: PairSamples, noise: tuple[float, float] = (1.0, 0.0)) -> Residuals:
    """[ours] L_P: r_i = n_j . (Q_i - P_j) / sigma(z_j), with P_j = D_t+1(p_j) K^-1 [p_j, 1], n_j frame t+1's
    normal at the pixel nearest p_j (held fixed, as point-to-plane ICP holds it) and the depth noise
    sigma(z) = noise[0] + noise[1] z^2 (metres; held fixed too: a weight); minimised as sum |r_i|.
    Where frame t+1 has no normal the residual and its Jacobian are 0. Depth pins the motion across the
    surfaces it sees; the flow terms keep the motion along them, where depth alone lets ICP slide."""
    u, v = nearest_pixel(w.pixels, samples.target_depth.shape)
    normals = samples.target_normals[v, u]
    has_normal = np.all(np.isfinite(normals), axis=1)
    scale = 1.0 / (noise[0] + noise[1] * np.square(w.target_depth))
    normals = np.where(has_normal[:, None], normals * scale[:, None], 0.0)
    P_j, dP_dpixel = target_points(w, samples.K)
    values = np.where(has_normal, np.sum(normals * (w.Q - P_j), axis=1), 0.0)
    # n^T dQ/d delta = n^T [I | -[Q]x] = [n, Q x n]
    along_normal = np.concatenate([normals, np.cross(w.Q, normals)], axis=1)
    jacobian = along_normal - chain(chain(normals, dP_dpixel), w.pixel_jacobian)
    return Residuals(np.nan_to_num(values)[:, None], np.nan_to_num(jacobian)[:, None, :])
