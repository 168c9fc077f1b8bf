"""Rigid-body maths in NumPy: SO(3)/SE(3) exp and log, quaternions, interpolation, projection, and a depth
map's median.

Conventions used everywhere in taichi-gs:
- A pose is a camera-to-world 4x4 matrix with OpenCV camera axes (x right, y down, z forward).
- A twist is a 6-vector ``[rho, phi]``: translation part first, rotation part second.
- Quaternions are ``[w, x, y, z]`` inside the package; TUM files use ``qx qy qz qw`` and are
  converted in :mod:`taichi_gs.io` only.
- Pose perturbations are left-multiplied: ``T' = se3_exp(delta) @ T``.
"""

from __future__ import annotations

import numpy as np

from . import profiling

_SMALL = 1e-10


def skew(v: np.ndarray) -> np.ndarray:
    """Return the 3x3 cross-product matrix of a 3-vector."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix of the axis-angle vector ``phi`` (Rodrigues)."""
    phi = np.asarray(phi, dtype=np.float64)
    theta = np.linalg.norm(phi)
    K = skew(phi)
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    a = np.sin(theta) / theta
    b = (1.0 - np.cos(theta)) / theta**2
    return np.eye(3) + a * K + b * K @ K


def so3_log(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix, robust near 0 and pi."""
    R = np.asarray(R, dtype=np.float64)
    cos_theta = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos_theta)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-6:
        return 0.5 * w
    if np.pi - theta < 1e-4:
        # Near pi: take the axis from the symmetric part, sign from w.
        B = 0.5 * (R + np.eye(3))
        axis = np.sqrt(np.clip(np.diag(B), 0.0, None))
        i = int(np.argmax(axis))
        axis = B[i] / max(axis[i], _SMALL)
        axis /= np.linalg.norm(axis)
        if np.dot(axis, w) < 0:
            axis = -axis
        return theta * axis
    return theta / (2.0 * np.sin(theta)) * w


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(phi)
    K = skew(phi)
    if theta < 1e-8:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return (
        np.eye(3)
        + (1.0 - np.cos(theta)) / theta**2 * K
        + (theta - np.sin(theta)) / theta**3 * K @ K
    )


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 rigid transform of the twist ``xi = [rho, phi]``."""
    xi = np.asarray(xi, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = so3_exp(xi[3:])
    T[:3, 3] = _left_jacobian(xi[3:]) @ xi[:3]
    return T


def se3_left_jacobian(xi: np.ndarray) -> np.ndarray:
    """6x6 left Jacobian of SE(3) at ``xi = [rho, phi]``: ``exp(xi + d) ~ exp(J d) exp(xi)`` (Barfoot's
    closed form, with its Q block; series below 0.02 rad, where the closed form cancels)."""
    xi = np.asarray(xi, dtype=np.float64)
    rho, phi = xi[:3], xi[3:]
    theta = np.linalg.norm(phi)
    P, R = skew(phi), skew(rho)
    if theta < 0.02:
        t2 = theta * theta
        c1, c2, c3 = 1.0 / 6.0 - t2 / 120.0, 1.0 / 24.0 - t2 / 720.0, 1.0 / 120.0 - t2 / 2520.0
    else:
        s, c = np.sin(theta), np.cos(theta)
        c1 = (theta - s) / theta**3
        c2 = (theta * theta + 2.0 * c - 2.0) / (2.0 * theta**4)
        c3 = (2.0 * theta - 3.0 * s + theta * c) / (2.0 * theta**5)
    PR, RP, PRP = P @ R, R @ P, P @ R @ P
    Q = 0.5 * R + c1 * (PR + RP + PRP) + c2 * (P @ PR + RP @ P - 3.0 * PRP) + c3 * (PRP @ P + P @ PRP)
    J = np.zeros((6, 6))
    J[:3, :3] = J[3:, 3:] = _left_jacobian(phi)
    J[:3, 3:] = Q
    return J


def se3_right_jacobian(xi: np.ndarray) -> np.ndarray:
    """6x6 right Jacobian of SE(3): ``exp(xi + d) ~ exp(xi) exp(J d)``; equals the left one at ``-xi``."""
    return se3_left_jacobian(-np.asarray(xi, dtype=np.float64))


def se3_log(T: np.ndarray) -> np.ndarray:
    """Twist ``[rho, phi]`` of a 4x4 rigid transform (inverse of :func:`se3_exp`)."""
    phi = so3_log(T[:3, :3])
    rho = np.linalg.solve(_left_jacobian(phi), T[:3, 3])
    return np.concatenate([rho, phi])


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of T for twists [translation, rotation]: T exp(e) T^-1 = exp(Ad e)."""
    R, t = T[:3, :3], T[:3, 3]
    ad = np.zeros((6, 6))
    ad[:3, :3] = R
    ad[:3, 3:] = skew(t) @ R
    ad[3:, 3:] = R
    return ad


def interpolate(T_a: np.ndarray, T_b: np.ndarray, tau: float) -> np.ndarray:
    """Geodesic SE(3) interpolation: ``T_a`` at tau=0, ``T_b`` at tau=1."""
    return T_a @ se3_exp(tau * se3_log(invert(T_a) @ T_b))


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion ``[w, x, y, z]`` (normalised first); (..., 4) quaternions
    give (..., 3, 3) matrices."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q) if q.ndim == 1 else np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q / norm, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``[w, x, y, z]`` with w >= 0 of a rotation matrix (Shepperd)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def pose_from_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 transform from a rotation matrix and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """3x3 pinhole matrix."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def backproject(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-space points (H x W x 3) of a depth map; pixel centres at integer coordinates.

    Pixel (u, v) of the image array sits at image coordinate (u, v), the OpenCV convention; the
    rasterizer's +0.5 pixel-centre convention applies to its own screen space only.
    """
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    z = depth.astype(np.float64)
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=-1)


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates (... x 2) of camera-space points (... x 3)."""
    z = points[..., 2]
    u = K[0, 0] * points[..., 0] / z + K[0, 2]
    v = K[1, 1] * points[..., 1] / z + K[1, 2]
    return np.stack([u, v], axis=-1)


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points of shape (..., 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def fit_scale_translation(source: np.ndarray, target: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray]:
    """Scale s and translation t minimising sum |s source_i + t - target_i|^2 (no rotation) over points (N, 3);
    ``with_scale=False``, or source points that do not spread (one point): the translation alone (s = 1)."""
    source, target = np.asarray(source, dtype=np.float64), np.asarray(target, dtype=np.float64)
    centred = source - source.mean(axis=0)
    spread = (centred ** 2).sum()
    scale = float((centred * (target - target.mean(axis=0))).sum() / spread) if with_scale and spread > 0 else 1.0
    return scale, target.mean(axis=0) - scale * source.mean(axis=0)


def raster_intrinsics(K: np.ndarray) -> np.ndarray:
    """Intrinsics for the rasterizer, whose pixel centres sit at +0.5 (gsplat's convention).

    Data intrinsics follow OpenCV (pixel index u samples image coordinate u); the rasterizer samples
    pixel u at u + 0.5, so the principal point moves by half a pixel.
    """
    K = np.array(K, dtype=np.float64)
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    return K


def exposure_twist(d_start: np.ndarray, d_end: np.ndarray, tau: float, bend: np.ndarray | None = None) -> np.ndarray:
    """The twist at exposure fraction tau, ``(1 - tau) d_start + tau d_end``, plus [ours] ``4 tau (1 - tau) bend``:
    a path bowed by ``bend`` at its middle and not at its ends (None: straight, the method's)."""
    xi = (1.0 - tau) * np.asarray(d_start, dtype=np.float64) + tau * np.asarray(d_end, dtype=np.float64)
    return xi if bend is None else xi + 4.0 * tau * (1.0 - tau) * np.asarray(bend, dtype=np.float64)


def virtual_pose(base: np.ndarray, d_start: np.ndarray, d_end: np.ndarray, tau: float,
                 bend: np.ndarray | None = None) -> np.ndarray:
    """Pose at exposure fraction tau: ``base @ exp(exposure_twist(d_start, d_end, tau, bend))``."""
    return base @ se3_exp(exposure_twist(d_start, d_end, tau, bend))


def relative_pose_gradients(anchor: np.ndarray, g_relative: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Given dL/d epsilon (V, 6) of ``exp(epsilon) @ invert(anchor) @ target_i`` for V targets (left
    perturbations in the anchor's camera frame, [translation, rotation]), the gradients of the left
    perturbations of the camera-to-world poses: (dL/d each target's (V, 6), dL/d the anchor's (6,)).
    ``exp(d) @ target`` moves the relative pose by ``Ad(anchor^-1) d``, ``exp(d) @ anchor`` by minus that
    (so the targets themselves do not enter)."""
    g = np.atleast_2d(np.asarray(g_relative, dtype=np.float64)) @ adjoint(invert(anchor))
    return g, -g.sum(axis=0)


@profiling.timed("exposure gradients (host)")
def exposure_pose_gradients(
    base: np.ndarray, d_start: np.ndarray, d_end: np.ndarray, taus, pose_grads, bend: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chain the rasterizer's pose gradients of the k virtual views (left perturbations, one 6-vector
    per tau) to the exposure offsets: returns (dL/d d_start, dL/d d_end, dL/d bend) for :func:`virtual_pose`.

    Uses dL/dxi = J_r(xi)^T Ad(T_v)^T g_v with xi = :func:`exposure_twist` and J_r in closed
    form (:func:`se3_right_jacobian`)."""
    g_start, g_end, g_bend = np.zeros(6), np.zeros(6), np.zeros(6)
    for tau, g in zip(taus, pose_grads):
        xi = exposure_twist(d_start, d_end, tau, bend)
        g_xi = se3_right_jacobian(xi).T @ (adjoint(base @ se3_exp(xi)).T @ np.asarray(g, dtype=np.float64))
        g_start += (1.0 - tau) * g_xi
        g_end += tau * g_xi
        g_bend += 4.0 * tau * (1.0 - tau) * g_xi
    return g_start, g_end, g_bend


def median_depth(depth: np.ndarray, default: float = 1.0) -> float:
    """Median valid (> 0) depth of a frame, ``default`` (1 m) without any."""
    valid = depth[depth > 0]
    return float(np.median(valid)) if valid.size else default


def median_depths(depths: list[np.ndarray]) -> np.ndarray:
    """Each frame's :func:`median_depth`; a frame without valid depth (a dropped sensor frame) takes the median of
    the others' (1 m when none has any), so that its exposure's length in pixels stays at the scene's depth."""
    medians = np.array([median_depth(d, default=np.nan) for d in depths])
    missing = np.isnan(medians)
    medians[missing] = median_depth(medians[~missing])
    return medians
