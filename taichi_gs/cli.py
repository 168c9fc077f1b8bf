"""The `taichi-gs` command line: thin wrappers from options to configs to stage calls."""

from __future__ import annotations

import dataclasses
import functools
import json
import platform
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from enum import Enum
from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from . import __version__
from .errors import BackendError, InputError

app = typer.Typer(
    help="Splat-based 3D reconstruction from RGB-D sequences with extreme motion blur.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console(stderr=True)
EXIT_BAD_INPUT = 2
EXIT_NOT_BUILT = 3


class Arch(str, Enum):
    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


class _State:
    arch: str = "auto"


state = _State()


def _fail(message: str, code: int) -> None:
    console.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def handles_errors(command: Callable[..., Any]) -> Callable[..., Any]:
    """Turn user-facing errors into one line on stderr and exit code 2."""

    @functools.wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return command(*args, **kwargs)
        except (InputError, BackendError) as err:
            _fail(str(err), EXIT_BAD_INPUT)

    return wrapper


@contextmanager
def progress_bar(description: str, total: int) -> Iterator[Callable[..., None]]:
    """A rich progress bar; yields ``update(done, total, **fields)``."""
    columns = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn(), TimeRemainingColumn(), TextColumn("{task.fields[info]}")]
    with Progress(*columns, console=console, transient=False) as progress:
        task = progress.add_task(description, total=total, info="")

        def update(done: int, total: int | None = None, **info: Any) -> None:
            text = "  ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in info.items())
            progress.update(task, completed=done, total=total, info=text)

        yield update


@app.callback()
def main(
    arch: Annotated[Arch, typer.Option(help="Taichi backend: auto picks CUDA only if a GPU is present.")] = Arch.auto,
    version: Annotated[bool, typer.Option("--version", help="Print the version and exit.")] = False,
) -> None:
    """taichi-gs: reconstruct a scene from a motion-blurred RGB-D sequence."""
    if version:
        typer.echo(__version__)
        raise typer.Exit()
    state.arch = arch.value


@app.command()
@handles_errors
def info() -> None:
    """Print versions, the Taichi backend actually obtained, and the kernel cache location."""
    import cv2
    import numpy
    import open3d
    import taichi

    from .kernels import runtime

    backend = runtime.init(state.arch)
    rows = {
        "taichi-gs": __version__,
        "python": platform.python_version(),
        "taichi": ".".join(map(str, taichi.__version__)),
        "numpy": numpy.__version__,
        "open3d": open3d.__version__,
        "opencv": cv2.__version__,
        "arch requested": state.arch,
        "arch obtained": backend.arch,
        "cpu threads": str(backend.cpu_threads),
        "kernel cache": backend.cache_dir,
    }
    for key, value in rows.items():
        typer.echo(f"{key:15s} {value}")


@app.command()
@handles_errors
def synth(
    out: Annotated[Path, typer.Argument(help="Folder to write the sequence into.")],
    frames: int = 60,
    width: int = 320,
    height: int = 240,
    trajectory: Annotated[str, typer.Option(help="translation | turn | handheld")] = "handheld",
    blur: Annotated[str, typer.Option(help="none | moderate | extreme")] = "extreme",
    seed: int = 0,
    noise: Annotated[bool, typer.Option(help="Sensor-like depth noise.")] = True,
    holes: Annotated[bool, typer.Option(help="Depth holes and dropouts.")] = True,
) -> None:
    """Generate a synthetic blurred RGB-D sequence with exact ground truth."""
    from .synth import SynthConfig, generate

    try:
        config = SynthConfig(width=width, height=height, frames=frames, trajectory=trajectory, blur=blur,
                             seed=seed, depth_noise=noise, holes=holes)
    except ValueError as err:
        raise InputError(None, str(err), "see 'taichi-gs synth --help'") from None
    with progress_bar("synth", frames) as update:
        generate(config, out, progress=lambda done, total: update(done, total))
    console.print(f"wrote {frames} frames to {out}")


