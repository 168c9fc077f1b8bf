"""[ours] Depth moved to its colour's instant (stages/deblur/depth_instant.py): the moved depth is the depth the moved
camera sees, the nearer surface wins, and only training frames whose depth was taken apart from their colour move."""

import numpy as np

from taichi_gs.geometry import invert, se3_exp
from taichi_gs.stages.deblur.depth_instant import colour_instant_motions, moved_depth
from taichi_gs.stages.deblur.exposures import DepthMoments
from taichi_gs.stages.deblur.frames import _load_frames

W, H = 80, 60
K = np.array([[70.0, 0.0, 39.5], [0.0, 70.0, 29.5], [0.0, 0.0, 1.0]])
PLANE_N, PLANE_D = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0]), 2.0  # n . x = d in the world


def plane_depth(cam_to_world: np.ndarray) -> np.ndarray:
    """Depth (z) of the world plane n . x = d seen by a pinhole camera at ``cam_to_world``, by ray casting."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)  # z = 1
    R, c = cam_to_world[:3, :3], cam_to_world[:3, 3]
    return (PLANE_D - PLANE_N @ c) / (rays @ R.T @ PLANE_N)  # z along each ray where it meets the plane


def test_moved_depth_is_what_the_moved_camera_sees_of_a_tilted_plane():
    depth_pose = np.eye(4)
    colour_pose = depth_pose @ se3_exp(np.array([0.04, -0.02, 0.03, 0.01, -0.02, 0.015]))
    motion = invert(colour_pose) @ depth_pose  # depth-camera points into the colour camera
    moved = moved_depth(plane_depth(depth_pose), K, motion)
    truth = plane_depth(colour_pose)
    valid = moved > 0
    assert valid.mean() > 0.75  # the moved camera sees most of what the depth camera saw
    slope = np.abs(np.gradient(truth)).max()  # landing on the pixels around: at most about a pixel's change
    assert np.abs(moved[valid] - truth[valid]).max() < slope
    raw_error = np.abs(plane_depth(depth_pose) - truth)[valid].mean()
    assert np.abs(moved[valid] - truth[valid]).mean() < 0.2 * raw_error  # and far closer than the depth as taken


def test_the_nearer_surface_wins_and_disoccluded_pixels_have_no_depth():
    depth = np.full((H, W), 3.0, np.float32)
    depth[20:40, 30:50] = 1.0  # a box in front of a wall
    depth[0, 0] = 0.0  # no reading
    moved = moved_depth(depth, K, se3_exp(np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0])))  # camera 5 cm to the left
    # the box's columns 30..49 move 70 * 0.05 / 1 = 3.5 px right, to 33.5..52.5, and cover the wall there (each
    # point lands on the pixels either side: 33..53); the wall moves 1.17 px, so column 32 is wall the depth camera
    # never saw behind the box
    np.testing.assert_array_equal(moved[20:40, 33:54], 1.0)
    assert (moved[20:40, 32] == 0).all()
    assert (moved[20:40, 54:] == 3.0).all() and (moved[5:15, 5:25] == 3.0).all()
    assert (moved[20:40, :32] == 3.0).sum() > 0.9 * 20 * 32


def test_only_training_frames_with_an_offset_depth_move():
    velocities = np.tile(np.array([0.3, 0.0, 0.0, 0.0, 0.5, 0.0]), (4, 1))
    offsets = np.array([-0.01, 0.0, -0.02, 0.005])
    motions = colour_instant_motions(DepthMoments(velocities, offsets), [0, 1, 3], 4)
    np.testing.assert_allclose(motions[0], se3_exp(-0.01 * velocities[0]))
    np.testing.assert_array_equal(motions[1], np.eye(4))  # taken with its colour
    np.testing.assert_array_equal(motions[2], np.eye(4))  # held out: its fit moves the render instead
    np.testing.assert_allclose(motions[3], se3_exp(0.005 * velocities[3]))
    assert colour_instant_motions(DepthMoments(velocities, np.zeros(4)), [0, 1, 3], 4) is None


class _PlaneSequence:
    """Two frames of the plane: colour unused (grey), depth as the identity camera takes it."""

    def __len__(self) -> int:
        return 2

    def color(self, i: int) -> np.ndarray:
        return np.full((H, W, 3), 0.5, np.float32)

    def depth(self, i: int) -> np.ndarray:
        return plane_depth(np.eye(4)).astype(np.float32)

    def K(self) -> np.ndarray:
        return K


def test_load_frames_moves_each_frames_depth_by_its_motion_at_the_loaded_resolution():
    motion = se3_exp(np.array([0.03, 0.0, 0.0, 0.0, 0.02, 0.0]))
    frames = _load_frames(_PlaneSequence(), 1, None, None, np.stack([np.eye(4), motion]))
    np.testing.assert_array_equal(frames.depths[0], plane_depth(np.eye(4)).astype(np.float32))
    np.testing.assert_array_equal(frames.depths[1], moved_depth(plane_depth(np.eye(4)).astype(np.float32), K, motion))
    half = _load_frames(_PlaneSequence(), 2, None, None, np.stack([np.eye(4), motion]))
    truth = plane_depth(invert(motion))  # the camera the motion takes the depth to, at full resolution
    valid = half.depths[1] > 0
    assert valid.mean() > 0.7
    np.testing.assert_allclose(half.depths[1][valid], truth[1::2, 1::2][valid], atol=0.05)
