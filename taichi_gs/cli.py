"""The `taichi-gs` command line: thin wrappers from options to configs to stage calls."""

from __future__ import annotations

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
    console.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True)
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


def _not_built(name: str, issue: str) -> Callable[..., None]:
    def command() -> None:
        _fail(f"'{name}' is not built yet ({issue}); nothing was run", EXIT_NOT_BUILT)

    command.__doc__ = f"[not built yet] {issue}."
    return command


for _name, _issue in {
    "reconstruct": "end-to-end issue: runs pose, refine and deblur",
    "pose": "stage 1: local pose",
    "refine": "stage 2: global refinement",
    "deblur": "stage 3: deblurring",
    "render": "end-to-end issue: renders from a finished run",
    "export": "end-to-end issue: nerfstudio/COLMAP/PLY export",
}.items():
    app.command(_name, context_settings={"allow_extra_args": True, "ignore_unknown_options": True})(_not_built(_name, _issue))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
