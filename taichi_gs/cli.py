"""The `taichi-gs` command line: thin wrappers from options to configs to stage calls."""

from __future__ import annotations

import dataclasses
import errno
import functools
import platform
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, Optional, TypeVar

import typer
from rich.markup import escape

from . import __version__
from .choices import (
    ARCH_CHOICES,
    BLUR_LEVELS,
    EXPORT_FORMATS,
    PRESET_NAMES,
    RENDER_PATHS,
    SCENES,
    TRAJECTORIES,
)
from .cli_options import (
    AS_FOUND,
    CommandGroup,
    InputOptions,
    choices,
    parse_holdout,
    state,
    with_input_options,
)
from .errors import BackendError, DivergenceError, InputError
from .stages.declaration import STAGE_NAMES
from .terminal import Verbosity, configure_logging, console, progress_bar

app = typer.Typer(
    cls=CommandGroup,
    help="Splat-based 3D reconstruction from RGB-D sequences with extreme motion blur. "
         "The options below may also follow the command (taichi-gs pose --arch cpu ...).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 4
EXIT_INTERRUPTED = 130
MAX_SYNTH_FRAMES = 10_000
MAX_SYNTH_SIZE = 4096


Arch = choices("Arch", ARCH_CHOICES)


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
        except DivergenceError as err:
            _fail(f"{err}; the stage is not marked done and its last checkpoint is kept. Lower its learning "
                  "rates in --config", EXIT_DIVERGED)
        except OSError as err:
            _fail(_os_error_message(err), EXIT_BAD_INPUT)
        except KeyboardInterrupt:
            _fail("interrupted; finished work is kept: rerun the same command to resume", EXIT_INTERRUPTED)

    return wrapper


def _os_error_message(err: OSError) -> str:
    """One line for a file-system failure: the path, what happened, what to do."""
    where = f"{err.filename}: " if err.filename else ""
    fixes = {errno.ENOSPC: "free disk space and rerun the same command (finished work is kept)",
             errno.EROFS: "choose an --out on a writable file system",
             errno.EACCES: "choose an --out you may write to, or fix the permissions",
             errno.EPERM: "choose an --out you may write to, or fix the permissions",
             errno.ENOTDIR: "a path component is a file, not a folder: choose another path",
             errno.EEXIST: "the path exists and is not a folder: choose another path"}
    fix = fixes.get(err.errno, "check the path, free space and permissions")
    return f"{where}{err.strerror or err}; {fix}"


@app.callback(invoke_without_command=True)
def main(
    ctx: typer.Context,
    arch: Annotated[Arch, typer.Option(
        envvar="TAICHI_GS_ARCH",
        help="Taichi backend: auto takes CUDA, then Metal (macOS) or a hardware Vulkan GPU, then the CPU.",
    )] = Arch.auto,
    version: Annotated[bool, typer.Option("--version", help="Print the version and exit.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Print only warnings and errors (OUT/log.txt still gets everything).")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Also print debug messages, and a progress line per step when not on a terminal.")] = False,
) -> None:
    """taichi-gs: reconstruct a scene from a motion-blurred RGB-D sequence."""
    if quiet and verbose:
        raise typer.BadParameter("--quiet and --verbose exclude each other")
    state.verbosity = Verbosity.QUIET if quiet else Verbosity.VERBOSE if verbose else Verbosity.NORMAL
    configure_logging(state.verbosity)
    if version:
        typer.echo(__version__)
        raise typer.Exit()
    if ctx.invoked_subcommand is None:
        typer.echo(ctx.get_help())
        raise typer.Exit()
    state.arch = arch.value


def _open3d_version() -> str:
    from .stages.pose.icp import open3d

    try:
        return open3d().__version__
    except ImportError:
        return "not installed (stage 1 needs it; stages 2 and 3 run without it)"


@app.command()
@handles_errors
def info() -> None:
    """Print versions, the Taichi backend actually obtained, and the kernel cache location."""
    import cv2
    import numpy

    from .kernels import runtime  # first: it keeps Taichi's banner off stdout

    import taichi

    backend = runtime.init(state.arch)
    from .stages.pose import PoseConfig, stage_threads

    rows = {
        "taichi-gs": __version__,
        "python": platform.python_version(),
        "taichi": ".".join(map(str, taichi.__version__)),
        "numpy": numpy.__version__,
        "open3d": _open3d_version(),
        "opencv": cv2.__version__,
        "arch requested": state.arch,
        "arch obtained": backend.arch,
        "device": backend.device,
        "cpu threads": str(backend.cpu_threads),
        "stage 1 threads": str(stage_threads(PoseConfig())),
        "kernel cache": backend.cache_dir,
    }
    for key, value in rows.items():
        typer.echo(f"{key:15s} {value}")


SynthTrajectory = choices("SynthTrajectory", TRAJECTORIES)
SynthScene = choices("SynthScene", SCENES)
SynthBlur = choices("SynthBlur", BLUR_LEVELS)


@app.command()
@handles_errors
def synth(
    out: Annotated[Path, typer.Argument(help="Folder to write the sequence into (new or empty; see --overwrite).")],
    frames: Annotated[int, typer.Option(min=2, max=MAX_SYNTH_FRAMES, help="Number of frames (30 per second).")] = 60,
    width: Annotated[int, typer.Option(min=16, max=MAX_SYNTH_SIZE, help="Image width in pixels.")] = 320,
    height: Annotated[int, typer.Option(min=16, max=MAX_SYNTH_SIZE, help="Image height in pixels.")] = 240,
    trajectory: Annotated[SynthTrajectory, typer.Option(help="Camera motion: translation, turn in place, or hand-held shake.")] = SynthTrajectory.handheld,
    scene: Annotated[SynthScene, typer.Option(help="Room kind: textured room with objects, office with furniture, plain (low-texture, planar), corridor.")] = SynthScene.room,
    blur: Annotated[SynthBlur, typer.Option(help="Motion blur: none, moderate (~7 px at 640 wide) or extreme (~30 px).")] = SynthBlur.extreme,
    seed: Annotated[int, typer.Option(help="Random seed of the scene, trajectory and noise.")] = 0,
    noise: Annotated[bool, typer.Option(help="Sensor-like depth noise.")] = True,
    holes: Annotated[bool, typer.Option(help="Depth holes and dropouts.")] = True,
    readout_ms: Annotated[float, typer.Option(help="Rolling shutter: rows read top to bottom over this many ms (0: global shutter; Kinect v1 colour: about 25).")] = 0.0,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing sequence made by synth in OUT.")] = False,
) -> None:
    """Generate a synthetic blurred RGB-D sequence with exact ground truth."""
    from .io.atomic import atomic_folder
    from .synth import SynthConfig, generate

    try:
        config = SynthConfig(width=width, height=height, frames=frames, trajectory=trajectory.value, scene=scene.value,
                             blur=blur.value, seed=seed, depth_noise=noise, holes=holes, readout_ms=readout_ms)
    except ValueError as err:
        raise InputError(None, str(err), "see 'taichi-gs synth --help'") from None
    if out.exists() and not out.is_dir():
        raise InputError(out, "is a file, not a folder", "give a folder path to write the sequence into")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise InputError(out, "folder is not empty", "give a new folder, or --overwrite to replace a synth sequence")
        if not (out / "synth.json").is_file():
            raise InputError(out, "folder holds something other than a synth sequence (no synth.json)",
                             "give a new folder; --overwrite only replaces sequences made by synth")
    with atomic_folder(out) as staging, progress_bar("synth", frames) as update:
        generate(config, staging, progress=lambda done, total: update(done, total))
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
    """Evaluate a run folder (writes metrics.json and report/; without ground-truth poses or sharp frames, the
    figures that need none, naming the rest) or a pair of TUM trajectories (--traj, --gt-traj)."""
    from .evaluate import match_by_time
    from .io import jsonout
    from .io.trajectory import read_tum
    from .report import trajectory_record

    if traj is not None or gt_traj is not None:
        if traj is None or gt_traj is None:
            raise InputError(None, "--traj and --gt-traj go together", "give both TUM files")
        t_est, est = read_tum(traj)
        t_ref, ref = read_tum(gt_traj)
        i, j = match_by_time(t_est, t_ref)
        if len(i) < 3:
            raise InputError(traj, f"only {len(i)} poses match {gt_traj.name} by timestamp (within 0.01 s)",
                             "give trajectories of the same sequence")
        dropped = [] if len(i) == len(t_est) else [{"reason": f"no pose of {gt_traj.name} within 0.01 s",
                                                   "count": len(t_est) - len(i), "frames": []}]
        result = trajectory_record(est[i], ref[j], dropped)
        typer.echo(jsonout.dumps(result) if as_json else "\n".join(f"{k:12s} {v}" for k, v in result.items()))
        return
    if run_dir is None:
        raise InputError(None, "nothing to evaluate", "give RUN_DIR, or --traj and --gt-traj")
    from .report import evaluate_run, format_metrics

    from .io.lock import output_lock

    if not run_dir.is_dir():
        raise InputError(run_dir, "run folder not found", "give the --out folder of a taichi-gs run")
    with output_lock(run_dir):
        metrics = evaluate_run(run_dir, gt)
    if as_json:
        typer.echo(jsonout.dumps(metrics, indent=2))
    else:
        typer.echo(format_metrics(metrics))
        console.print(f"wrote {run_dir / 'metrics.json'} and plots in {run_dir / 'report'}", highlight=False)


Preset = choices("Preset", PRESET_NAMES)
Stage = choices("Stage", STAGE_NAMES)


PresetOption = Annotated[Preset, typer.Option(help=(
    "fast (default): ours, CPU-sized schedules with every addition of ours on (verified pair candidates, RGB-D "
    "odometry, pose graph, rolling shutter, warped views, adaptive k, colour transforms, ...); paper: the paper's "
    "method exactly, its schedules and none of our additions (DIS in place of Unimatch)."))]


ConfigOption = Annotated[Optional[Path], typer.Option("--config", help="TOML file with \\[pose], \\[refine], \\[deblur] tables.")]
ProfileOption = Annotated[bool, typer.Option("--profile", help="Write OUT/profile.json and OUT/profile.md: wall and "
                                          "CPU seconds per stage and per kind of work (flow, ICP, renders, losses, ...).")]
READOUT_STAGES = ("pose", "refine", "deblur")  # the sections a rolling shutter's --readout-ms sets
StageConfig = TypeVar("StageConfig")
ReadoutOption = Annotated[Optional[float], typer.Option("--readout-ms", min=0.0, help="Rolling shutter: the camera reads its rows top to bottom over this many ms (0: a global shutter; default: the preset's, which in fast is 25 for TUM fr1 and 7-Scenes (Kinect v1) and 0 otherwise).")]


def with_readout(config: StageConfig, readout_ms: float | None) -> StageConfig:
    """``config`` with the user's ``--readout-ms``, which (0 included) stands over a known camera's readout."""
    if readout_ms is None:
        return config
    return dataclasses.replace(config, readout_ms=readout_ms, camera_readout=False)


@app.command()
@handles_errors
@with_input_options
def pose(
    folder: Annotated[Path, typer.Argument(help="Input sequence folder (TUM or taichi-gs layout).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder; results go to OUT/pose/.")],
    flow_dir: Annotated[Optional[Path], typer.Option(help="Precomputed flows (.flo or .npy, one per pair).")] = None,
    preset: PresetOption = Preset.fast,
    config_file: ConfigOption = None,
    reading: InputOptions = AS_FOUND,
    readout_ms: ReadoutOption = None,
    profile: ProfileOption = False,
) -> None:
    """Stage 1: relative poses from optical flow and depth, refined by ICP, chained; fused point cloud."""
    from . import pipeline
    from .io.lock import output_lock
    from .pipeline import check_run_input, resolve_sections, write_run_info
    from .validation import validate_sections

    _check_output_folder(folder, out)
    config = with_readout(resolve_sections(preset.value, config_file, only=("pose",))["pose"], readout_ms)
    validate_sections({"pose": config})
    if flow_dir is not None:
        config = dataclasses.replace(config, flow_dir=str(flow_dir))
    sequence = reading.load(folder)
    _init_backend()
    with output_lock(out), _profiled(profile, out) as threads:
        check_run_input(out, sequence)
        write_run_info(out, sequence)
        summary = pipeline.run_stage("pose", sequence, out, config, progress_bar, threads=threads)
    console.print(f"stage 1 done: {summary}; results in {out / 'pose'}")


@app.command("import")
@handles_errors
@with_input_options
def import_(
    folder: Annotated[Path, typer.Argument(help="Input sequence folder, any readable layout (see --format).")],
    out: Annotated[Path, typer.Option("--out", help="New folder to write the taichi-gs layout into.")],
    reading: InputOptions = AS_FOUND,
    average: Annotated[int, typer.Option("--average", min=1, help=(
        "Average each W consecutive frames (W odd) in linear light into one long exposure: real motion blur "
        "whose sharp reference (sharp/), depth, time and pose are the centre frame's; --count counts the "
        "averaged frames; writes blur.json (each frame's measured streak)."))] = 1,
) -> None:
    """Convert a sequence to taichi-gs's own layout (frames.txt, rgb/, depth/, intrinsics.json, groundtruth.txt)."""
    from .io.average import AveragedSequence
    from .io.convert import import_sequence

    _check_output_folder(folder, out)
    sequence = dataclasses.replace(reading, count=reading.count * average).load(folder)
    if average > 1:
        sequence = AveragedSequence(sequence, average)
    with progress_bar("import", len(sequence)) as update:
        import_sequence(sequence, out, progress=lambda done, total: update(done, total))
    console.print(f"wrote {len(sequence)} frames ({sequence.source['format']}) to {out}", highlight=False)


@app.command()
@handles_errors
def refine(
    out: Annotated[Path, typer.Argument(help="Run folder holding pose/ from stage 1; results go to OUT/refine/.")],
    poses: Annotated[Optional[Path], typer.Option(help="TUM trajectory to start from (default OUT/pose/trajectory.txt).")] = None,
    points: Annotated[Optional[Path], typer.Option(help="Fused point cloud PLY (default OUT/pose/points.ply).")] = None,
    preset: PresetOption = Preset.fast,
    config_file: ConfigOption = None,
    profile: ProfileOption = False,
) -> None:
    """Stage 2: refine poses, positions and opacities of fixed-scale Gaussians against the input depth."""
    from . import pipeline
    from .io.lock import output_lock
    from .pipeline import open_run_sequence, resolve_sections, resolve_stage

    sections = resolve_sections(preset.value, config_file, only=("pose", "refine"))
    config = resolve_stage("refine", sections, out)
    for given in (poses, points):
        if given is not None and not given.is_file():
            raise InputError(given, "file not found", "give an existing TUM trajectory (--poses) or PLY (--points)")
    sequence = open_run_sequence(out)
    _init_backend()
    with output_lock(out), _profiled(profile, out):
        summary = pipeline.run_stage("refine", sequence, out, config, progress_bar, poses=poses,
                                     points=points)  # --profile wraps it
    console.print(f"stage 2 done: {summary}; results in {out / 'refine'}")


@app.command()
@handles_errors
@with_input_options
def reconstruct(
    folder: Annotated[Path, typer.Argument(help="Input sequence folder (TUM or taichi-gs layout).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder (pose/, refine/, deblur/, config.toml).")],
    preset: PresetOption = Preset.fast,
    config_file: ConfigOption = None,
    force: Annotated[Optional[Stage], typer.Option(help="Rerun from this stage on.")] = None,
    reading: InputOptions = AS_FOUND,
    readout_ms: ReadoutOption = None,
    profile: ProfileOption = False,
) -> None:
    """All three stages end to end; a rerun skips finished stages and resumes an interrupted one."""
    from .io.lock import output_lock
    from .pipeline import reconstruct as run_all
    from .pipeline import resolve_sections
    from .validation import validate_sections

    _check_output_folder(folder, out)
    sections = {name: with_readout(section, readout_ms) if name in READOUT_STAGES else section
                for name, section in resolve_sections(preset.value, config_file).items()}
    validate_sections(sections)
    sequence = reading.load(folder)
    sequence.check_all()
    _init_backend()

    def report(stage) -> None:
        verb = "done" if stage.ran else "already done, skipped"
        console.print(f"{stage.stage}: {verb} ({stage.summary}; {stage.seconds:.1f} s)", highlight=False)

    with output_lock(out), _profiled(profile, out) as threads:
        run_all(sequence, out, sections, progress_bar, force=None if force is None else force.value, on_stage=report,
                threads=threads)
    console.print(f"finished: results in {out}/deblur (splats.ply, renders/, grid.png); "
                  f"next: 'taichi-gs eval {out}' for metrics and plots in {out}/report", highlight=False)


PathKind = choices("PathKind", RENDER_PATHS)


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
    from .io.lock import output_lock
    from .pipeline import open_run_sequence

    sequence = open_run_sequence(out)
    _init_backend()
    with output_lock(out), progress_bar(f"render {path.value}", frames) as update:
        target = render_path(out, sequence, path.value, frames, scale, progress=update)
    console.print(f"wrote {frames} views to {target} and {target}.gif")


ExportFormat = choices("ExportFormat", EXPORT_FORMATS)


@app.command()
@handles_errors
def export(
    out: Annotated[Path, typer.Argument(help="Finished run folder.")],
    format: Annotated[ExportFormat, typer.Option("--format", help="nerfstudio: transforms.json (depth in mm); colmap: text model; ply: splats (SH degree 3) and points; 3dgs: reference 3DGS model folder; mesh: TSDF mesh coloured by the sharp renders.")] = ExportFormat.nerfstudio,
    dest: Annotated[Optional[Path], typer.Option(help="Target folder (default OUT/export/FORMAT).")] = None,
    voxel_size: Annotated[Optional[float], typer.Option("--voxel-size", min=0.0005, help="mesh: TSDF voxel in metres (default from the scene's depth).")] = None,
) -> None:
    """Write the result for other tools: nerfstudio transforms.json, COLMAP text model, PLYs, a 3DGS model folder, or a TSDF mesh."""
    from .export import export_3dgs, export_colmap, export_nerfstudio, export_ply
    from .io.lock import output_lock
    from .pipeline import STAGES, open_run_sequence

    sequence = open_run_sequence(out)
    dest = dest or out / "export" / format.value
    _check_output_folder(sequence.root, dest, "--dest")
    if dest.resolve() == out.resolve() or any(dest.resolve() == (out / stage).resolve() for stage in STAGES):
        raise InputError(dest, "would overwrite the run's own results", "give a --dest outside the stage folders")
    with output_lock(out):
        if format.value == "ply":
            written = export_ply(out, dest)
        elif format.value == "mesh":
            from .mesh import export_mesh

            with progress_bar("TSDF fusion", len(sequence)) as update:
                written = export_mesh(out, sequence, dest, voxel_size, progress=lambda done, total: update(done, total))
        else:
            exporter = {"nerfstudio": export_nerfstudio, "colmap": export_colmap, "3dgs": export_3dgs}[format.value]
            written = exporter(out, sequence, dest)
    console.print(f"exported {format.value} to {written}")


@app.command()
@handles_errors
def view(
    out: Annotated[Path, typer.Argument(help="Run folder (any finished stage).")],
    host: Annotated[str, typer.Option(help="Address to serve on (0.0.0.0: every interface).")] = "127.0.0.1",
    port: Annotated[int, typer.Option(min=0, max=65535, help="Port to serve on (0: any free port).")] = 8080,
) -> None:
    """Look around a run in the browser: splats, cameras with their exposures, trajectory, a stage switch; a
    camera click shows its blurred input beside the sharp render. Needs pip install 'taichi-gs\\[viewer]'."""
    import time

    from .viewer.app import serve

    viewer = serve(out, host, port, state.arch)
    try:  # from here on a Ctrl-C stops the server's threads, which would otherwise keep the process alive
        console.print(f"viewer of {out} at {viewer.url} (Ctrl-C to stop)", highlight=False, soft_wrap=True)
        typer.echo(viewer.url)
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()


@app.command()
@handles_errors
def deblur(
    out: Annotated[Path, typer.Argument(help="Run folder holding refine/ from stage 2; results go to OUT/deblur/.")],
    preset: PresetOption = Preset.fast,
    config_file: ConfigOption = None,
    k: Annotated[Optional[int], typer.Option("--k", min=1, help="Virtual sharp views per exposure (default: the preset's).")] = None,
    holdout: Annotated[Optional[str], typer.Option(metavar="N|none|sharpest", help="Hold out every N-th frame as a test view, 'none', or 'sharpest' (the sharpest of every N frames; for real data).")] = None,
    readout_ms: ReadoutOption = None,
    profile: ProfileOption = False,
) -> None:
    """Stage 3: train sharp Gaussians and each frame's exposure start/end poses through the k-view blur model."""
    from . import pipeline
    from .io.lock import output_lock
    from .pipeline import open_run_sequence, resolve_sections
    from .validation import validate_sections

    config = with_readout(resolve_sections(preset.value, config_file, only=("deblur",))["deblur"], readout_ms)
    changes: dict[str, int | str | float | bool] = {} if k is None else {"k": k}
    if holdout is not None and holdout.strip().lower() == "sharpest":
        changes["holdout"] = "sharpest"
    elif holdout is not None:
        changes["holdout_every"] = parse_holdout(holdout)
    config = dataclasses.replace(config, **changes)
    validate_sections({"deblur": config})
    sequence = open_run_sequence(out)
    _init_backend()
    with output_lock(out), _profiled(profile, out):
        summary = pipeline.run_stage("deblur", sequence, out, config, progress_bar)  # --profile wraps it
    console.print(f"stage 3 done: {summary}; results in {out / 'deblur'}", highlight=False)


@contextmanager
def _profiled(profile: bool, out: Path) -> Iterator[int | None]:
    """With ``profile``, time the enclosed stages' work and write OUT/profile.json and OUT/profile.md. Yields
    the stages' thread count: one when profiled (stage 1's sections then do not overlap), else None (their
    configs')."""
    if not profile:
        yield None
        return
    from . import profiling
    from .kernels.splat import sync

    profiler = profiling.Profiler(sync=sync)
    profiling.install(profiler)
    try:
        yield 1
    finally:
        profiling.uninstall()
    paths = profiling.write(profiler, out)
    console.print(f"profile: {paths[1]}", highlight=False)


def _init_backend() -> None:
    from .kernels import runtime

    backend = runtime.init(state.arch)
    console.print(f"Taichi backend: {backend.arch}", highlight=False)


def _check_output_folder(folder: Path, out: Path, option: str = "--out") -> None:
    """Refuse to write inside the input folder, or into a path that is a file."""
    folder, target = Path(folder).resolve(), out.resolve()
    if target == folder or folder in target.parents:
        raise InputError(out, "output folder lies inside the input folder",
                         f"choose a {option} outside the input (inputs are never written to)")
    if out.exists() and not out.is_dir():
        raise InputError(out, "is a file, not a folder", f"give a folder path for {option}")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
