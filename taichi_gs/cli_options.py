"""CLI plumbing shared by every command: the order commands are listed in, the group's options
(``--arch``, ``--quiet``, ``--verbose``) accepted after the subcommand too, the run log, the options of every
command that reads a sequence folder (written once: :class:`InputOptions`), choices from tuples, option parsers."""

from __future__ import annotations

import dataclasses
import functools
import inspect
import shlex
import sys
import typing
from collections.abc import Callable, Iterable
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional

import typer
from typer.core import TyperGroup

from .terminal import Verbosity, console

if TYPE_CHECKING:
    from .io.sequence import Sequence

# Listed first, in this order (the rest follow in definition order): the everyday path first.
COMMAND_ORDER = ("reconstruct", "eval", "view", "export", "render", "pose", "refine", "deblur", "import", "synth", "info")


class _State:
    """The group's options, set by its callback."""

    arch: str = "auto"
    verbosity: int = Verbosity.NORMAL


state = _State()


GLOBAL_FLAGS = ("--quiet", "-q", "--verbose", "-v")
GLOBAL_WITH_VALUE = ("--arch",)


def hoist_global_options(args: list[str], commands: set[str]) -> list[str]:
    """Move the group's own options written after the subcommand (``pose --arch cpu ...``) in
    front of it, so that they work in either place; nothing after ``--`` is touched."""
    i = 0
    while i < len(args) and args[i] not in commands:
        i += 2 if args[i] in GLOBAL_WITH_VALUE else 1
    if i >= len(args):
        return list(args)
    head, command, tail = list(args[:i]), args[i], list(args[i + 1:])
    moved, rest, j = [], [], 0
    while j < len(tail):
        token = tail[j]
        if token == "--":
            rest += tail[j:]
            break
        if token in GLOBAL_FLAGS or token.startswith(tuple(f"{o}=" for o in GLOBAL_WITH_VALUE)):
            moved.append(token)
        elif token in GLOBAL_WITH_VALUE and j + 1 < len(tail):
            moved += tail[j:j + 2]
            j += 1
        else:
            rest.append(token)
        j += 1
    return head + moved + [command] + rest


class CommandGroup(TyperGroup):
    """Lists commands in :data:`COMMAND_ORDER`; accepts the group's options (``--arch``,
    ``--quiet``, ``--verbose``) after the subcommand too; and points the console's log at the
    command's run folder (its ``out`` or ``run_dir`` argument)."""

    def list_commands(self, ctx: Any) -> list[str]:
        names = super().list_commands(ctx)
        rank = {name: i for i, name in enumerate(COMMAND_ORDER)}
        return sorted(names, key=lambda n: (rank.get(n, len(rank)), names.index(n)))

    def parse_args(self, ctx: Any, args: list[str]) -> list[str]:
        return super().parse_args(ctx, hoist_global_options(args, set(self.commands)))

    def get_command(self, ctx: Any, cmd_name: str) -> Any:
        command = super().get_command(ctx, cmd_name)
        if command is not None and command.callback is not None and not getattr(command, "_taichi_gs_logged", False):
            command.callback = _logged(command.callback)
            command._taichi_gs_logged = True
        return command


def _logged(callback: Any) -> Any:
    """Run a command with the console's log pointed at its run folder."""

    @functools.wraps(callback)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        folder = kwargs.get("out") or kwargs.get("run_dir")
        console.run_log.start(Path(folder) if folder is not None else None,
                              shlex.join(["taichi-gs", *sys.argv[1:]]))
        try:
            return callback(*args, **kwargs)
        finally:
            console.run_log.start(None, "")

    return wrapper


def choices(name: str, values: Iterable[str]) -> Any:
    """A ``str`` Enum named ``name`` with one member per value, named as it (typer's choices, in that order)."""
    return Enum(name, [(value, value) for value in values], type=str)


FxOption = Annotated[Optional[float], typer.Option("--fx", help="Focal length x (px); wins over intrinsics.json.")]
FyOption = Annotated[Optional[float], typer.Option("--fy", help="Focal length y (px).")]
CxOption = Annotated[Optional[float], typer.Option("--cx", help="Principal point x (px).")]
CyOption = Annotated[Optional[float], typer.Option("--cy", help="Principal point y (px).")]
DepthScaleOption = Annotated[Optional[float], typer.Option("--depth-scale", help="Depth PNG units per metre (TUM: 5000).")]
TrustDepthOption = Annotated[bool, typer.Option(
    "--trust-depth-scale", help="Accept a median depth outside 0.25-6 m (the indoor check of the depth scale).")]