@app.command("eval")
@handles_errors
def eval_(
    run_dir: Annotated[Optional[Path], typer.Argument(help="Output folder of a run.")] = None,
    gt: Annotated[Optional[Path], typer.Option(help="Sequence folder holding the ground truth.")] = None,
    traj: Annotated[Optional[Path], typer.Option(help="Estimated TUM trajectory.")] = None,
    gt_traj: Annotated[Optional[Path], typer.Option(help="Reference TUM trajectory.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
) -> None:
    """Evaluate a run folder (writes metrics.json) or a pair of TUM trajectories (--traj, --gt-traj)."""
    from .evaluate import match_by_time, trajectory_errors
    from .io.trajectory import read_tum

    if traj is not None or gt_traj is not None:
        if traj is None or gt_traj is None:
            raise InputError(None, "--traj and --gt-traj go together", "give both TUM files")
        t_est, est = read_tum(traj)
        t_ref, ref = read_tum(gt_traj)
        i, j = match_by_time(t_est, t_ref)
        if len(i) < 3:
            raise InputError(traj, f"only {len(i)} poses match {gt_traj.name} by timestamp (within 0.01 s)",
                             "give trajectories of the same sequence")
        result = trajectory_errors(est[i], ref[j]).as_dict()
        typer.echo(json.dumps(result) if as_json else "\n".join(f"{k:12s} {v}" for k, v in result.items()))
        return
    if run_dir is None:
        raise InputError(None, "nothing to evaluate", "give RUN_DIR, or --traj and --gt-traj")
    from .report import evaluate_run

    metrics = evaluate_run(run_dir, gt)
    typer.echo(json.dumps(metrics, indent=2) if as_json else f"wrote {run_dir / 'metrics.json'}")


def _intrinsics_override(fx, fy, cx, cy, depth_scale):
    from .io.sequence import IntrinsicsOverride

    return IntrinsicsOverride(fx=fx, fy=fy, cx=cx, cy=cy, depth_scale=depth_scale)


FxOption = Annotated[Optional[float], typer.Option("--fx", help="Focal length x (px); wins over intrinsics.json.")]
FyOption = Annotated[Optional[float], typer.Option("--fy", help="Focal length y (px).")]
CxOption = Annotated[Optional[float], typer.Option("--cx", help="Principal point x (px).")]
CyOption = Annotated[Optional[float], typer.Option("--cy", help="Principal point y (px).")]
DepthScaleOption = Annotated[Optional[float], typer.Option("--depth-scale", help="Depth PNG units per metre (TUM: 5000).")]


@app.command()
@handles_errors
def pose(
    folder: Annotated[Path, typer.Argument(help="Input sequence folder (TUM or taichi-gs layout).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder; results go to OUT/pose/.")],
    flow_dir: Annotated[Optional[Path], typer.Option(help="Precomputed flows (.flo or .npy, one per pair).")] = None,
    config_file: Annotated[Optional[Path], typer.Option("--config", help="TOML file with a [pose] table.")] = None,
    fx: FxOption = None, fy: FyOption = None, cx: CxOption = None, cy: CyOption = None,
    depth_scale: DepthScaleOption = None,
) -> None:
    """Stage 1: relative poses from optical flow and depth, refined by ICP, chained; fused point cloud."""
    from .config import read_config, write_config
    from .io.sequence import load_sequence
    from .report import write_run_info
    from .stages.pose import PoseConfig, run_pose

    _check_output_folder(folder, out)
    sequence = load_sequence(folder, _intrinsics_override(fx, fy, cx, cy, depth_scale))
    config = PoseConfig()
    if config_file is not None:
        config = read_config(config_file, {"pose": config})["pose"]
    if flow_dir is not None:
        config = dataclasses.replace(config, flow_dir=str(flow_dir))
    write_run_info(out, folder)
    write_config(out / "pose" / "config.toml", {"pose": config})
    with progress_bar("stage 1: pose", len(sequence) - 1) as update:
        result = run_pose(sequence, out, config, progress=lambda done, total: update(done, total))
    weak = sum(1 for p in result.pairs if p.get("weak"))
    console.print(f"stage 1 done: {len(sequence) - 1} pairs, {weak} weak; results in {out / 'pose'}")


class Preset(str, Enum):
    fast = "fast"
    paper = "paper"


@app.command()
@handles_errors
def refine(
    out: Annotated[Path, typer.Argument(help="Run folder holding pose/ from stage 1; results go to OUT/refine/.")],
    poses: Annotated[Optional[Path], typer.Option(help="TUM trajectory to start from (default OUT/pose/trajectory.txt).")] = None,
    points: Annotated[Optional[Path], typer.Option(help="Fused point cloud PLY (default OUT/pose/points.ply).")] = None,
    preset: Annotated[Preset, typer.Option(help="fast: a CPU-sized schedule; paper: the method's 600 N iterations.")] = Preset.fast,
    config_file: Annotated[Optional[Path], typer.Option("--config", help="TOML file with a [refine] table.")] = None,
) -> None:
    """Stage 2: refine poses, positions and opacities of fixed-scale Gaussians against the input depth."""
    from .config import read_config, write_config
    from .io.sequence import load_sequence
    from .report import sequence_folder
    from .stages.refine import PRESETS, load_stage1, run_refine

    _, initial, cloud, colors, voxel = load_stage1(out, poses, points)
    sequence = load_sequence(sequence_folder(out))
    config = PRESETS[preset.value]
    if config_file is not None:
        config = read_config(config_file, {"refine": config})["refine"]
    if config.voxel_size <= 0:
        config = dataclasses.replace(config, voxel_size=voxel)
    _init_backend()
    write_config(out / "refine" / "config.toml", {"refine": config})
    total = config.iterations_per_frame * len(sequence)
    with progress_bar("stage 2: refine", total) as update:
        result = run_refine(sequence, initial, cloud, colors, out, config, progress=update)
    console.print(f"stage 2 done: {result.gaussians} Gaussians, {result.seconds_per_iteration * 1000:.1f} ms/iteration; "
                  f"results in {out / 'refine'}")


def _init_backend() -> None:
    from .kernels import runtime

    backend = runtime.init(state.arch)
    console.print(f"Taichi backend: {backend.arch}", highlight=False)


def _check_output_folder(folder: Path, out: Path) -> None:
    """Refuse to write inside the input folder."""
    folder, target = folder.resolve(), out.resolve()
    if target == folder or folder in target.parents:
        raise InputError(out, "output folder lies inside the input folder", "choose an --out outside the input (inputs are never written to)")


def _not_built(name: str, issue: str) -> Callable[..., None]:
    def command() -> None:
        _fail(f"'{name}' is not built yet ({issue}); nothing was run", EXIT_NOT_BUILT)

    command.__doc__ = f"[not built yet] {issue}."
    return command


for _name, _issue in {
    "reconstruct": "end-to-end issue: runs pose, refine and deblur",
    "deblur": "stage 3: deblurring",
    "render": "end-to-end issue: renders from a finished run",
    "export": "end-to-end issue: nerfstudio/COLMAP/PLY export",
}.items():
    app.command(_name, context_settings={"allow_extra_args": True, "ignore_unknown_options": True})(_not_built(_name, _issue))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
