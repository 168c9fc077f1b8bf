"""Benchmark stage 1 (local pose) against classical peers on synthetic and real sequences, in one run.

    python bench/pose.py [--frames 60] [--size 320x240] [--trajectories handheld,turn,translation]
                         [--scenes room,office,plain,corridor] [--seeds 0,1,2] [--real-every 1,2,3] [--real-scale 0.5] [--real-camera shipped]
                         [--methods ...] [--out DIR]
    python bench/pose.py --sequence FOLDER [--sequence FOLDER ...]   # any folders with ground truth
                         [--first N] [--every N] [--camera C] [--scale S]   # how every --sequence folder is read
    python bench/pose.py ... --reference TRAJ.txt   # also score the real sequences against another reference

Sequences: ``taichi_gs.synth`` (extreme blur) for every scene kind, trajectory kind and seed, and the 7-Scenes
RedKitchen slice of ../shared/data at every 1st, 2nd, 3rd frame, read as shipped (``--camera shipped``:
colour and depth as one camera with the dataset's K, as every figure of this benchmark before 2026-11-28
read it) or, with ``--real-camera registered``, as the reader reads it by default (depth moved into the colour
camera, whose own focal length differs from the dataset's K; rows named "... registered").

Methods (each from identity at frame 0):
- ours: the stage as shipped (verified candidates + robust pose graph)
- ours no graph: the same run's verified pairs, chained (graph ablation, no extra cost)
- ours no flow check: ours with candidates scored without their disagreement with the measured flow
- ours no joint solve: ours without the joint candidate (flow terms plus point-to-plane, ``[pose] joint_solve``)
- ours no graph joint: ours without the joint candidate on the graph's extra edges (``[pose] graph_joint = false``)
- ours dense verification: ours with four times the verification grid (12000 points a direction)
- ours no long edges: ours with ``[pose] graph_long_spans = []`` (no long edges between close cameras)
- ours long edges every frame: ours with long edges from every frame (``graph_long_every = 1``), not every 4th
- ours preset DIS levels: ours with DIS's finest pyramid level as its preset has it (``flow_finest_width_px = 0``)
- ours no verify: the flow -> ICP -> RGB-D odometry path behind the method's guards, no graph
- paper: the ``paper`` preset (the paper's path only: flow solve, then point-to-plane ICP on every point, chained)
- method: the same path with ICP capped at 80000 points per frame (``pose_config.METHOD_ONLY``)
- cand:NAME: one candidate of ours' run (flow, joint, icp, icp-prior, rgbd-icp, ...), chained (verification ablation)
- oracle: in every pair of ours' run the candidate nearest the sequence's own reference (mm and mrad), chained:
  what the candidates can reach
- O3D hybrid: Open3D compute_rgbd_odometry (hybrid term, levels 20/10/5), pairs chained
- O3D ICP: multi-scale point-to-plane ICP (the stage's settings) from identity, chained
- O3D dense SLAM: Open3D's tensor frame-to-model tracking (voxel hashing, raycast), CPU
- DIS RANSAC: OpenCV DIS flow + depth -> 3D matches -> RANSAC Kabsch fit, chained

A variant of ours that changes only the graph (same pair cache key, e.g. the long-edge ones) starts from the pairs
an earlier method computed on the sequence: its seconds per pair are those pairs' own plus its graph's.

Prints one Markdown row per sequence and method: ATE, ATE between reference breaks, RPE translation and rotation
(RMSE), RPE rotation drift (the norm of the pairs' mean rotation error: the systematic part, which accumulates),
rotation scale (``taichi_gs.evaluate.rotation_scale``: how much of the reference's turning over spans of 10 frames
the method turns; when every method reads the same shortfall, the reference or the camera model is the suspect),
per-pair translation error p50 / p90 / max (mm), weak pairs, pruned graph edges, seconds per pair (wall).
A reference break is a pair whose ground-truth relative pose scores (stage 1's verification, the same for every
method) above ``--break-ratio`` x the sequence's median: 7-Scenes' reference jumps 36 mm between frames 121 and 122,
which every method's ATE carries; the ATE between breaks aligns each stretch between them on its own.
With ``--reference`` (a TUM trajectory whose time stamps are the frames', e.g. the structure-from-motion pseudo
ground truth that Brachmann et al., ICCV 2021, published for 7-Scenes), every real sequence's methods are also scored
against it, in rows named "... vs STEM" (the file's stem) with breaks of their own, beside a row that scores the
sequence's own reference against it: real captures have no true reference, and two references that disagree by as
much as the methods do cannot rank them.
After the table, a ground-truth check (with ``ours``): the pairs whose ground-truth relative pose aligns the two
frames far worse than ours does (verification score above ``--gt-check-ratio`` x ours'), where a pair error
measures the ground truth more than the method (real captures' ground truth has glitches). Then, per sequence,
ours' RPE rotation beside that of its candidates from colour alone (the flow solve) and from depth alone (ICP from
the prior), each chained, and the part of it those two share against the reference (``shared_rotation_error_deg``):
two sensors' own errors do not correlate, so what they share is the reference's error or the motion as both
recorded it, which no estimate from these frames can remove. Then issue 11's
targets for ``ours`` on the run (``target_report``): on how many sequences each is met, and the misses with their
figures (a folder given with ``--sequence`` counts as synthetic when ``taichi-gs synth`` made it). Last, per
sequence, ours' largest pair error against chance (``pair_tails.tail_line``): how likely an unbiased estimator with
Gaussian pair errors of the same covariance keeps its largest within 3x the median, and whether its most outlying
pair is an outlier of its own error distribution (leave-one-out Mahalanobis distance above the 99% quantile).
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from taichi_gs.evaluate import ate, match_by_time, trajectory_errors
from taichi_gs.flow import dis_flow, to_gray_u8
from taichi_gs.geometry import backproject, invert, so3_log
from taichi_gs.icp import align, depth_cloud, rgbd_odometry
from taichi_gs.io.load import load_sequence
from taichi_gs.io.trajectory import read_tum
from taichi_gs.pose_verify import frame_view, verify
from taichi_gs.stages.pose import PRESETS as POSE_PRESETS
from taichi_gs.stages.pose import PoseConfig, chain_poses, run_pose
from taichi_gs.stages.pose_config import METHOD_ONLY
from taichi_gs.stages.pose_pair import icp_levels

from pair_tails import tail_line

SEVEN_SCENES = Path("/work/shared/data/7scenes_redkitchen_000-249")
BREAK_RATIO = 3.0  # a reference pair scoring above this x its median is a break (see reference_breaks)


def fast(**overrides) -> PoseConfig:
    """The ``fast`` preset (ours as shipped) with ``overrides``."""
    return dataclasses.replace(POSE_PRESETS["fast"], **overrides)


OURS = {
    "ours": fast(),
    "ours global shutter": fast(camera_readout=False),
    "ours readout 25 ms": fast(readout_ms=25.0),
    "ours no flow check": fast(verify_flow_weight=0.0),
    "ours no joint solve": fast(joint_solve=False),
    "ours no graph joint": fast(graph_joint=False),
    "ours flow weight 0.2": fast(verify_flow_weight=0.2),
    "ours no long edges": fast(graph_long_spans=()),
    "ours long edges every frame": fast(graph_long_every=1),
    "ours light graph odometry": fast(graph_rgbd_iterations=(10, 5, 3)),
    "ours dense verification": fast(verify_grid_points=12000),
    "ours preset DIS levels": fast(flow_finest_width_px=0),
    "ours no near-tie edges": fast(graph_near_ties=False),
    "ours no verify": fast(verify=False, pose_graph=False),
    "paper": POSE_PRESETS["paper"],  # the paper's path as `--preset paper` runs it (ICP on every point)
    "method": METHOD_ONLY,  # the same at a benchmark's cost: ICP capped at 80000 points per frame
}
DERIVED = ("ours no graph", "cand:flow", "cand:joint", "cand:icp", "cand:rgbd-icp")


def run_ours(sequence, config: PoseConfig, work: Path, pair_caches: dict[str, Path]):
    """Stage 1 with ``config``; a variant whose pairs are the same as an earlier method's on this sequence
    (the same ``PoseConfig.pair_key``, e.g. one that changes only the graph) starts from that method's pair
    caches, ``pair_caches`` (pair key -> pose folder), and reports those pairs' own seconds plus its graph's (and,
    with a rolling shutter, the pairs as read)."""
    pose_dir = work / "pose"
    earlier = pair_caches.setdefault(config.pair_key(), pose_dir)
    for cache in ("pairs", "pairs_as_read"):  # de-skewed pairs are keyed by the readout and its motions too
        if earlier != pose_dir and (earlier / cache).is_dir() and not (pose_dir / cache).exists():
            shutil.copytree(earlier / cache, pose_dir / cache)
    result = run_pose(sequence, work, config)  # pairs are cached: time = pairs' own seconds + the graph's
    seconds = (float(np.mean([p["seconds"] for p in result.pairs]))
               + (result.pairs_as_read_seconds + result.graph_seconds) / (len(sequence) - 1))
    weak = sum(p["weak"] for p in result.pairs)
    pruned = sum(e["pruned"] for e in result.edges)
    extra = f"{weak} / {pruned} of {len(result.edges)}" if result.edges else f"{weak} / -"
    return result, seconds, extra


def candidate_transforms(result, name: str) -> list[np.ndarray | None]:
    """Each pair's transform from its candidate ``name`` in ours' run, None where the pair has no such candidate."""
    return [None if (candidate := pair.get("candidates", {}).get(name)) is None else np.array(candidate["transform"])
            for pair in result.pairs]


def derived(result, name: str) -> np.ndarray:
    """Chained poses of ours' pair transforms (``ours no graph``) or of one candidate per pair
    (the chosen transform where that candidate is missing)."""
    alone = candidate_transforms(result, name[5:]) if name.startswith("cand:") else [None] * len(result.pairs)
    return chain_poses([np.array(pair["transform"]) if T is None else T for pair, T in zip(result.pairs, alone)])


def oracle(result, gt: np.ndarray) -> np.ndarray:
    """Chained poses of the candidate nearest the reference in every pair (its translation error in mm and its
    rotation error in mrad, as one length): the best that stage 1's verification could pick from its candidates,
    so what they can reach. Pairs whose reference is not finite keep ours' transform."""
    def distance(T: np.ndarray, truth: np.ndarray) -> float:
        error = T @ invert(truth)
        return float(np.hypot(np.linalg.norm(error[:3, 3]), np.linalg.norm(so3_log(error[:3, :3]))))

    relatives = []
    for pair, truth in zip(result.pairs, reference_relatives(gt)):
        options = [np.array(c["transform"]) for c in pair.get("candidates", {}).values()] or [np.array(pair["transform"])]
        relatives.append(min(options, key=lambda T: distance(T, truth)) if np.all(np.isfinite(truth)) else options[0])
    return chain_poses(relatives)


