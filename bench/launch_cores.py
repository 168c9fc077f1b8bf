"""How many cores a Taichi CPU launch can keep busy, by the launch's length, and what that allows a stage-3 run.

    python bench/launch_cores.py [--seconds 2] [--run RUN]

Part one times one kernel of uniform work (a parallel loop whose items all cost the same) at lengths from about
0.1 to 160 ms, and the same work as a serial loop, in this process with the thread count that ``taichi_gs``
starts Taichi with (under the kernel profiler when ``--run`` is given, as the run will be). It prints ms of wall
and CPU per launch and cores (CPU over wall): what Taichi's thread pool leaves of the machine at each length when
no load imbalance exists. Then it measures whether a launch lets other Python code run meanwhile (whether Taichi
releases Python's global interpreter lock while its CPU kernels run): a second Python thread counts while the
main one launches, against the same time with no launch.

``--run RUN`` (a run folder with ``refine/`` finished) then runs ``taichi-gs deblur RUN --quiet`` in this
process under Taichi's kernel profiler, which times every offloaded task (each top-level loop of a launch). It
prints the tasks' count and length distribution, and the *uniform-work ceiling*: each parallel task's wall
time weighted by the cores that uniform work of its length reached in part one, serial tasks at one core.
Kernels at that ceiling would be balanced perfectly; the run's own cores (measured with the profiler on, whose
timers cost a little) show how far its kernels are from it. RUN's ``deblur/`` is rewritten.
"""

import argparse
import bisect
import functools
import math
import resource
import threading
import time
from collections.abc import Callable
from pathlib import Path

from ab import run_line
from kernel_tasks import init_with_profiler, task_name

LOOPS = ((3_000, 1), (30_000, 1), (100_000, 1), (100_000, 4), (100_000, 16), (100_000, 64), (100_000, 256))
"""(items, sin() calls per item) of each timed loop: about 0.03 to 310 ms per launch on one core here."""
BINS_MS = (0.3, 1.0, 3.0, 10.0)


def cpu_seconds() -> float:
    """User + system CPU seconds of this process so far."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


@functools.cache
def uniform_loops() -> tuple[Callable, Callable]:
    """(parallel, serial) kernels of uniform work: item i of ``values`` goes through ``reps`` x ``sin()``."""
    import taichi as ti

    @ti.kernel
    def parallel(values: ti.types.ndarray(), items: ti.i32, reps: ti.i32):
        for i in range(items):
            x = values[i]
            for _ in range(reps):
                x = ti.sin(x) + 0.1
            values[i] = x

    @ti.kernel
    def serial(values: ti.types.ndarray(), items: ti.i32, reps: ti.i32):
        ti.loop_config(serialize=True)
        for i in range(items):
            x = values[i]
            for _ in range(reps):
                x = ti.sin(x) + 0.1
            values[i] = x

    return parallel, serial


def uniform_values():
    """The loops' values: one float per item of the largest loop, all 0.5."""
    import taichi as ti

    values = ti.ndarray(ti.f32, max(items for items, _ in LOOPS))
    values.fill(0.5)
    return values


def launch_curve(seconds: float) -> list[dict]:
    """Per LOOPS entry: ms of wall and CPU per launch and cores, for the parallel and the serial loop."""
    import taichi as ti

    values = uniform_values()
    parallel, serial = uniform_loops()
    rows = []
    for items, reps in LOOPS:
        row = {"items": items, "reps": reps}
        for name, kernel in (("parallel", parallel), ("serial", serial)):
            kernel(values, items, reps)  # compile
            ti.sync()
            launches, start, cpu = 0, time.perf_counter(), cpu_seconds()
            while time.perf_counter() - start < seconds or launches < 3:
                kernel(values, items, reps)
                launches += 1
            ti.sync()
            wall, used = time.perf_counter() - start, cpu_seconds() - cpu
            row[name] = {"wall_ms": 1e3 * wall / launches, "cpu_ms": 1e3 * used / launches, "cores": used / wall}
        rows.append(row)
    return rows


def python_pace_during_launches(seconds: float, reps: int = 1024) -> float:
    """How fast a second Python thread runs while this one is inside parallel launches of about ``reps`` x 100,000
    ``sin()``, against its pace with no launch: near 0 when a launch holds the GIL, near 1 when it releases it."""
    import taichi as ti

    values, parallel = uniform_values(), uniform_loops()[0]
    items = values.shape[0]
    parallel(values, items, 1)  # compile
    ti.sync()
    count, stop = [0], threading.Event()

    def counter() -> None:
        while not stop.is_set():
            count[0] += 1

    def pace(launching: bool) -> float:
        start, before = time.perf_counter(), count[0]
        while time.perf_counter() - start < seconds:
            if launching:
                parallel(values, items, reps)
                ti.sync()
            else:
                time.sleep(0.01)
        return (count[0] - before) / (time.perf_counter() - start)

    thread = threading.Thread(target=counter, daemon=True)
    thread.start()
    try:
        idle = pace(False)
        busy = pace(True)
    finally:
        stop.set()
        thread.join()
    return busy / idle


def uniform_cores(curve: list[dict], ms: float) -> float:
    """Cores of uniform parallel work at ``ms`` per launch: the curve interpolated in log(ms), held at its ends."""
    points = sorted((row["parallel"]["wall_ms"], row["parallel"]["cores"]) for row in curve)
    lengths = [p[0] for p in points]
    i = bisect.bisect_left(lengths, ms)
    if i == 0:
        return points[0][1]
    if i == len(points):
        return points[-1][1]
    (m0, c0), (m1, c1) = points[i - 1], points[i]
    f = (math.log(ms) - math.log(m0)) / (math.log(m1) - math.log(m0))
    return c0 + f * (c1 - c0)


