"""CLI plumbing shared by every command: the order commands are listed in, the group's options
(``--arch``, ``--quiet``, ``--verbose``) accepted after the subcommand too, the run log, option parsers."""

from __future__ import annotations

import functools
import shlex
import sys
from pathlib import Path
from typing import Any

import typer
from typer.core import TyperGroup

from .terminal import Verbosity, console

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
