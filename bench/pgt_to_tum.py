"""Convert a 7-Scenes pseudo ground truth file (one line per image: ``seq-NN/frame-NNNNNN.color.png qw qx
qy qz tx ty tz f``, world-to-camera as COLMAP writes it; Brachmann et al., "On the Limits of Pseudo Ground Truth in
Visual Camera Re-localisation", ICCV 2021) into a TUM trajectory of one sequence, camera-to-world, stamped frame / 30
as taichi-gs's 7-Scenes reader stamps the frames, for ``bench/pose.py --reference``.

    python bench/pgt_to_tum.py PGT.txt --sequence seq-01 --out sfm_seq01.txt
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

from taichi_gs.geometry import invert, pose_from_rt, quat_to_rotmat
from taichi_gs.io.formats.common import NOMINAL_FPS
from taichi_gs.io.trajectory import write_tum

LINE = re.compile(r"(?P<sequence>[^/\s]+)/frame-(?P<frame>\d+)\.color\.\w+\s+(?P<numbers>.+)")


def read_pgt(path: Path, sequence: str) -> tuple[np.ndarray, np.ndarray]:
    """(frame numbers, camera-to-world poses) of ``sequence``'s lines in ``path``, in frame order."""
    frames, poses = [], []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        match = LINE.match(line.strip())
        if match is None or match["sequence"] != sequence:
            continue
        values = [float(v) for v in match["numbers"].split()]
        if len(values) < 7:
            raise SystemExit(f"{path}:{number}: expected qw qx qy qz tx ty tz after the image name")
        world_to_camera = pose_from_rt(quat_to_rotmat(values[:4]), np.array(values[4:7]))
        frames.append(int(match["frame"]))
        poses.append(invert(world_to_camera))
    if not frames:
        raise SystemExit(f"{path}: no line for {sequence}/frame-NNNNNN.color.*")
    order = np.argsort(frames)
    return np.array(frames)[order], np.stack(poses)[order]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("pgt", type=Path)
    parser.add_argument("--sequence", default="seq-01", help="the folder name the lines start with")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    frames, poses = read_pgt(args.pgt, args.sequence)
    write_tum(args.out, frames / NOMINAL_FPS, poses, header=f"{args.pgt.name} {args.sequence}, camera-to-world")
    print(f"{args.out}: {len(frames)} poses, frames {frames[0]}-{frames[-1]}")


if __name__ == "__main__":
    main()
