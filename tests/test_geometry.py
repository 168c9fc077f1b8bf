import numpy as np
import pytest

from taichi_gs import geometry as g


def random_twist(rng, scale=1.0):
    return rng.normal(size=6) * scale


@pytest.mark.parametrize("seed", range(5))
def test_se3_exp_log_round_trip(seed):
    rng = np.random.default_rng(seed)
    xi = random_twist(rng)
    xi[3:] *= 2.5 / max(np.linalg.norm(xi[3:]), 1e-9)  # rotation angle 2.5 rad
    assert np.allclose(g.se3_log(g.se3_exp(xi)), xi, atol=1e-9)


def test_so3_log_near_pi():
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    phi = axis * (np.pi - 1e-6)
    assert np.allclose(g.so3_exp(g.so3_log(g.so3_exp(phi))), g.so3_exp(phi), atol=1e-6)


def test_se3_exp_small_angle_matches_first_order():
    xi = np.array([0.1, -0.2, 0.3, 1e-10, -2e-10, 3e-10])
    T = g.se3_exp(xi)
    assert np.allclose(T[:3, 3], xi[:3]) and np.allclose(T[:3, :3], np.eye(3), atol=1e-9)


def test_quaternion_round_trip_and_convention():
    q = np.array([np.cos(0.4), 0.0, 0.0, np.sin(0.4)])  # w x y z: rotation of 0.8 rad about z
    R = g.quat_to_rotmat(q)
    assert np.allclose(R, g.so3_exp([0, 0, 0.8]))
    assert np.allclose(g.rotmat_to_quat(R), q)
    rng = np.random.default_rng(3)
    for _ in range(20):
        R = g.so3_exp(rng.normal(size=3) * 2)
        assert np.allclose(g.quat_to_rotmat(g.rotmat_to_quat(R)), R, atol=1e-12)


def test_interpolate_endpoints_and_midpoint():
    rng = np.random.default_rng(1)
    A, B = g.se3_exp(random_twist(rng, 0.5)), g.se3_exp(random_twist(rng, 0.5))
    assert np.allclose(g.interpolate(A, B, 0.0), A) and np.allclose(g.interpolate(A, B, 1.0), B)
    M = g.interpolate(A, B, 0.5)
    # The midpoint is equidistant (geodesically) from both ends.
    assert np.allclose(np.linalg.norm(g.se3_log(g.invert(A) @ M)), np.linalg.norm(g.se3_log(g.invert(M) @ B)))


def test_backproject_project_round_trip():
    K = g.intrinsics_matrix(100.0, 110.0, 31.5, 23.5)
    depth = np.random.default_rng(0).uniform(0.5, 3.0, size=(48, 64))
    P = g.backproject(depth, K)
    uv = g.project(P, K)
    v, u = np.mgrid[0:48, 0:64]
    assert np.allclose(uv[..., 0], u) and np.allclose(uv[..., 1], v) and np.allclose(P[..., 2], depth)


def test_raster_intrinsics_shifts_half_pixel():
    K = g.intrinsics_matrix(100.0, 100.0, 10.0, 20.0)
    assert np.allclose(g.raster_intrinsics(K)[:2, 2], [10.5, 20.5]) and K[0, 2] == 10.0


def test_quaternions_convert_in_batches():
    quats = np.array([[2 * np.cos(0.4), 0, 0, 2 * np.sin(0.4)],  # 0.8 rad about z, not unit: normalised first
                      [0.5, 0, 0, 0],  # identity
                      [0, 3, 0, 0]])  # pi about x
    batch = g.quat_to_rotmat(quats)
    assert batch.shape == (3, 3, 3)
    np.testing.assert_allclose(batch[0], g.so3_exp([0, 0, 0.8]), atol=1e-12)
    np.testing.assert_allclose(batch[1], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(batch[2], np.diag([1.0, -1.0, -1.0]), atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-4, 0.015, 0.025, 0.3, 2.0])
def test_se3_jacobians_match_central_differences(angle):
    """exp(xi + d) = exp(J_l d) exp(xi) = exp(xi) exp(J_r d) to first order, on both sides of the series
    switch (0.02 rad) and at large angles; J_r is the left Jacobian at -xi. The step is 1e-4: at 1e-6 the
    differences of se3_log near zero rotation lose ~1e-5 to cancellation in its own Jacobian."""
    rng = np.random.default_rng(int(angle * 1000) + 1)
    axis = rng.normal(size=3)
    xi = np.concatenate([rng.normal(size=3) * 0.4, angle * axis / np.linalg.norm(axis)])
    h = 1e-4
    T_inv = np.linalg.inv(g.se3_exp(xi))
    numeric_right = np.stack([(g.se3_log(T_inv @ g.se3_exp(xi + h * e)) - g.se3_log(T_inv @ g.se3_exp(xi - h * e)))
                              / (2 * h) for e in np.eye(6)], axis=1)
    numeric_left = np.stack([(g.se3_log(g.se3_exp(xi + h * e) @ T_inv) - g.se3_log(g.se3_exp(xi - h * e) @ T_inv))
                             / (2 * h) for e in np.eye(6)], axis=1)
    np.testing.assert_allclose(g.se3_right_jacobian(xi), numeric_right, atol=1e-7)
    np.testing.assert_allclose(g.se3_left_jacobian(xi), numeric_left, atol=1e-7)
    assert np.abs(g.se3_left_jacobian(xi)[:3, 3:]).max() > 0.05  # the Q block is exercised
