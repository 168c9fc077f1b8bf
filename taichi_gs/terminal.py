"""What the CLI tells the user: a stderr console that also writes the run's log file, progress bars
that fit 80 columns (plain lines when stderr is not a terminal), and warnings on their own lines.

stdout is kept for results (``info``, ``eval``, ``--json``); everything else goes to stderr.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.errors import MarkupError
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Column
from rich.text import Text

LOG_NAME = "log.txt"
RUN_MARKER = "run.json"  # the log is written only into folders that are taichi-gs run folders
PLAIN_EVERY_FRACTION = 0.1  # without a terminal: a progress line every 10% ...
PLAIN_EVERY_SECONDS = 30.0  # ... or every 30 s, whichever comes first


class Verbosity:
    """``--quiet``: only warnings and errors; ``--verbose``: also debug messages and every progress step."""

    QUIET, NORMAL, VERBOSE = 0, 1, 2


class RunLog:
    """Appends timestamped plain lines to RUN/log.txt once RUN is a run folder (it holds run.json);
    lines said before that are kept and written then, so a run's log starts at its command line."""

    def __init__(self) -> None:
        self.folder: Path | None = None
        self.pending: list[str] = []

    def start(self, folder: Path | None, command: str) -> None:
        self.folder, self.pending = folder, []
        if folder is not None:
            self.write(f"$ {command}")

    def write(self, text: str) -> None:
        if self.folder is None:
            return
        stamp = datetime.now().isoformat(timespec="seconds")
        self.pending += [f"{stamp} {line}" for line in text.splitlines() or [""]]
        if (self.folder / RUN_MARKER).is_file():
            try:
                with open(self.folder / LOG_NAME, "a", encoding="utf-8") as f:
                    f.write("\n".join(self.pending) + "\n")
                self.pending = []
            except OSError:  # a log must never stop a run
                self.folder = None


class RunConsole(Console):
    """A stderr console that mirrors what it prints into the run log; with ``--quiet`` it prints
    only lines starting with 'error' or 'warning' (the log still gets everything)."""

    def __init__(self) -> None:
        super().__init__(stderr=True)
        self.verbosity = Verbosity.NORMAL
        self.run_log = RunLog()

    def print(self, *objects: Any, **kwargs: Any) -> None:  # noqa: A003 - rich's name
        texts = [o for o in objects if isinstance(o, str)]
        if texts:
            plain = _plain(" ".join(texts), kwargs.get("markup", True))
            self.run_log.write(plain)
            if self.verbosity == Verbosity.QUIET and not plain.lower().startswith(("error", "warning")):
                return
        super().print(*objects, **kwargs)


def _plain(text: str, markup: bool) -> str:
    if not markup:
        return text
    try:
        return Text.from_markup(text).plain
    except MarkupError:
        return text


console = RunConsole()


class _ConsoleHandler(logging.Handler):
    """Package log records as their own console lines: 'warning: ...' in yellow."""

    def emit(self, record: logging.LogRecord) -> None:
        level = record.levelname.lower()
        colour = {"warning": "yellow", "error": "bold red"}.get(level, "dim")
        console.print(f"[{colour}]{level}:[/] {escape(record.getMessage())}", highlight=False, soft_wrap=True)


def configure_logging(verbosity: int) -> None:
    """Route the ``taichi_gs`` logger to the console (debug messages only with ``--verbose``)."""
    console.verbosity = verbosity
    logger = logging.getLogger("taichi_gs")
    logger.handlers = [h for h in logger.handlers if not isinstance(h, _ConsoleHandler)] + [_ConsoleHandler()]
    logger.setLevel(logging.DEBUG if verbosity >= Verbosity.VERBOSE else logging.INFO)
    logger.propagate = False


def _format_info(info: dict[str, Any]) -> str:
    return "  ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in info.items())


def _clock(seconds: float | None) -> str:
    if seconds is None or seconds != seconds or seconds < 0:
        return "-:--:--"
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class PlainProgress:
    """Progress as plain lines for logs and pipes: one every ``PLAIN_EVERY_FRACTION`` of the total
    or ``PLAIN_EVERY_SECONDS``, whichever comes first, and one at the end."""

    def __init__(self, description: str, total: int, emit: Callable[[str], None], every_step: bool = False,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.description, self.total, self.emit, self.every_step, self.clock = description, max(total, 1), emit, every_step, clock
        self.start = self.last_time = clock()
        self.last_done = 0

    def update(self, done: int, total: int | None = None, **info: Any) -> None:
        if total:
            self.total = max(int(total), 1)
        now = self.clock()
        step = max(1, int(self.total * PLAIN_EVERY_FRACTION))
        due = (self.every_step or done >= self.total or done // step > self.last_done // step
               or now - self.last_time >= PLAIN_EVERY_SECONDS)
        if not due or done == self.last_done and done < self.total:
            return
        elapsed = now - self.start
        eta = elapsed / done * (self.total - done) if done > 0 else None
        line = (f"{self.description}: {done}/{self.total} ({100 * done / self.total:.0f}%) "
                f"elapsed {_clock(elapsed)} eta {_clock(eta)}")
        text = _format_info(info)
        self.emit(f"{line}  {text}" if text else line)
        self.last_time, self.last_done = now, done


def count_width(total: int) -> int:
    """Characters that 'done/total' needs at most."""
    return 2 * len(str(max(total, 1))) + 1


def progress_columns(description: str, total: int) -> list[Any]:
    """Columns whose description, count, elapsed time and ETA keep their full width at 80 columns
    (rich otherwise shrinks them all to '600… 0:0…'); the bar has a fixed 20 characters and the
    free-text info takes what is left, cut with an ellipsis."""
    return [
        TextColumn("[bold]{task.description}", table_column=Column(no_wrap=True, min_width=len(description))),
        BarColumn(bar_width=20, table_column=Column(no_wrap=True, min_width=20)),
        MofNCompleteColumn(table_column=Column(min_width=count_width(max(total, 9999)), no_wrap=True, justify="right")),
        TimeElapsedColumn(table_column=Column(no_wrap=True, min_width=7)),
        TimeRemainingColumn(table_column=Column(no_wrap=True, min_width=7)),
        TextColumn("{task.fields[info]}", table_column=Column(ratio=1, no_wrap=True, overflow="ellipsis")),
    ]


@contextmanager
def progress_bar(description: str, total: int) -> Iterator[Callable[..., None]]:
    """Progress of one task; yields ``update(done, total=None, **info)``.

    On a terminal: a rich bar (nothing with ``--quiet``). Otherwise: plain lines (see
    :class:`PlainProgress`). The run log gets the plain lines in both cases."""
    verbose = console.verbosity >= Verbosity.VERBOSE
    to_log = PlainProgress(description, total, console.run_log.write)
    plain = None
    if not console.is_terminal and console.verbosity > Verbosity.QUIET:
        plain = PlainProgress(description, total, lambda line: Console.print(console, line, markup=False,
                                                                              highlight=False), every_step=verbose)
    if console.is_terminal and console.verbosity > Verbosity.QUIET:
        with Progress(*progress_columns(description, total), console=console, transient=False) as progress:
            task = progress.add_task(description, total=total, info="")

            def update(done: int, total: int | None = None, **info: Any) -> None:
                progress.update(task, completed=done, total=total, info=_format_info(info))
                to_log.update(done, total, **info)

            yield update
        return

    def update_plain(done: int, total: int | None = None, **info: Any) -> None:
        to_log.update(done, total, **info)
        if plain is not None:
            plain.update(done, total, **info)

    yield update_plain

