"""[ours] Stage 2's acceptance test: keep the refined trajectory only if it explains the frames at
least as well as stage 1's did, judged by stage 1's own depth + colour verification score.

Stage 2 fits poses to depth alone, through Gaussians whose footprint smooths every depth step; along
planes and low-relief structure its loss barely constrains a pose, and the positions it trains at the
same time can absorb a pose's error. Started from good poses it can move them away from the truth while
its own loss goes down (from exact ground truth too). :mod:`taichi_gs.stages.pose.verify` is an independent
judge that also uses colour, which constrains motion along planes. Both trajectories are scored on the
same edges, every (i, j) with 0 < i - j <= ``neighbours``, as the mean verification score of the
relative poses; the refined one is kept if its mean is not higher.

The whole trajectory is accepted or rejected: choosing per frame (tried) mixes two trajectories whose
frames agree with their own neighbours but not with each other's, and measured worse.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...geometry import invert
from ...io.sequence import Sequence
from ..pose.verify import FrameView, VerifySettings, frame_view, verify


@dataclass(frozen=True)
class Acceptance:
    """Mean verification score of each trajectory over the same edges, and which one was kept."""

    neighbours: int
    edges: int
    stage1_score: float
    refined_score: float
    kept_refined: bool

    def to_dict(self) -> dict:
        return {"neighbours": self.neighbours, "edges": self.edges, "stage1_score": round(self.stage1_score, 6),
                "refined_score": round(self.refined_score, 6), "kept_refined": self.kept_refined}


def trajectory_score(poses: np.ndarray, views: list[FrameView], K: np.ndarray, neighbours: int,
                     settings: VerifySettings = VerifySettings()) -> tuple[float, int]:
    """Mean verification score of the relative poses of every (i, j), 0 < i - j <= ``neighbours``,
    over the edges that overlap, and their number (lower score is better)."""
    scores = []
    for i in range(1, len(poses)):
        for j in range(max(0, i - neighbours), i):
            score = verify(invert(poses[j]) @ poses[i], views[i], views[j], K, settings).score
            if np.isfinite(score):
                scores.append(score)
    return (float(np.mean(scores)) if scores else float("inf")), len(scores)


def accept_refined_poses(sequence: Sequence, stage1: np.ndarray, refined: np.ndarray, neighbours: int = 3,
                         settings: VerifySettings = VerifySettings()) -> tuple[np.ndarray, Acceptance]:
    """The refined poses if their mean verification score is not higher than stage 1's, else stage 1's."""
    K = sequence.K()
    views = [frame_view(sequence.color(i), sequence.depth(i), K, settings) for i in range(len(sequence))]
    before, edges = trajectory_score(stage1, views, K, neighbours, settings)
    after, _ = trajectory_score(refined, views, K, neighbours, settings)
    keep = after <= before
    return (refined if keep else stage1).copy(), Acceptance(neighbours, edges, before, after, bool(keep))