def task_ceiling(tasks: list[tuple[str, float]], curve: list[dict]) -> float:
    """Cores of ``tasks`` ([(profiler name, ms)]) if each parallel one ran as uniform work of its length does in
    ``curve`` and each serial one (a name ending in "serial") on one core: their wall-time-weighted mean."""
    total = sum(ms for _, ms in tasks)
    used = sum(ms if name.endswith("serial") else ms * uniform_cores(curve, ms) for name, ms in tasks)
    return used / total


def profile_stage3(run: Path) -> tuple[list[tuple[str, float]], float, float]:
    """([(task name, ms)] of every offloaded task, wall s, CPU s) of ``taichi-gs deblur RUN`` in this process."""
    import taichi as ti
    from taichi.lang import impl

    from taichi_gs.cli import app

    ti.profiler.clear_kernel_profiler_info()
    start, cpu = time.perf_counter(), cpu_seconds()
    code = app(["deblur", str(run), "--quiet"], standalone_mode=False)
    if code:  # the CLI has printed why
        raise SystemExit(code)
    ti.sync()
    wall, used = time.perf_counter() - start, cpu_seconds() - cpu
    prog = impl.get_runtime().prog
    prog.sync_kernel_profiler()
    prog.update_kernel_profiler()
    return [(r.name, r.kernel_time) for r in prog.get_kernel_profiler_records()], wall, used


def tasks_by_kind(tasks: list[tuple[str, float]]) -> dict[str, list]:
    """{kind (``kernel_tasks.task_name``): [calls, ms]} of profiled ``tasks`` ([(profiler name, ms)])."""
    kinds: dict[str, list] = {}
    for name, ms in tasks:
        kind = kinds.setdefault(task_name(name), [0, 0.0])
        kind[0] += 1
        kind[1] += ms
    return kinds


def report_tasks(tasks: list[tuple[str, float]], curve: list[dict], wall: float, used: float) -> None:
    """The tasks' length distribution and the uniform-work ceiling against the run's own cores."""
    parallel = [ms for name, ms in tasks if not name.endswith("serial")]
    serial_ms = sum(ms for name, ms in tasks if name.endswith("serial"))
    task_ms = sum(parallel) + serial_ms
    print(f"\nstage 3 with the kernel profiler: {wall:.1f} s wall, {used:.1f} CPU-s, {used / wall:.3f} cores; "
          f"{len(tasks)} tasks ({len(tasks) - len(parallel)} serial), {task_ms / 1e3:.1f} s inside them, "
          f"mean parallel task {sum(parallel) / max(len(parallel), 1):.2f} ms\n")
    print("| parallel task length | tasks | share of the tasks' time | uniform work's cores there |")
    print("|---|---|---|---|")
    edges = (0.0, *BINS_MS, math.inf)
    for lo, hi in zip(edges, edges[1:]):
        inside = [ms for ms in parallel if lo <= ms < hi]
        if inside:
            mid = sum(inside) / len(inside)
            label = f"{lo:g}-{hi:g} ms" if hi < math.inf else f">= {lo:g} ms"
            print(f"| {label} | {len(inside)} | {sum(inside) / task_ms:.1%} | {uniform_cores(curve, mid):.2f} |")
    outside = wall - task_ms / 1e3
    print(f"\nuniform-work ceiling of the tasks: {task_ceiling(tasks, curve):.3f} cores; the tasks' own cores if the "
          f"{outside:.1f} s outside them (Python, launches, the profiler's timers) used one core: "
          f"{(used - outside) / (task_ms / 1e3):.3f}; serial tasks {serial_ms / 1e3:.2f} s\n")
    ranked = sorted(tasks_by_kind(tasks).items(), key=lambda item: -item[1][1])
    print("| task (the 10 longest in all, then the 6 longest serial ones) | calls | s | mean ms |")
    print("|---|---|---|---|")
    for name, (calls, ms) in ranked[:10] + [item for item in ranked if item[0].endswith("serial")][:6]:
        print(f"| {name} | {calls} | {ms / 1e3:.2f} | {ms / calls:.3f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=2.0, help="timing window per loop and length")
    parser.add_argument("--run", type=Path, help="a run folder whose stage 3 to profile (its deblur/ is rewritten)")
    args = parser.parse_args()
    backend = init_with_profiler("cpu", profiler=args.run is not None)
    curve = launch_curve(args.seconds)
    print(run_line("cpu") + f", {backend.cpu_threads} Taichi threads, kernel profiler {'on' if args.run else 'off'}\n")
    print("| items x sin() | parallel: ms wall / CPU per launch | cores | serial: ms wall per launch |")
    print("|---|---|---|---|")
    for row in curve:
        p, s = row["parallel"], row["serial"]
        print(f"| {row['items']} x {row['reps']} | {p['wall_ms']:.3f} / {p['cpu_ms']:.3f} | {p['cores']:.3f} "
              f"| {s['wall_ms']:.3f} |")
    share = python_pace_during_launches(args.seconds)
    print(f"\nA second Python thread ran at {share:.1%} of its own pace while launches ran: Taichi "
          f"{'holds' if share < 0.5 else 'releases'} Python's GIL while its CPU kernels run.")
    if args.run:
        tasks, wall, used = profile_stage3(args.run)
        report_tasks(tasks, curve, wall, used)


if __name__ == "__main__":
    main()
