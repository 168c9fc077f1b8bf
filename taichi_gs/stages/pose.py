"""Stage 1: local pose. Relative poses frame t -> t+1 from optical flow, colour and depth, refined by
point-to-plane ICP, chained into camera-to-world poses; all frames fused into one coloured cloud.

Outputs in OUT/pose/: ``trajectory.txt`` (TUM, camera-to-world, first frame = identity),
``points.ply`` (voxel-downsampled coloured cloud), ``pairs.json`` (per-pair diagnostics and a
summary), and ``pairs/NNNNNN.json`` (per-pair cache, so a rerun skips finished pairs; with a rolling shutter
``pairs_as_read/`` caches the pairs of the frames as read, and ``pairs/`` those of the de-skewed frames); the
pipeline adds ``config.toml``.

The stage's parts: its settings (``pose_config``), one pair's estimate (``pose_pair``), the window of frames
(``pose_frames``) and the pose graph's edges (``pose_edges``); this module runs them over a sequence.
"""

from __future__ import annotations

import functools
import hashlib
import json
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .. import profiling
from ..errors import InputError
from ..flow import DISFlow, FileFlow, FlowProvider
from ..geometry import invert
from ..icp import depth_cloud, open3d
from ..io.atomic import write_text
from ..io import jsonout
from ..io.ply import write_point_cloud
from ..io.trajectory import write_tum
from ..machine import available_cores
from ..pose_graph import Edge
from ..rolling_shutter import DeskewedSequence, deskewing_motions, readout_motions, stage_readout_ms
from .declaration import StageContext, StageDeclaration, StageInputs, StageRun
from .pose_config import PRESETS, PoseConfig
from .pose_edges import edge_record, refine_with_graph
from .pose_frames import FrameCache
from .pose_pair import (FROM_CONSTANT_VELOCITY, PairStart, RelativePose, estimate_relative_pose, fallback_pose,
                        start_pair)

if TYPE_CHECKING:
    from ..io.sequence import Sequence

# What a degenerate pair may raise; anything else is a bug or bad input and ends the run.
NUMERICAL_FAILURES = (np.linalg.LinAlgError, ArithmeticError)


@dataclass
class PoseResult:
    """Camera-to-world poses (N x 4 x 4), per-pair records (as in pairs.json) and the files written."""

    poses: np.ndarray
    pairs: list[dict]
    paths: dict[str, Path] = field(default_factory=dict)
    edges: list[dict] = field(default_factory=list)  # pose-graph edges (empty without the graph)
    graph_seconds: float = 0.0  # extra edges and optimisation
    rolling_shutter: dict | None = None  # readout_ms and skew_px of de-skewed frames (None: as read)
    pairs_as_read_seconds: float = 0.0  # with a rolling shutter: the pairs of the frames as read, all together

    def summary(self) -> str:
        weak = sum(1 for p in self.pairs if p["weak"])
        fallback = sum(1 for p in self.pairs if p["estimate"] == FROM_CONSTANT_VELOCITY)
        text = f"{len(self.pairs)} pairs, {weak} weak ({fallback} replaced by constant velocity)"
        if self.edges:
            loops = sum(e["kind"] == "loop" for e in self.edges)
            pruned = sum(e["pruned"] for e in self.edges)
            rechosen = sum(e["kind"] == "odometry" and e["estimate"] != self.pairs[e["source"]]["estimate"]
                           for e in self.edges)
            text += f"; pose graph: {len(self.edges)} edges ({loops} loop closures), {pruned} pruned"
            text += f", {rechosen} pairs re-chosen among near-ties" if rechosen else ""
        if self.rolling_shutter:
            text += (f"; frames de-skewed for a rolling shutter of {self.rolling_shutter['readout_ms']:g} ms (rows up "
                     f"to {self.rolling_shutter['skew_px']:.1f} px from their frame's pose)")
        return text


def chain_poses(relatives: list[np.ndarray]) -> np.ndarray:
    """Camera-to-world poses from transforms camera t -> t+1; the first camera is the world frame."""
    poses = [np.eye(4)]
    for T in relatives:
        poses.append(poses[-1] @ invert(T))
    return np.stack(poses)


