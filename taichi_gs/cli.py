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
EXIT_DIVERGED = 4
EXIT_INTERRUPTED = 130


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
    """Turn user-facing errors into one line on stderr: bad input exits 2, a diverging optimiser 4,
    Ctrl-C 130 (outputs are atomic, so rerunning the same command resumes)."""

    @functools.wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return command(*args, **kwargs)
        except (InputError, BackendError) as err:
            _fail(str(err), EXIT_BAD_INPUT)
        except FloatingPointError as err:
            _fail(f"{err}; nothing was written for this stage. Lower its learning rates in --config", EXIT_DIVERGED)
        except KeyboardInterrupt:
            _fail("interrupted; finished work is kept: rerun the same command to resume", EXIT_INTERRUPTED)

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


@app.callback(invoke_without_command=True)
def main(
    ctx: typer.Context,
    arch: Annotated[Arch, typer.Option(help="Taichi backend: auto picks CUDA only if a GPU is present.")] = Arch.auto,
    version: Annotated[bool, typer.Option("--version", help="Print the version and exit.")] = False,
) -> None:
    """taichi-gs: reconstruct a scene from a motion-blurred RGB-D sequence."""
    if version:
        typer.echo(__version__)
        raise typer.Exit()
    if ctx.invoked_subcommand is None:
        typer.echo(ctx.get_help())
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
ConfigOption = Annotated[Optional[Path], typer.Option("--config", help="TOML file with [pose], [refine], [deblur] tables.")]


@app.command()
@handles_errors
def pose(
    folder: Annotated[Path, typer.Argument(help="Input sequence folder (TUM or taichi-gs layout).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder; results go to OUT/pose/.")],
    flow_dir: Annotated[Optional[Path], typer.Option(help="Precomputed flows (.flo or .npy, one per pair).")] = None,
    config_file: ConfigOption = None,
    fx: FxOption = None, fy: FyOption = None, cx: CxOption = None, cy: CyOption = None,
    depth_scale: DepthScaleOption = None,
) -> None:
    """Stage 1: relative poses from optical flow and depth, refined by ICP, chained; fused point cloud."""
    from .io.sequence import load_sequence
    from .pipeline import resolve_sections, run_stage, write_run_info

    _check_output_folder(folder, out)
    sequence = load_sequence(folder, _intrinsics_override(fx, fy, cx, cy, depth_scale))
    config = resolve_sections("fast", config_file, only=("pose",))["pose"]
    if flow_dir is not None:
        config = dataclasses.replace(config, flow_dir=str(flow_dir))
    write_run_info(out, folder)
    _, summary = run_stage("pose", sequence, out, config, progress_bar)
    console.print(f"stage 1 done: {summary}; results in {out / 'pose'}")


class Preset(str, Enum):
    fast = "fast"
    paper = "paper"


PresetOption = Annotated[Preset, typer.Option(help="fast: CPU-sized schedules; paper: the method's schedules.")]


@app.command()
@handles_errors
def refine(
    out: Annotated[Path, typer.Argument(help="Run folder holding pose/ from stage 1; results go to OUT/refine/.")],
    poses: Annotated[Optional[Path], typer.Option(help="TUM trajectory to start from (default OUT/pose/trajectory.txt).")] = None,
    points: Annotated[Optional[Path], typer.Option(help="Fused point cloud PLY (default OUT/pose/points.ply).")] = None,
    preset: PresetOption = Preset.fast,
    config_file: ConfigOption = None,
) -> None:
    """Stage 2: refine poses, positions and opacities of fixed-scale Gaussians against the input depth."""
    from .io.sequence import load_sequence
    from .pipeline import resolve_sections, run_stage, sequence_folder

    sequence = load_sequence(sequence_folder(out))
    config = resolve_sections(preset.value, config_file, only=("refine",))["refine"]
    _init_backend()
    _, summary = run_stage("refine", sequence, out, config, progress_bar, poses=poses, points=points)
    console.print(f"stage 2 done: {summary}; results in {out / 'refine'}")


@app.command()
@handles_errors
def reconstruct(
    folder: Annotated[Path, typer.Argument(help="Input sequence folder (TUM or taichi-gs layout).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder (pose/, refine/, deblur/, config.toml).")],
    preset: PresetOption = Preset.fast,
    config_file: ConfigOption = None,
    force: Annotated[Optional[str], typer.Option(help="Rerun from this stage on: pose | refine | deblur.")] = None,
    fx: FxOption = None, fy: FyOption = None, cx: CxOption = None, cy: CyOption = None,
    depth_scale: DepthScaleOption = None,
) -> None:
    """All three stages end to end; a rerun skips finished stages and resumes an interrupted one."""
    from .io.sequence import load_sequence
    from .pipeline import reconstruct as run_all
    from .pipeline import resolve_sections

    _check_output_folder(folder, out)
    sequence = load_sequence(folder, _intrinsics_override(fx, fy, cx, cy, depth_scale))
    sequence.check_all()
    sections = resolve_sections(preset.value, config_file)
    _init_backend()

    def report(stage) -> None:
        verb = "done" if stage.ran else "already done, skipped"
        console.print(f"{stage.stage}: {verb} ({stage.summary}; {stage.seconds:.1f} s)", highlight=False)

    run_all(sequence, out, sections, progress_bar, force=force, on_stage=report)
    console.print(f"finished: results in {out}/deblur (splats.ply, renders/, grid.png); "
                  f"next: 'taichi-gs eval {out}' for metrics and plots in {out}/report", highlight=False)