def run_icp(sequence, config: PoseConfig = PoseConfig(icp_max_points=80000)):
    K = sequence.intrinsics.K()
    relatives, start = [], time.perf_counter()
    for k in range(len(sequence) - 1):
        clouds = []
        for i in (k, k + 1):
            depth = sequence.depth(i)
            clouds.append(depth_cloud(depth, K, config.reliable_depth(depth)))
        relatives.append(align(icp_levels(clouds[0], clouds[1], config), np.eye(4)).transform)
    return chain_poses(relatives), (time.perf_counter() - start) / (len(sequence) - 1), "-"


def run_hybrid(sequence):
    K = sequence.intrinsics.K()
    relatives, failed, start = [], 0, time.perf_counter()
    for k in range(len(sequence) - 1):
        T = rgbd_odometry(sequence.color(k), sequence.depth(k), sequence.color(k + 1), sequence.depth(k + 1), K, np.eye(4))
        failed += T is None
        relatives.append(np.eye(4) if T is None else T)
    return chain_poses(relatives), (time.perf_counter() - start) / (len(sequence) - 1), f"{failed} failed"


def run_dis_ransac(sequence, iterations: int = 300, inlier_m: float = 0.02, seed: int = 0):
    """DIS flow + depth: 3D-3D matches, RANSAC over 3-point Kabsch fits, refit on the inliers."""
    K = sequence.intrinsics.K()
    rng = np.random.default_rng(seed)
    relatives, start = [], time.perf_counter()
    for k in range(len(sequence) - 1):
        d0, d1 = sequence.depth(k), sequence.depth(k + 1)
        flow = dis_flow(to_gray_u8(sequence.color(k)), to_gray_u8(sequence.color(k + 1)), "medium")
        h, w = d0.shape
        v, u = np.mgrid[0:h:2, 0:w:2]
        u1 = np.round(u + flow[v, u, 0]).astype(int)
        v1 = np.round(v + flow[v, u, 1]).astype(int)
        ok = (d0[v, u] > 0) & (u1 >= 0) & (u1 < w) & (v1 >= 0) & (v1 < h)
        u, v, u1, v1 = u[ok], v[ok], u1[ok], v1[ok]
        ok = d1[v1, u1] > 0
        a = backproject(d0, K)[v[ok], u[ok]]
        b = backproject(d1, K)[v1[ok], u1[ok]]
        best = np.zeros(len(a), bool)
        for _ in range(iterations if len(a) >= 3 else 0):
            pick = rng.choice(len(a), 3, replace=False)
            T = kabsch(a[pick], b[pick])
            inliers = np.linalg.norm(a @ T[:3, :3].T + T[:3, 3] - b, axis=1) < inlier_m
            if inliers.sum() > best.sum():
                best = inliers
        relatives.append(kabsch(a[best], b[best]) if best.sum() >= 3 else np.eye(4))
    return chain_poses(relatives), (time.perf_counter() - start) / (len(sequence) - 1), "-"


def kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rigid T minimising |T a - b|^2."""
    ca, cb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    T = np.eye(4)
    T[:3, :3] = Vt.T @ D @ U.T
    T[:3, 3] = cb - T[:3, :3] @ ca
    return T


def run_dense_slam(sequence, voxel: float = 0.01, depth_max: float = 5.0):
    """Open3D's dense RGB-D SLAM (frame-to-model tracking on a TSDF voxel-hash map) on the CPU; a frame
    whose tracking fails (Open3D raises on a singular system) keeps the last pose and is counted."""
    import open3d as o3d
    import open3d.core as o3c

    device = o3c.Device("CPU:0")
    K = o3c.Tensor(sequence.intrinsics.K(), o3c.float64)
    T = o3c.Tensor(np.eye(4), o3c.float64)
    model = o3d.t.pipelines.slam.Model(voxel, 16, 40000, T, device)
    h, w = sequence.depth(0).shape
    frame, raycast = o3d.t.pipelines.slam.Frame(h, w, K, device), o3d.t.pipelines.slam.Frame(h, w, K, device)
    poses, failed, start = [], 0, time.perf_counter()
    for i in range(len(sequence)):
        depth = np.round(sequence.depth(i) * 1000.0).astype(np.uint16)
        color = np.ascontiguousarray(np.clip(sequence.color(i) * 255, 0, 255).astype(np.uint8))
        frame.set_data_from_image("depth", o3d.t.geometry.Image(o3c.Tensor(depth)))
        frame.set_data_from_image("color", o3d.t.geometry.Image(o3c.Tensor(color)))
        if i > 0:
            try:
                T = T @ model.track_frame_to_model(frame, raycast, 1000.0, depth_max, 0.07).transformation
            except RuntimeError:
                failed += 1
        poses.append(T.cpu().numpy())
        model.update_frame_pose(i, T)
        model.integrate(frame, 1000.0, depth_max, 8.0)
        model.synthesize_model_frame(raycast, 1000.0, 0.1, depth_max, 8.0, False)
    return np.stack(poses), (time.perf_counter() - start) / (len(sequence) - 1), f"{failed} failed"


def pair_error_vectors_mm(poses: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Translation error (mm, n - 1 x 3, in the camera's axes) of each consecutive relative pose."""
    return np.array([1000 * (invert(invert(poses[k]) @ poses[k + 1]) @ (invert(gt[k]) @ gt[k + 1]))[:3, 3]
                     for k in range(len(gt) - 1)])