@profiling.timed("fused point cloud")
def fuse_points(sequence, poses: np.ndarray, config: PoseConfig,
                on_frame: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World points and colours of all frames' reliable depth, voxel-downsampled to ``voxel_size_m``;
    ``on_frame(done)`` after each frame."""
    K = sequence.intrinsics.K()
    fused = open3d().geometry.PointCloud()
    for i, pose in enumerate(poses):
        depth = sequence.depth(i)
        mask = config.reliable_depth(depth)
        cloud = depth_cloud(depth, K, mask, sequence.color(i)).transform(pose)
        fused += cloud.voxel_down_sample(config.voxel_size_m)
        fused = fused.voxel_down_sample(config.voxel_size_m)
        if on_frame is not None:
            on_frame(i + 1)
    return np.asarray(fused.points), np.asarray(fused.colors)


def flow_provider(sequence, config: PoseConfig, frames: FrameCache) -> FlowProvider:
    """Precomputed flows when ``flow_dir`` is set (checked now), else DIS on ``frames``' grey frames."""
    if config.flow_dir:
        provider = FileFlow(config.flow_dir, list(sequence.names))
        provider.check()
        return provider
    return DISFlow(frames.gray, config.flow_preset, config.flow_finest_width_px)


def run_pose(sequence, out_dir: Path, config: PoseConfig = PoseConfig(),
             progress: Callable[[int, int, str], None] | None = None, threads: int | None = None) -> PoseResult:
    """Stage 1 over a whole sequence, resuming from cached pairs; writes OUT/pose/ (see module doc).
    ``progress(done, total, step)`` counts the pairs (first "pairs as read" with a rolling shutter), then the
    pose graph's frames, then the frames fused into the cloud (``step``: "pairs", "graph", "fused cloud").
    ``threads``: the caller's thread count, in place of the config's (:func:`stage_threads`)."""
    n = len(sequence)
    if n < 2:
        raise InputError(getattr(sequence, "root", None), f"sequence has {n} frame(s)", "give at least two frames")
    pose_dir = Path(out_dir) / "pose"
    K = sequence.intrinsics.K()
    key = config.pair_key()
    readout_ms = pose_readout_ms(sequence, config)
    steps = progress_steps(n, config, readout_ms)

    def progress_of(kind: str, offset: int) -> Callable[[int], None]:
        return (lambda done: progress(offset + done, steps, kind)) if progress is not None else (lambda done: None)

    shutter: dict | None = None
    as_read_seconds = 0.0
    threads = stage_threads(config, threads)
    with _workers(threads) as pool:
        if readout_ms > 0:  # [ours] the pairs as read give each frame's motion over its readout; de-skew, redo
            as_read = _pair_estimates(sequence, FrameCache(sequence, K, config), pose_dir / "pairs_as_read", key,
                                      config, pool, threads, progress_of("pairs as read", 0))
            motions, skew_px = deskewing_motions(sequence, readout_motions(
                chain_poses([r.transform for r in as_read]), sequence.timestamps, readout_ms / 1000.0))
            sequence = DeskewedSequence(sequence, motions)
            key = _deskewed_pair_key(key, readout_ms, motions)
            shutter = {"readout_ms": readout_ms, "skew_px": round(skew_px, 3)}
            as_read_seconds = sum(r.seconds for r in as_read)
        frames = FrameCache(sequence, K, config)
        offset = n - 1 if readout_ms > 0 else 0
        relatives = _pair_estimates(sequence, frames, pose_dir / "pairs", key, config, pool, threads,
                                    progress_of("pairs", offset))
        poses = chain_poses([r.transform for r in relatives])
        pairs = [_pair_record(k, sequence.names, r) for k, r in enumerate(relatives)]
        edges: list[Edge] = []
        graph_start = time.perf_counter()
        if config.pose_graph:
            poses, edges = refine_with_graph(sequence, relatives, poses, config, frames, pool,
                                             on_frame=progress_of("graph", offset + n - 1))
    result = PoseResult(poses, pairs, edges=[edge_record(e) for e in edges],
                        graph_seconds=time.perf_counter() - graph_start, rolling_shutter=shutter,
                        pairs_as_read_seconds=as_read_seconds)
    paths = {"trajectory": pose_dir / "trajectory.txt", "points": pose_dir / "points.ply", "pairs": pose_dir / "pairs.json"}
    write_tum(paths["trajectory"], np.asarray(sequence.timestamps), poses, header="taichi-gs stage 1, camera-to-world")
    record = {"summary": result.summary(), "pairs": pairs, "edges": result.edges}
    if shutter is not None:
        record["rolling_shutter"] = shutter
    write_text(paths["pairs"], jsonout.dumps(record, indent=1) + "\n")
    points, colors = fuse_points(sequence, poses, config, on_frame=progress_of("fused cloud", steps - n))
    write_point_cloud(paths["points"], points, colors)
    result.paths = paths
    return result


def _pair_estimates(sequence, frames: FrameCache, pair_dir: Path, key: str, config: PoseConfig, pool: Executor,
                    threads: int, on_pair: Callable[[int], None]) -> list[RelativePose]:
    """Every pair (k, k+1) of ``frames``, each read from ``pair_dir`` when cached there under ``key``, else
    estimated (the ``threads`` workers of ``pool`` start the next pairs while this thread finishes one) and
    cached."""
    pair_dir.mkdir(parents=True, exist_ok=True)
    K = sequence.intrinsics.K()
    cached = [_load_pair(pair_dir / f"{k:06d}.json", key) for k in range(len(sequence) - 1)]
    started = _run_ahead(pool, [k for k, r in enumerate(cached) if r is None],
                         functools.partial(_start_pair_of, frames, flow_provider(sequence, config, frames), K, config),
                         ahead=2 * threads if threads > 1 else 0)
    relatives: list[RelativePose] = []
    last = time.perf_counter()
    for k, relative in enumerate(cached):
        if relative is None:
            prior = relatives[-1].transform if relatives else np.eye(4)
            relative = _estimate_pair(frames, k, K, config, prior, next(started))
            relative.seconds = time.perf_counter() - last  # the wall time it added, its work ahead overlapped
            write_text(pair_dir / f"{k:06d}.json", jsonout.dumps({"config_key": key, **relative.to_dict()}) + "\n")
        relatives.append(relative)
        on_pair(k + 1)
        last = time.perf_counter()
    return relatives


def pose_readout_ms(sequence, config: PoseConfig) -> float:
    """Stage 1's rolling-shutter readout (ms) for ``sequence`` (:func:`rolling_shutter.stage_readout_ms`); 0 with
    precomputed flows (``flow_dir``), which are the frames' as read, and an input error if a readout is asked
    for with them."""
    if config.flow_dir:
        if config.readout_ms > 0:
            raise InputError(Path(config.flow_dir), "precomputed flows are of the frames as read, and a rolling "
                             "shutter's readout de-skews the frames", "give --readout-ms 0, or leave out --flow-dir")
        return 0.0
    return stage_readout_ms(config.readout_ms, config.camera_readout, getattr(sequence, "source", {}))


def _deskewed_pair_key(key: str, readout_ms: float, motions: np.ndarray) -> str:
    """The cache key of pairs on de-skewed frames: the pairs' own ``key``, the readout and its motions."""
    text = json.dumps({"key": key, "readout_ms": readout_ms, "motions": np.round(motions, 9).tolist()})
    return hashlib.sha1(text.encode()).hexdigest()[:16]


def _start_pair_of(frames: FrameCache, provider: FlowProvider, K: np.ndarray, config: PoseConfig, k: int) -> PairStart:
    """Pair k's :func:`start_pair` on the provider's flows (run ahead, on a worker thread when there are several)."""
    views = (frames.view(k), frames.view(k + 1)) if config.verify else None
    return start_pair(frames.color(k), frames.depth(k), frames.color(k + 1), frames.depth(k + 1), K,
                      provider.flow(k, k + 1), provider.flow(k + 1, k), config, views, frames.normals(k + 1))


def _estimate_pair(frames: FrameCache, k: int, K: np.ndarray, config: PoseConfig, prior: np.ndarray,
                   started: Future) -> RelativePose:
    """Pair k from its started part (a future of :func:`_start_pair_of`); numerical trouble (a singular
    system, an overflow) makes it a weak constant-velocity pair, recorded with its reason. Input and
    programming errors are not caught: they end the run."""
    start = time.perf_counter()
    try:
        return estimate_relative_pose(frames.color(k), frames.depth(k), frames.color(k + 1), frames.depth(k + 1),
                                      K, config=config, prior=prior, ahead=started.result(),
                                      views=(frames.view(k), frames.view(k + 1)) if config.verify else None)
    except NUMERICAL_FAILURES as err:  # one degenerate pair must not end the run; the reason is recorded
        return fallback_pose(prior, f"{type(err).__name__}: {err}", start)


# The most threads stage 1 takes by default: the pairs finish one after another on one thread, which bounds what
# more workers can start ahead, and each Open3D call runs its own threads (measured on 2 cores only)
DEFAULT_MAX_THREADS = 4


def stage_threads(config: PoseConfig, threads: int | None = None) -> int:
    """Threads stage 1 runs on: ``threads`` when the caller gives it (one under --profile, whose sections are
    timed on one thread; the results are the same), else ``config.threads``, 0 meaning one per available core
    up to :data:`DEFAULT_MAX_THREADS`."""
    return threads or config.threads or min(available_cores(), DEFAULT_MAX_THREADS)


class _Inline(Executor):
    """An executor that runs each task in the caller's thread when it is submitted."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as error:  # re-raised by future.result(), where a pool would raise it
            future.set_exception(error)
        return future


@contextmanager
def _workers(threads: int) -> Iterator[Executor]:
    """A pool of ``threads`` worker threads, or the caller's thread alone for one; waiting tasks are cancelled
    on the way out."""
    pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="pose") if threads > 1 else _Inline()
    try:
        yield pool
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _run_ahead(pool: Executor, keys: list[int], task: Callable[[int], PairStart], ahead: int) -> Iterator[Future]:
    """Futures of ``task(key)`` in the order of ``keys``; when one is taken, the tasks of the next ``ahead``
    keys are submitted too, so that the pool runs ahead of the caller by that many keys at most."""
    futures: dict[int, Future] = {}
    for i, key in enumerate(keys):
        for upcoming in keys[i:i + ahead + 1]:
            if upcoming not in futures:
                futures[upcoming] = pool.submit(task, upcoming)
        yield futures.pop(key)


def _load_pair(path: Path, key: str) -> RelativePose | None:
    """A cached pair computed with the same settings, or None."""
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        return RelativePose.from_dict(data) if data.get("config_key") == key else None
    except (ValueError, KeyError, TypeError):
        return None


def _pair_record(k: int, names: list[str], r: RelativePose) -> dict:
    record = {"index": k, "source": names[k], "target": names[k + 1]}
    record.update({key: value for key, value in r.to_dict().items() if key != "flow_transform"})
    return record


def progress_steps(frames: int, config: PoseConfig, readout_ms: float = 0.0) -> int:
    """Stage 1's progress steps: the pairs (twice with a rolling shutter's ``readout_ms``), the pose graph's
    frames (with ``pose_graph``), the fused frames."""
    return (frames - 1) * ((2 if config.pose_graph else 1) + (1 if readout_ms > 0 else 0)) + frames


MAX_PAIR_WARNINGS = 5  # weak pairs named one by one on the console; pairs.json lists them all


def weak_pair_warnings(sequence: Sequence, pairs: list[dict], config: PoseConfig) -> list[str]:
    """One line per frame of a weak pair whose depth has fewer usable pixels than a pair needs (naming its depth
    file), then one per other weak pair (at most :data:`MAX_PAIR_WARNINGS`, and a count of the rest)."""
    weak = [p for p in pairs if p.get("weak")]
    frames = sorted({p["index"] for p in weak} | {p["index"] + 1 for p in weak})
    depthless = {}
    for i in frames:
        usable = int(np.count_nonzero(config.reliable_depth(sequence.depth(i))))
        if usable < config.min_points:
            depthless[i] = usable
    lines = [f"{sequence.depth_paths[i]}: {usable} pixels of usable depth ({config.min_depth_m:g}-"
             f"{config.max_depth_m:g} m), fewer than a pair needs ({config.min_points}); frame {sequence.names[i]}'s "
             f"pose comes from its neighbours; check the depth file" for i, usable in depthless.items()]
    others = [p for p in weak if p["index"] not in depthless and p["index"] + 1 not in depthless]
    for p in others[:MAX_PAIR_WARNINGS]:
        held = ("the constant-velocity guess" if p["estimate"] == FROM_CONSTANT_VELOCITY
                else f"the {p['estimate']} estimate")
        fate = (f"its edge ({held}) is weighted down in the pose graph" if config.pose_graph
                else f"the trajectory keeps {held}")
        lines.append(f"weak pair {p['source']} -> {p['target']} ({p['reason'] or 'no reason recorded'}); {fate}")
    if len(others) > MAX_PAIR_WARNINGS:
        lines.append(f"{len(others) - MAX_PAIR_WARNINGS} more weak pairs: see pose/pairs.json")
    return lines


def _run_stage(context: StageContext) -> StageRun:
    pairs = len(context.sequence) - 1
    steps = progress_steps(len(context.sequence), context.config, pose_readout_ms(context.sequence, context.config))
    with context.progress(STAGE.title, steps) as update:
        result = run_pose(context.sequence, context.out, context.config,
                          progress=lambda done, total, kind: update(done, total, step=kind), threads=context.threads)
    weak = sum(1 for p in result.pairs if p.get("weak"))
    shutter = result.rolling_shutter
    deskewed = (f"; frames de-skewed for a rolling shutter of {shutter['readout_ms']:g} ms (rows up to "
                f"{shutter['skew_px']:.1f} px from their frame's pose)") if shutter else ""
    return StageRun(f"{pairs} pairs, {weak} weak{deskewed}",
                    weak_pair_warnings(context.sequence, result.pairs, context.config))


def _stage_inputs(out: Path, config: PoseConfig, poses: Path | None, points: Path | None) -> StageInputs:
    return StageInputs(folders=[Path(config.flow_dir)] if config.flow_dir else [])


STAGE = StageDeclaration(
    name="pose", title="stage 1: pose", config_type=PoseConfig, presets=PRESETS,
    outputs=("trajectory.txt", "points.ply", "pairs.json"), run=_run_stage, inputs=_stage_inputs,
)
