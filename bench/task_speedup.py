"""How much faster each of a stage-3 run's kernels gets from one Taichi thread to the default count, and how much
of the stage's wall time runs outside the kernels.

    python bench/task_speedup.py --run RUN

Runs ``taichi-gs deblur RUN --quiet`` twice, each in a fresh process under Taichi's kernel profiler: once with
one CPU thread (``TI_CPU_MAX_NUM_THREADS=1``) and once with the thread count ``taichi_gs`` picks. Per kind of
task (a kernel's top-level loop, named as in ``kernel_tasks.py``) it prints the seconds in both runs and their
ratio, the *speed-up*. A loop whose costly items fall into a few of Taichi's contiguous pieces, or that waits on
its own threads, stays well under the core count; a balanced one comes close to it. The last lines split each
run's wall time into the time inside the tasks and the time outside them (Python, launches, buffer growth, the
profiler's timers): what no kernel change can speed up. RUN's ``deblur/`` is rewritten (twice).

Cores (CPU over wall, as ``launch_cores.py`` and ``time`` report them) count all CPU time, also a thread's time
without useful work; a speed-up counts only what finishes sooner.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from ab import run_line
from kernel_tasks import init_with_profiler
from launch_cores import profile_stage3, tasks_by_kind

from taichi_gs.kernels.runtime import CPU_THREADS_ENV

SHOWN = 12  # kinds of task listed, the longest on one thread first


def profile_in_child(run: Path, threads: int | None) -> dict:
    """This script's ``--child`` result for ``run`` in a fresh process: ``threads`` Taichi CPU threads, or
    ``taichi_gs``'s own count when None."""
    env = {key: value for key, value in os.environ.items() if key != CPU_THREADS_ENV}
    if threads is not None:
        env[CPU_THREADS_ENV] = str(threads)
    done = subprocess.run([sys.executable, __file__, "--run", str(run), "--child"], env=env, capture_output=True,
                          text=True)
    if done.returncode != 0:
        raise SystemExit(f"stage 3 of {run} failed with {threads or 'the default'} thread(s):\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def child(run: Path) -> dict:
    """{threads, wall_s, cpu_s, tasks: {kind: [calls, ms]}} of one profiled stage-3 run in this process."""
    backend = init_with_profiler("cpu")
    tasks, wall, used = profile_stage3(run)
    return {"threads": backend.cpu_threads, "wall_s": wall, "cpu_s": used, "tasks": tasks_by_kind(tasks)}


def speedups(one: dict, many: dict) -> list[tuple[str, int, float, float]]:
    """[(kind, calls, s on one thread, s on many)] for the kinds of task both runs have, longest on one thread
    first; a kind that only one run has (a different schedule) is left out."""
    rows = [(kind, many["tasks"][kind][0], ms / 1e3, many["tasks"][kind][1] / 1e3)
            for kind, (_, ms) in one["tasks"].items() if kind in many["tasks"]]
    return sorted(rows, key=lambda row: -row[2])


def inside_outside(result: dict) -> tuple[float, float]:
    """(seconds inside the profiled tasks, seconds of the run's wall time outside them)."""
    inside = sum(ms for _, ms in result["tasks"].values()) / 1e3
    return inside, result["wall_s"] - inside


def report(one: dict, many: dict) -> None:
    """The per-kind table and the inside / outside split of both runs."""
    rows = speedups(one, many)
    n = many["threads"]
    print(f"| task (the {SHOWN} longest on one thread) | calls | 1 thread s | {n} threads s | speed-up |")
    print("|---|---|---|---|---|")
    for kind, calls, s_one, s_many in rows[:SHOWN]:
        print(f"| {kind} | {calls} | {s_one:.2f} | {s_many:.2f} | {s_one / s_many:.2f} |")
    in_one, in_many = inside_outside(one)[0], inside_outside(many)[0]
    print(f"\nall tasks: {in_one:.1f} s on one thread, {in_many:.1f} s on {n}: speed-up {in_one / in_many:.2f}")
    for label, result in (("1 thread", one), (f"{n} threads", many)):
        inside, outside = inside_outside(result)
        print(f"{label}: {result['wall_s']:.1f} s wall, {result['cpu_s'] / result['wall_s']:.2f} cores; "
              f"{inside:.1f} s inside the tasks, {outside:.1f} s outside them ({outside / result['wall_s']:.0%})")
    print(f"stage speed-up {one['wall_s'] / many['wall_s']:.2f}; with no time outside the tasks it would be "
          f"{in_one / in_many:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="a run folder with refine/ finished")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)  # one profiled run, as JSON
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.run)))
        return
    one = profile_in_child(args.run, 1)
    many = profile_in_child(args.run, None)
    print(run_line("cpu") + f", stage 3 of {args.run}, Taichi's kernel profiler on\n")
    report(one, many)


if __name__ == "__main__":
    main()