TimeToleranceOption = Annotated[Optional[float], typer.Option(
    "--time-tolerance", min=0.0, help="TUM layout: max seconds between associated colour and depth (default 0.02).")]
FormatOption = Annotated[Optional[str], typer.Option("--format", help="Input layout (default: detected): taichi-gs | tum | 7scenes | scannet | replica | stray.")]
CameraOption = Annotated[Optional[str], typer.Option("--camera", help="TUM: fr1 | fr2 | fr3 (intrinsics and distortion; default from the folder name). 7-Scenes: registered (default: depth moved into the colour camera) | shipped (colour and depth as one camera, as distributed).")]
EveryOption = Annotated[int, typer.Option("--every", min=1, help="Keep every N-th frame.")]
ScaleOption = Annotated[float, typer.Option("--scale", help="Read frames at S times their width and height (0.5: half).")]
FirstOption = Annotated[int, typer.Option("--first", min=0, help="Start at this frame of the sequence as read (counted from 0; TUM: after colour-depth association).")]
CountOption = Annotated[int, typer.Option("--count", min=0, help="Keep this many frames (after --every; 0: to the end).")]


@dataclasses.dataclass(frozen=True)
class InputOptions:
    """How a command reads its input sequence folder: the options of every command that reads one, in the order
    its --help lists them. A command takes them as one parameter ``reading: InputOptions`` (see
    :func:`with_input_options`)."""

    fx: FxOption = None
    fy: FyOption = None
    cx: CxOption = None
    cy: CyOption = None
    depth_scale: DepthScaleOption = None
    trust_depth_scale: TrustDepthOption = False
    time_tolerance: TimeToleranceOption = None
    format: FormatOption = None
    camera: CameraOption = None
    every: EveryOption = 1
    scale: ScaleOption = 1.0
    first: FirstOption = 0
    count: CountOption = 0

    def load(self, folder: Path) -> Sequence:
        """The sequence in ``folder``, read as these options say (``io.load.load_sequence``)."""
        from .io.load import load_sequence
        from .io.sequence import IntrinsicsOverride

        override = IntrinsicsOverride(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, depth_scale=self.depth_scale)
        return load_sequence(folder, override, self.time_tolerance, self.trust_depth_scale, format=self.format,
                             camera=self.camera, every=self.every, scale=self.scale, first=self.first, count=self.count)


AS_FOUND = InputOptions()  # every input option at its default


def with_input_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """``command`` with its parameter ``reading: InputOptions`` spread into :class:`InputOptions`' fields, in its
    place, as typer reads them (each field's annotation and default); their values come back as one
    ``InputOptions``."""
    annotations = typing.get_type_hints(InputOptions, include_extras=True)
    fields = [inspect.Parameter(f.name, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=f.default,
                                annotation=annotations[f.name]) for f in dataclasses.fields(InputOptions)]
    signature = inspect.signature(command, eval_str=True)
    parameters = []
    for parameter in signature.parameters.values():
        parameters += fields if parameter.name == "reading" else [parameter]

    @functools.wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        reading = InputOptions(**{f.name: kwargs.pop(f.name) for f in fields})
        return command(*args, reading=reading, **kwargs)

    wrapper.__signature__ = signature.replace(parameters=parameters)  # type: ignore[attr-defined]
    wrapper.__annotations__ = {p.name: p.annotation for p in parameters}
    return wrapper


def parse_holdout(value: str | int) -> int:
    """``--holdout``: 'none' (0: train on every frame) or an integer N >= 2 (every N-th frame is a test view)."""
    if isinstance(value, int):
        return value
    text = str(value).strip().lower()
    if text == "none":
        return 0
    if text.isdigit() and int(text) >= 2:
        return int(text)
    raise typer.BadParameter(f"{value!r} is not 'none' or an integer of at least 2 (e.g. --holdout 3)")
