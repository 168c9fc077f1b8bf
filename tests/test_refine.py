"""Stage 2 on a short synthetic sequence with extreme blur, started from perturbed ground truth."""

from __future__ import annotations

import dataclasses
from contextlib import contextmanager
from types import SimpleNamespace

import numpy as np
import pytest

from taichi_gs.standins import perturbed

from taichi_gs.errors import InputError
from taichi_gs.evaluate import ate, rpe
from taichi_gs.geometry import invert
from taichi_gs.io.ply import read_point_cloud, read_splats, write_point_cloud
from taichi_gs.io.trajectory import read_tum, write_tum
from taichi_gs.stages.pose import PoseConfig, fuse_points
from taichi_gs.stages.declaration import StageContext
from taichi_gs.stages.refine import PRESETS, STAGE, gaussian_footprint_px, load_stage1, run_refine

synth = pytest.importorskip("taichi_gs.synth")

# the method's 1 cm pose steps: this test undoes a 1 cm / 3 cm perturbation, far beyond stage 1's error
CONFIG = dataclasses.replace(PRESETS["fast"], voxel_size=0.02, iterations_per_frame=100, prune_every_per_frame=30,
                             reset_every_per_frame=60, lr_pose=1e-2, lr_pose_final=1e-5)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from taichi_gs.io.load import load_sequence

    folder = tmp_path_factory.mktemp("refine") / "seq"
    synth.generate(synth.SynthConfig(width=160, height=120, frames=8, trajectory="handheld", blur="extreme", seed=3), folder)
    sequence = load_sequence(folder)
    gt = invert(sequence.gt_poses[0]) @ sequence.gt_poses
    start = perturbed(gt)
    points, colors = fuse_points(sequence, start, PoseConfig(voxel_size_m=CONFIG.voxel_size))
    return sequence, gt, start, points, colors


def test_refinement_undoes_a_known_perturbation(scene, tmp_path):
    sequence, gt, start, points, colors = scene
    result = run_refine(sequence, start, points, colors, tmp_path, CONFIG)
    before, after = ate(start, gt), ate(result.poses, gt)
    (_, rot_before), (_, rot_after) = rpe(start, gt), rpe(result.poses, gt)
    assert after < 0.6 * before, (before, after)
    assert rot_after < 0.6 * rot_before, (rot_before, rot_after)
    depth = [h["depth"] for h in result.loss_history]
    assert np.mean(depth[-5:]) < 0.6 * np.mean(depth[:3])
    np.testing.assert_array_equal(result.poses[0], start[0])
    assert np.allclose(result.poses[:, :3, :3].transpose(0, 2, 1) @ result.poses[:, :3, :3], np.eye(3), atol=1e-9)

    stage = tmp_path / "refine"
    timestamps, poses = read_tum(stage / "trajectory.txt")
    np.testing.assert_allclose(timestamps, sequence.timestamps, atol=1e-6)
    np.testing.assert_allclose(poses, result.poses, atol=1e-5)
    splats = read_splats(stage / "splats.ply")
    assert len(splats) == result.gaussians < len(points)
    np.testing.assert_allclose(splats.log_scales, np.log(CONFIG.voxel_size / 2), rtol=1e-5)
    # the last pruning (at 90 N) left only opaque Gaussians, and few fade in the last 10 N (measured: none)
    assert np.mean(splats.opacities >= CONFIG.prune_opacity) > 0.9, np.mean(splats.opacities >= CONFIG.prune_opacity)
    cloud, _ = read_point_cloud(stage / "points.ply")
    assert len(cloud) == result.gaussians
    assert (stage / "loss.png").stat().st_size > 0
    assert not (stage / "checkpoint.npz").exists()


def test_no_iterations_hands_stage_1s_poses_and_cloud_over_untrained(scene, tmp_path):
    """``iterations_per_frame = 0`` ([ours], the fast preset): stage 2 writes its files without training, so
    stage 3 starts from stage 1's poses and one Gaussian per fused point at the initial scale and opacity."""
    sequence, _, start, points, colors = scene
    config = dataclasses.replace(CONFIG, iterations_per_frame=0)
    result = run_refine(sequence, start, points, colors, tmp_path, config)
    assert (result.iterations, result.loss_history, result.gaussians) == (0, [], len(points))
    np.testing.assert_array_equal(result.poses, start)
    stage = tmp_path / "refine"
    _, poses = read_tum(stage / "trajectory.txt")
    np.testing.assert_allclose(poses, start, atol=1e-6)
    splats = read_splats(stage / "splats.ply")
    np.testing.assert_allclose(splats.means, points, atol=1e-6)
    np.testing.assert_allclose(splats.log_scales, np.log(config.voxel_size / 2), rtol=1e-5)
    np.testing.assert_allclose(splats.opacities, config.initial_opacity, atol=1e-6)
    cloud, cloud_colors = read_point_cloud(stage / "points.ply")
    np.testing.assert_allclose(cloud, points, atol=1e-6)
    np.testing.assert_allclose(cloud_colors, colors, atol=1 / 255)
    assert not (stage / "acceptance.json").exists()  # nothing refined, nothing to accept


def test_resume_from_a_checkpoint_matches_an_uninterrupted_run(scene, tmp_path):
    sequence, _, start, points, colors = scene
    config = dataclasses.replace(CONFIG, iterations_per_frame=4, prune_every_per_frame=2, reset_every_per_frame=3,
                                 checkpoint_every=10)
    whole = run_refine(sequence, start, points, colors, tmp_path / "whole", config)

    def stop_at_25(iteration, total, **_):
        if iteration == 25:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_refine(sequence, start, points, colors, tmp_path / "resumed", config, progress=stop_at_25)
    assert (tmp_path / "resumed" / "refine" / "checkpoint.npz").is_file()
    resumed = run_refine(sequence, start, points, colors, tmp_path / "resumed", config)
    np.testing.assert_allclose(resumed.poses, whole.poses, atol=1e-6)
    assert resumed.gaussians == whole.gaussians


