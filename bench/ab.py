"""Alternating A/B rounds of a bench script: this tree against another code root (e.g. a ``git worktree``
of an older commit), each round in fresh processes, so a comparison survives a machine whose speed drifts.

A script using it runs itself with ``--json`` in each root (cwd and ``PYTHONPATH`` set to that root) and
prints one JSON object as its last line of output."""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options every script using this module takes: --rounds, --baseline and the hidden --json."""
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds with --baseline")
    parser.add_argument("--baseline", type=Path, help="another code root to run in the same run")
    parser.add_argument("--json", action="store_true", help=argparse.SUPPRESS)  # one process's raw result


def run_in(root: Path, script: str, args: list[str]) -> dict:
    """``script --json *args`` in a fresh process importing ``taichi_gs`` from ``root``; its last output line."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    done = subprocess.run([sys.executable, str(Path(script).resolve()), "--json", *args], cwd=root, env=env,
                          capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def alternate(script: str, args: list[str], baseline: Path | None, rounds: int) -> dict[str, list[dict]]:
    """{"this tree": [result per round], "baseline": [...]} (no baseline: one round of this tree)."""
    roots = {"this tree": HERE} | ({"baseline": baseline.resolve()} if baseline else {})
    results: dict[str, list[dict]] = {name: [] for name in roots}
    for _ in range(rounds if baseline else 1):
        for name, root in roots.items():
            results[name].append(run_in(root, script, args))
    return results


def run_line(arch: str) -> str:
    """The first words of a results table's caption: date, processor, CPU count, backend."""
    processor = platform.processor() or platform.machine()
    return f"# {datetime.date.today()}, {processor}, {os.cpu_count()} CPUs, --arch {arch}"