class PathKind(str, Enum):
    orbit = "orbit"
    trajectory = "trajectory"


@app.command()
@handles_errors
def render(
    out: Annotated[Path, typer.Argument(help="Finished run folder.")],
    path: Annotated[PathKind, typer.Option(help="orbit: circle around the scene; trajectory: along the cameras.")] = PathKind.orbit,
    frames: Annotated[int, typer.Option(min=2, help="Number of views.")] = 60,
    scale: Annotated[float, typer.Option(min=0.1, max=4.0, help="Image size relative to the input.")] = 1.0,
) -> None:
    """Sharp renders of the newest splats along a camera path: OUT/render/PATH/*.png and PATH.gif."""
    from .export import render_path
    from .io.sequence import load_sequence
    from .pipeline import sequence_folder

    sequence = load_sequence(sequence_folder(out))
    _init_backend()
    with progress_bar(f"render {path.value}", frames) as update:
        target = render_path(out, sequence, path.value, frames, scale, progress=update)
    console.print(f"wrote {frames} views to {target} and {target}.gif")


class ExportFormat(str, Enum):
    nerfstudio = "nerfstudio"
    colmap = "colmap"
    ply = "ply"


@app.command()
@handles_errors
def export(
    out: Annotated[Path, typer.Argument(help="Finished run folder.")],
    format: Annotated[ExportFormat, typer.Option("--format", help="nerfstudio | colmap | ply")] = ExportFormat.nerfstudio,
    dest: Annotated[Optional[Path], typer.Option(help="Target folder (default OUT/export/FORMAT).")] = None,
) -> None:
    """Write the result for other tools: nerfstudio transforms.json, COLMAP text model, or PLYs."""
    from .export import export_colmap, export_nerfstudio, export_ply
    from .io.sequence import load_sequence
    from .pipeline import sequence_folder

    dest = dest or out / "export" / format.value
    if format is ExportFormat.ply:
        written = export_ply(out, dest)
    else:
        sequence = load_sequence(sequence_folder(out))
        exporter = export_nerfstudio if format is ExportFormat.nerfstudio else export_colmap
        written = exporter(out, sequence, dest)
    console.print(f"exported {format.value} to {written}")


@app.command()
@handles_errors
def deblur(
    out: Annotated[Path, typer.Argument(help="Run folder holding refine/ from stage 2; results go to OUT/deblur/.")],
    preset: PresetOption = Preset.fast,
    config_file: ConfigOption = None,
    k: Annotated[Optional[int], typer.Option("--k", min=1, help="Virtual sharp views per exposure (default: the preset's).")] = None,
    holdout: Annotated[Optional[str], typer.Option(help="Hold out every N-th frame as a test view, 'none', or 'sharpest' (the sharpest of every N frames; for real data).")] = None,
) -> None:
    """Stage 3: train sharp Gaussians and each frame's exposure start/end poses through the k-view blur model."""
    from .io.sequence import load_sequence
    from .pipeline import resolve_sections, run_stage, sequence_folder

    sequence = load_sequence(sequence_folder(out))
    config = resolve_sections(preset.value, config_file, only=("deblur",))["deblur"]
    changes: dict[str, int | str] = {} if k is None else {"k": k}
    if holdout is not None and holdout.strip().lower() == "sharpest":
        changes["holdout"] = "sharpest"
    elif holdout is not None:
        changes["holdout_every"] = _holdout_every(holdout)
    config = dataclasses.replace(config, **changes)
    _init_backend()
    _, summary = run_stage("deblur", sequence, out, config, progress_bar)
    console.print(f"stage 3 done: {summary}; results in {out / 'deblur'}", highlight=False)


def _holdout_every(text: str) -> int:
    """``--holdout`` value: 'none' -> 0, else a positive integer."""
    if text.strip().lower() == "none":
        return 0
    if not text.strip().isdigit() or int(text) < 2:
        raise InputError(None, f"--holdout {text!r} is not 'none' or an integer of at least 2", "e.g. --holdout 3 or --holdout none")
    return int(text)


def _init_backend() -> None:
    from .kernels import runtime

    backend = runtime.init(state.arch)
    console.print(f"Taichi backend: {backend.arch}", highlight=False)


def _check_output_folder(folder: Path, out: Path) -> None:
    """Refuse to write inside the input folder."""
    folder, target = folder.resolve(), out.resolve()
    if target == folder or folder in target.parents:
        raise InputError(out, "output folder lies inside the input folder", "choose an --out outside the input (inputs are never written to)")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