def test_missing_stage1_outputs_are_input_errors(tmp_path):
    with pytest.raises(InputError, match="stage-1 output missing"):
        load_stage1(tmp_path, np.arange(3.0))


def test_spatial_order_changes_the_memory_layout_not_the_steps():
    """``spatial_order`` puts stage 2's Gaussians in Morton order: the same losses and pose gradients
    (up to float32 summation order), and ``kept_indices`` maps each Gaussian back to its input row."""
    from taichi_gs.stages.refine.model import DepthRefiner

    rng = np.random.default_rng(3)
    width, height = 64, 48
    K = np.array([[55.0, 0.0, 31.5], [0.0, 55.0, 23.5], [0.0, 0.0, 1.0]])
    gx, gy = np.meshgrid(np.linspace(-1.4, 1.4, 36), np.linspace(-1.0, 1.0, 26))
    means = np.stack([gx, gy, 2.0 + 0.2 * gx], axis=-1).reshape(-1, 3) + rng.normal(0, 0.03, (gx.size, 3))
    means = means[rng.permutation(len(means))]  # hash order, as a fused cloud comes
    logits = rng.normal(1.5, 1.0, len(means))
    target = np.full((height, width), 2.05)
    runs = []
    for ordered in (False, True):
        model = DepthRefiner(means, logits, scale=0.04, K=K, width=width, height=height, spatial_order=ordered)
        steps = [model.step([target], [np.eye(4)], lambda_depth=1.0, lambda_coverage=0.3, lambda_opacity=0.01,
                            lrs={"means": 1e-3, "opacity_logits": 0.05}) for _ in range(3)]
        assert model.prune(0.9) > 0
        runs.append((model, steps))
    (plain, plain_steps), (ordered, ordered_steps) = runs
    kept = ordered.kept_indices()
    assert not np.array_equal(np.sort(kept), kept)
    for (values_a, grads_a), (values_b, grads_b) in zip(plain_steps, ordered_steps):
        for name in values_a:
            np.testing.assert_allclose(values_b[name], values_a[name], rtol=1e-4)
        np.testing.assert_allclose(grads_b[0], grads_a[0], rtol=1e-3, atol=1e-6 * np.abs(grads_a[0]).max())
    back = np.argsort(kept)  # the ordered model's rows in input order
    np.testing.assert_array_equal(kept[back], plain.kept_indices())
    np.testing.assert_allclose(ordered.means()[back], plain.means(), atol=1e-5)
    np.testing.assert_allclose(ordered.opacity_logits()[back], plain.opacity_logits(), atol=1e-4)


class _PlaneDepths:
    """A stand-in sequence: frame i sees a plane at ``depths[i]`` metres (0: no valid depth), focal 500 px."""

    intrinsics = SimpleNamespace(fx=500.0)

    def __init__(self, depths: list[float]):
        self.depths = depths

    def __len__(self) -> int:
        return len(self.depths)

    def depth(self, i: int) -> np.ndarray:
        return np.full((6, 8), self.depths[i], np.float32)


def test_the_gaussian_footprint_is_the_scale_in_pixels_at_the_median_depth():
    assert gaussian_footprint_px(_PlaneDepths([2.0, 2.0, 2.0]), 0.01) == pytest.approx((2.5, 2.0))
    # frames without depth take the others' median; the median over frames, not the mean (1, 2, 2, 4 m -> 2 m)
    assert gaussian_footprint_px(_PlaneDepths([1.0, 0.0, 2.0, 4.0]), 0.01) == pytest.approx((2.5, 2.0))
    # a long sequence is sampled at 8 evenly spread frames: 4 in each half here, so the median lies between them
    pixels, depth = gaussian_footprint_px(_PlaneDepths([1.0] * 50 + [3.0] * 50), 0.004)
    assert depth == 2.0 and pixels == pytest.approx(1.0)
    planes = _PlaneDepths([4.0])
    assert gaussian_footprint_px(planes, 0.005)[0] == pytest.approx(gaussian_footprint_px(planes, 0.01)[0] / 2)


def test_the_stage_summary_names_the_gaussians_width_in_pixels(scene, tmp_path):
    sequence, _, start, points, colors = scene
    (tmp_path / "pose").mkdir()
    write_tum(tmp_path / "pose" / "trajectory.txt", sequence.timestamps, start)
    write_point_cloud(tmp_path / "pose" / "points.ply", points, colors)

    @contextmanager
    def no_progress(description, total):
        yield lambda *args, **kwargs: None

    config = dataclasses.replace(CONFIG, iterations_per_frame=0)
    summary = STAGE.run(StageContext(sequence, tmp_path, config, no_progress)).summary
    pixels, depth = gaussian_footprint_px(sequence, config.voxel_size / 2)
    assert f"sigma 1 cm = {pixels:.2f} px at the median depth {depth:.2f} m" in summary, summary
    median = np.median([np.median(sequence.depth(i)[sequence.depth(i) > 0]) for i in range(len(sequence))])
    assert depth == pytest.approx(median, rel=1e-6)  # 8 frames: every one sampled
    assert pixels == pytest.approx(0.01 * sequence.intrinsics.fx / median, rel=1e-6)