def pair_errors_mm(poses: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Translation error (mm) of each consecutive relative pose."""
    return np.linalg.norm(pair_error_vectors_mm(poses, gt), axis=1)


def pair_scores(sequence, relatives: list[np.ndarray]) -> np.ndarray:
    """Stage 1's verification score of each relative pose (camera k -> camera k + 1) on its two frames."""
    settings, K = PoseConfig().verify_settings(), sequence.intrinsics.K()

    def view(i: int):
        return frame_view(sequence.color(i), sequence.depth(i), K, settings)

    scores, views_k = [], (None, view(0))
    for k, relative in enumerate(relatives):
        views_k = views_k[1], view(k + 1)  # each frame's view made once, two held at a time
        scores.append(verify(relative, *views_k, K, settings).score)
    return np.array(scores)


def reference_poses(path: Path, timestamps: np.ndarray, max_difference: float = 0.001) -> np.ndarray:
    """The poses of the TUM trajectory ``path`` at ``timestamps`` (each within ``max_difference`` s of one of its
    rows); SystemExit naming the first frame it lacks."""
    times, poses = read_tum(path)
    frames, rows = match_by_time(timestamps, times, max_difference)
    if len(frames) < len(timestamps):
        first = min(set(range(len(timestamps))) - set(frames.tolist()))
        raise SystemExit(f"{path}: no pose at time {timestamps[first]:.4f} s (frame {first} of the sequence); "
                         "give a reference with a row per frame, stamped as the sequence's frames")
    return poses[rows]


def other_reference(path: Path, name: str, sequence, break_ratio: float) -> tuple[str, np.ndarray, list[int], list[str]]:
    """``--reference`` for one real sequence: its rows' name, its poses at the frames, its breaks and their lines."""
    poses = reference_poses(path, sequence.timestamps)
    scores = pair_scores(sequence, reference_relatives(poses))
    breaks = reference_breaks(scores, break_ratio)
    row_name = f"{name} vs {path.stem}"
    lines = [f"- {row_name}, pair {k}: the reference scores {scores[k]:.3f}, {scores[k] / np.median(scores):.1f}x its "
             "median" for k in breaks]
    return row_name, poses, breaks, lines


def reference_relatives(gt: np.ndarray) -> list[np.ndarray]:
    """The reference's relative poses, camera k -> camera k + 1."""
    return [invert(gt[k + 1]) @ gt[k] for k in range(len(gt) - 1)]


def reference_breaks(truth_scores: np.ndarray, ratio: float) -> list[int]:
    """Pairs k whose reference relative pose scores above ``ratio`` x the sequence's median: jumps of the
    reference itself (a real capture's reference has glitches; every method's ATE carries them), where
    :func:`segment_ate` aligns the stretches on either side separately."""
    if ratio <= 0 or not len(truth_scores):
        return []
    return [int(k) for k in np.nonzero(truth_scores > ratio * np.median(truth_scores))[0]]


def segment_ate(poses: np.ndarray, gt: np.ndarray, breaks: list[int]) -> float:
    """ATE (m) with each stretch between reference breaks aligned on its own: the RMSE over their frames
    (stretches under 3 frames are left out); the plain ATE when there are no breaks."""
    bounds = [0, *(k + 1 for k in breaks), len(gt)]
    squares, frames = 0.0, 0
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        if hi - lo >= 3:
            squares += ate(poses[lo:hi], gt[lo:hi]) ** 2 * (hi - lo)
            frames += hi - lo
    return float(np.sqrt(squares / frames)) if frames else float("nan")


def ground_truth_check(name: str, sequence, result, truth_scores: np.ndarray, ratio: float) -> list[str]:
    """One line per pair whose ground-truth relative pose scores above ``ratio`` x ours' verification score."""
    truths = reference_relatives(sequence.gt_poses)
    relatives = [np.array(pair["transform"]) for pair in result.pairs]
    lines = []
    for k, (ours, ours_score) in enumerate(zip(relatives, pair_scores(sequence, relatives))):
        truth, truth_score = truths[k], truth_scores[k]
        if truth_score > ratio * ours_score:
            error = 1000 * np.linalg.norm((ours @ invert(truth))[:3, 3])
            lines.append(f"- {name}, pair {k} ({sequence.names[k]} -> {sequence.names[k + 1]}): the ground truth scores "
                         f"{truth_score:.3f}, ours {ours_score:.3f}; ours is {error:.1f} mm from it")
    return lines


INDEPENDENT_CANDIDATES = ("flow", "icp-prior")  # colour alone (the flow solve), depth alone (ICP from the prior)


def shared_rotation_error_deg(a: list[np.ndarray | None], b: list[np.ndarray | None], truths: list[np.ndarray]) -> float:
    """RMS (deg) of the rotation error that two estimates of each pair share against the reference ``truths``
    (camera k -> k + 1, as ``chain_poses`` takes them; None where an estimate is missing): the square root of the
    mean dot product of their error vectors log(R_truth^T R). Errors of estimates made from independent measurements
    (colour alone, depth alone) do not correlate, so the mean keeps only the error they have in common: the
    reference's own (its noise, its timing against the frames) or the motion as both sensors recorded it, which no
    estimate from these frames can tell from the truth. 0 where the mean is negative; NaN without a pair."""
    products = [float(so3_log(t[:3, :3].T @ x[:3, :3]) @ so3_log(t[:3, :3].T @ y[:3, :3]))
                for x, y, t in zip(a, b, truths) if x is not None and y is not None and np.all(np.isfinite(t))]
    if not products:
        return float("nan")
    return float(np.degrees(np.sqrt(max(np.mean(products), 0.0))))


def shared_error_line(name: str, reference: np.ndarray, result, ours: Measured) -> str:
    """What of ours' RPE rotation on ``name`` the colour-only and depth-only candidates share against the
    ``reference`` poses (``shared_rotation_error_deg``), beside each one's own RPE rotation."""
    truths = reference_relatives(reference)
    alone = {c: candidate_transforms(result, c) for c in INDEPENDENT_CANDIDATES}
    own = {c: trajectory_errors(derived(result, f"cand:{c}"), reference).rpe_rot_deg for c in alone}
    colour, depth = INDEPENDENT_CANDIDATES
    return (f"- {name}: ours {ours.rpe_rot_deg:.3f} deg; {colour} (colour) {own[colour]:.3f}, {depth} (depth) "
            f"{own[depth]:.3f}; shared by those two: {shared_rotation_error_deg(alone[colour], alone[depth], truths):.3f}")


PEERS = ("O3D hybrid", "O3D ICP", "O3D dense SLAM", "DIS RANSAC")


@dataclasses.dataclass(frozen=True)
class Measured:
    """One method's figures on one sequence, as the table prints them and issue 11's targets read them."""

    sequence: str
    method: str
    synthetic: bool
    width: int
    ate_mm: float
    segment_ate_mm: float
    rpe_trans_mm: float
    rpe_rot_deg: float
    rpe_rot_drift_deg: float
    rotation_scale: float
    pair_errors_mm: np.ndarray
    seconds: float | None
    extra: str


def measure(name: str, method: str, poses: np.ndarray, gt: np.ndarray, breaks: list[int], seconds: float | None,
            extra: str, synthetic: bool, width: int) -> Measured:
    """``poses`` against the reference ``gt``: ATE (also between reference ``breaks``), RPE, pair errors."""
    t = trajectory_errors(poses, gt)
    return Measured(name, method, synthetic, width, 1000 * t.ate_m, 1000 * segment_ate(poses, gt, breaks),
                    1000 * t.rpe_trans_m, t.rpe_rot_deg, t.rpe_rot_drift_deg, t.rotation_scale, pair_errors_mm(poses, gt),
                    seconds, extra)


def row(m: Measured) -> str:
    """The table's Markdown row of ``m``."""
    e = m.pair_errors_mm
    s = "-" if m.seconds is None else f"{m.seconds:.2f}"
    return (f"| {m.sequence} | {m.method} | {m.ate_mm:.1f} | {m.segment_ate_mm:.1f} | {m.rpe_trans_mm:.1f} | "
            f"{m.rpe_rot_deg:.3f} | {m.rpe_rot_drift_deg:.3f} | {m.rotation_scale:.3f} | "
            f"{np.median(e):.1f} / {np.percentile(e, 90):.1f} / {e.max():.1f} | {m.extra} | {s} |")


def best_peer(measured: list[Measured], sequence: str) -> Measured | None:
    """The peer (``PEERS``) with the lowest ATE on ``sequence``, if any ran there."""
    peers = [m for m in measured if m.sequence == sequence and m.method in PEERS and np.isfinite(m.ate_mm)]
    return min(peers, key=lambda m: m.ate_mm, default=None)


def target_report(measured: list[Measured], method: str = "ours") -> list[str]:
    """Issue 11's targets for ``method`` on this run, one line each: on how many sequences it is met, and the
    misses with their figures. ATE at most 1/3 of the best peer's (where a peer ran) and at most 5 mm on
    synthetic sequences; RPE rotation under 0.1 deg; no pair error above 3x the sequence's median; at most 2 s
    per pair at 640 px width or more (the table's seconds per pair)."""
    ours = [m for m in measured if m.method == method]
    peers = {m.sequence: best_peer(measured, m.sequence) for m in ours}

    def ratio(m: Measured) -> float:
        median = float(np.median(m.pair_errors_mm))
        return float(m.pair_errors_mm.max()) / median if median > 0 else float("inf")

    def peer_text(m: Measured) -> str:
        return f"{m.ate_mm:.1f} mm against {peers[m.sequence].method}'s {peers[m.sequence].ate_mm:.1f}"

    targets = [
        ("ATE at most 1/3 of the best peer's", lambda m: peers[m.sequence] is not None,
         lambda m: m.ate_mm <= peers[m.sequence].ate_mm / 3, peer_text),
        ("ATE at most 5 mm on synthetic sequences", lambda m: m.synthetic, lambda m: m.ate_mm <= 5.0,
         lambda m: f"{m.ate_mm:.1f} mm"),
        ("RPE rotation under 0.1 deg", lambda m: True, lambda m: m.rpe_rot_deg < 0.1,
         lambda m: f"{m.rpe_rot_deg:.3f} deg"),
        ("no pair error above 3x the median", lambda m: True, lambda m: ratio(m) <= 3.0,
         lambda m: f"{m.pair_errors_mm.max():.1f} mm, {ratio(m):.1f}x {np.median(m.pair_errors_mm):.1f}"),
        ("at most 2 s per pair at 640x480", lambda m: m.width >= 640 and m.seconds is not None,
         lambda m: m.seconds <= 2.0, lambda m: f"{m.seconds:.2f} s"),
    ]
    lines = []
    for label, applies, met, describe in targets:
        rows = [m for m in ours if applies(m)]
        if not rows:
            lines.append(f"- {label}: no sequence of this run applies")
            continue
        missed = [m for m in rows if not met(m)]
        text = f"- {label}: met on {len(rows) - len(missed)} of {len(rows)}"
        if missed:
            text += "; missed: " + "; ".join(f"{m.sequence} ({describe(m)})" for m in missed)
        lines.append(text)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--trajectories", default="handheld,turn,translation")
    parser.add_argument("--scenes", default="room,office,plain,corridor", help="synth scene kinds")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--synth-readout-ms", type=float, default=0.0,
                        help="synth sequences read through a rolling shutter of this many ms (0: a global shutter)")
    parser.add_argument("--real-every", default="1,2,3", help="7-Scenes frame steps; empty: no real data")
    parser.add_argument("--real-scale", type=float, default=0.5)
    parser.add_argument("--real-camera", default="shipped", choices=("shipped", "registered"),
                        help="how the 7-Scenes grid is read: shipped (the dataset's single K, as this benchmark always "
                             "read it) or registered (the reader's default: depth moved into the colour camera)")
    parser.add_argument("--methods", default=",".join([*OURS, *DERIVED, "O3D hybrid", "O3D ICP", "O3D dense SLAM", "DIS RANSAC"]))
    parser.add_argument("--sequence", type=Path, action="append", help="benchmark these folders instead")
    parser.add_argument("--first", type=int, default=0, help="--sequence folders: start at this frame")
    parser.add_argument("--every", type=int, default=1, help="--sequence folders: keep every N-th frame")
    parser.add_argument("--camera", default=None, help="--sequence folders: the reader's --camera (TUM: fr1 ...)")
    parser.add_argument("--scale", type=float, default=1.0, help="--sequence folders: read at S times their size")
    parser.add_argument("--out", type=Path, default=None, help="keep sequences and outputs here")
    parser.add_argument("--reference", type=Path, default=None,
                        help="also score real sequences against this TUM trajectory (rows '... vs STEM')")
    parser.add_argument("--gt-check-ratio", type=float, default=2.0,
                        help="list pairs whose ground truth scores above this x ours' (0: no check)")
    parser.add_argument("--break-ratio", type=float, default=BREAK_RATIO,
                        help="reference breaks: pairs whose ground truth scores above this x its median (0: none)")
    args = parser.parse_args()
    methods = args.methods.split(",")
    root = args.out or Path(tempfile.mkdtemp(prefix="bench_pose_"))
    print("| sequence | method | ATE (mm) | ATE between reference breaks (mm) | RPE trans (mm) | RPE rot (deg) | "
          "RPE rot drift (deg/pair) | rotation scale | pair err p50 / p90 / max (mm) | weak / pruned | s/pair |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    suspects, break_lines, measured, shared_lines, tail_lines = [], [], [], [], []
    for name, sequence, synthetic in sequences(args, root):
        gt = sequence.gt_poses
        truth_scores = pair_scores(sequence, reference_relatives(gt))
        breaks = reference_breaks(truth_scores, args.break_ratio)
        break_lines += [f"- {name}, pair {k} ({sequence.names[k]} -> {sequence.names[k + 1]}): the ground truth scores "
                        f"{truth_scores[k]:.3f}, {truth_scores[k] / np.median(truth_scores):.1f}x its median" for k in breaks]
        scorings = [(name, gt, breaks)]
        if args.reference is not None and not synthetic:
            other_name, other, other_breaks, lines = other_reference(args.reference, name, sequence, args.break_ratio)
            scorings.append((other_name, other, other_breaks))
            break_lines += lines
            measured.append(measure(other_name, "the sequence's own reference", gt, other, other_breaks, None, "-",
                                    synthetic, sequence.intrinsics.width))
            print(row(measured[-1]), flush=True)
        ours, pair_caches = None, {}
        for method in methods:
            if method in OURS:
                result, seconds, extra = run_ours(sequence, OURS[method], root / slug(name) / slug(method), pair_caches)
                poses = result.poses
                if method == "ours":
                    ours = result
            elif method == "oracle":
                if ours is None:
                    continue
                poses, seconds, extra = oracle(ours, gt), None, "-"
            elif method in DERIVED or method.startswith("cand:"):
                if ours is None:
                    continue
                poses, seconds, extra = derived(ours, method), None, "-"
            elif method == "O3D hybrid":
                poses, seconds, extra = run_hybrid(sequence)
            elif method == "O3D ICP":
                poses, seconds, extra = run_icp(sequence)
            elif method == "O3D dense SLAM":
                poses, seconds, extra = run_dense_slam(sequence)
            elif method == "DIS RANSAC":
                poses, seconds, extra = run_dis_ransac(sequence)
            else:
                raise SystemExit(f"unknown method {method!r}")
            for scored_name, scored_gt, scored_breaks in scorings:
                measured.append(measure(scored_name, method, poses, scored_gt, scored_breaks, seconds, extra,
                                        synthetic, sequence.intrinsics.width))
                print(row(measured[-1]), flush=True)
        if ours is not None and args.gt_check_ratio > 0:
            suspects += ground_truth_check(name, sequence, ours, truth_scores, args.gt_check_ratio)
        if ours is not None:
            for scored_name, scored_gt, _ in scorings:
                ours_row = next(m for m in measured if m.sequence == scored_name and m.method == "ours")
                shared_lines.append(shared_error_line(scored_name, scored_gt, ours, ours_row))
                tail_lines.append(tail_line(scored_name, pair_error_vectors_mm(ours.poses, scored_gt)))
    if args.gt_check_ratio > 0 and "ours" in methods:
        print(f"\nGround-truth check, pairs whose ground truth scores above {args.gt_check_ratio:g}x ours: "
              f"{len(suspects) or 'none'}", *suspects, sep="\n")
    if shared_lines:
        print("\nRPE rotation (deg) of ours and of its candidates from colour alone and from depth alone, and the part "
              "of it those two share against the reference (the reference's own error or the motion as both sensors "
              "recorded it):", *shared_lines, sep="\n")
    if any(m.method == "ours" for m in measured):
        print("\nIssue 11's targets for ours on this run:", *target_report(measured), sep="\n")
    if tail_lines:
        print("\nOurs' largest pair error against chance (bench/pair_tails.py: an unbiased estimator whose pair "
              "errors are Gaussian with the sequence's own covariance; a whitened error above its 99% quantile is an "
              "outlier):", *tail_lines, sep="\n")
    if args.break_ratio > 0:
        print(f"\nReference breaks, pairs whose ground truth scores above {args.break_ratio:g}x its median: "
              f"{len(break_lines) or 'none'}", *break_lines, sep="\n")


def slug(label: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in label)


def sequence_label(folder: Path, args) -> str:
    """A ``--sequence`` folder's row name: its folder name, and how it was read where that is not as stored."""
    read = [f"from {args.first}" if args.first else "", f"every {args.every}" if args.every > 1 else "",
            f"x{args.scale:g}" if args.scale != 1.0 else ""]
    return " ".join([folder.name, *filter(None, read)])


def sequences(args, root: Path):
    """(name, sequence, synthetic) of the given folders (read from ``--first``, every ``--every``-th frame,
    ``--frames`` of them, with ``--camera`` at ``--scale``), or of the synthetic and 7-Scenes grid; a folder is
    synthetic when ``taichi-gs synth`` made it (its synth.json)."""
    if args.sequence:
        for folder in args.sequence:
            sequence = load_sequence(folder, camera=args.camera, first=args.first, every=args.every,
                                     count=args.frames, scale=args.scale)
            yield sequence_label(folder, args), sequence, (folder / "synth.json").is_file()
        return
    from taichi_gs.synth import SynthConfig, generate

    w, h = (int(x) for x in args.size.split("x"))
    grid = [(scene, trajectory, int(seed)) for scene in args.scenes.split(",") if scene
            for trajectory in args.trajectories.split(",") for seed in args.seeds.split(",")]
    for scene, trajectory, seed in grid:
        shutter = f"_rs{args.synth_readout_ms:g}" if args.synth_readout_ms else ""
        folder = root / f"{scene}_{trajectory}_{w}x{h}_s{seed}{shutter}"
        if not (folder / "frames.txt").is_file():
            generate(SynthConfig(width=w, height=h, frames=args.frames, trajectory=trajectory, scene=scene,
                                 blur="extreme", seed=seed, readout_ms=args.synth_readout_ms), folder)
        yield f"{scene} {trajectory} {w}x{h} seed {seed}{shutter.replace('_rs', ' readout ')}", load_sequence(folder), True
    reading = "" if args.real_camera == "shipped" else f" {args.real_camera}"
    for every in (int(e) for e in args.real_every.split(",") if e):
        yield f"7-Scenes every {every} x{args.real_scale:g}{reading}", load_sequence(
            SEVEN_SCENES, camera=args.real_camera, every=every, count=args.frames, scale=args.real_scale), False


if __name__ == "__main__":
    main()
