"""The launch and sync budget (issue 87): the counter counts launches, reads, writes and bytes right and
unhooks Taichi after its block (also after an exception), and a render's and the training steps' counts stay
under today's (a regression ceiling; the issue's target is about 10 launches and 0 host reads per virtual
view, forward + backward).

The ceilings are per backend: the CPU path by default, and with ``TAICHI_GS_ARCH=vulkan`` (after
``source scripts/vulkan.sh``; ``-m gpu``) the GPU path.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import taichi as ti

from taichi_gs.kernels import host_copy, launch_budget, runtime

BENCH = Path(__file__).resolve().parents[1] / "bench" / "launch_budget.py"
ARCH = os.environ.get(runtime.ARCH_ENV, "").lower()
COMBO = (400, (48, 40))  # Gaussians, (width, height); only bytes and the GPU path's pose sum (below) depend on them
# Counts of bench/launch_budget.py's cases (2-core x86_64, no GPU; docs/notebook/launch-budget.md): issue 87's
# item 1 measured them at commit 245dce3, its item 2 lowered them (per view no host read: the slot count stays on
# the device, the k pose gradients come back in one read per step; a step's loss values in one read), and its
# leftovers to one read per step (every value a step hands back in one StepValues buffer; the densification
# statistics summed on the device). A regression fails here; lower the ceilings with any further fusion. The target
# is about 10 launches and 0 host reads per render (forward + backward).
CPU_CEILINGS = {
    "render": {"launches": 4, "tasks": 25, "host_reads": 0, "syncs": 0},
    "stage 3 paper": {"launches": 70, "tasks": 399, "host_reads": 1, "syncs": 0},
    "stage 3 fast": {"launches": 17, "tasks": 55, "host_reads": 1, "syncs": 0},
    "stage 2": {"launches": 10, "tasks": 37, "host_reads": 1, "syncs": 0},
}
VULKAN_CEILINGS = {  # the GPU path (raster_gpu); its pose sum takes a launch more per 256x the Gaussians (3 at 100k)
    "render": {"launches": 10, "host_reads": 0, "syncs": 0},
    "stage 3 paper": {"launches": 163, "host_reads": 1, "syncs": 0},
    "stage 3 fast": {"launches": 28, "host_reads": 1, "syncs": 0},
    "stage 2": {"launches": 18, "host_reads": 1, "syncs": 0},
}


@pytest.fixture(scope="module")
def toy():
    """A (10, 3) float32 ndarray and a kernel that writes it."""
    runtime.init()

    @ti.kernel
    def write_rows(x: ti.types.ndarray(dtype=ti.f32, ndim=2)):
        for i in range(x.shape[0]):
            x[i, 0] = i

    array = ti.ndarray(ti.f32, (10, 3))
    write_rows(array)
    return array, write_rows


def test_counts_each_launch_by_kernel_name(toy):
    array, write_rows = toy
    with launch_budget.counting() as budget:
        for _ in range(5):
            write_rows(array)
    assert budget.launches == 5
    assert budget.by_name("launch") == {"write_rows": 5}
    assert budget.host_reads == budget.host_writes == budget.syncs == 0


def test_counts_a_read_once_with_its_bytes_and_site(toy):
    array, _ = toy
    with launch_budget.counting() as budget:
        values = host_copy.read(array)
    assert budget.host_reads == 1
    assert budget.bytes_to_host == values.nbytes == 10 * 3 * 4
    assert budget.by_site("read") == {"host_copy.read @ test_launch_budget.py:test_counts_a_read_once_with_its_bytes_and_site": 1}
    with launch_budget.counting() as budget:
        value = array[3, 0]
        array.to_numpy()
    assert value == 3.0
    assert budget.host_reads == 2
    assert budget.bytes_to_host == 4 + 10 * 3 * 4


def test_counts_writes_fills_and_syncs(toy):
    array, write_rows = toy
    with launch_budget.counting() as budget:
        host_copy.write(array, np.zeros((10, 3)))
        array[0, 1] = 2.0
        array.fill(0.0)
        ti.sync()
    assert budget.host_writes == 2
    assert budget.bytes_to_device == 10 * 3 * 4 + 4
    assert budget.launches >= 1 and budget.by_name("launch").keys() <= {"ndarray.fill", "fill_ndarray",
                                                                         "ext_arr_to_ndarray"}
    assert budget.syncs == 1 and budget.host_reads == 0
    write_rows(array)


def test_unhooks_after_the_block_and_after_an_exception(toy):
    array, write_rows = toy
    hooked = [(ti.lang.kernel_impl.Kernel, "launch_kernel"), (host_copy, "read"), (host_copy, "write")]
    before = [vars(owner)[name] for owner, name in hooked]
    with launch_budget.counting() as budget:
        assert [vars(owner)[name] for owner, name in hooked] != before
        write_rows(array)
    write_rows(array)
    host_copy.read(array)
    assert budget.launches == 1 and budget.host_reads == 0
    assert [vars(owner)[name] for owner, name in hooked] == before
    with pytest.raises(ValueError, match="inside the block"), launch_budget.counting():
        write_rows(array)
        raise ValueError("inside the block")
    assert [vars(owner)[name] for owner, name in hooked] == before
    with launch_budget.counting(), pytest.raises(RuntimeError, match="already active"), launch_budget.counting():
        pass
    assert [vars(owner)[name] for owner, name in hooked] == before


def test_counts_device_tasks_with_the_kernel_profiler_on(tmp_path):
    """Each top-level loop of a kernel is a task (after the kernel's serial prologue on the CPU)."""
    script = """
import json, sys
sys.path.insert(0, sys.argv[1])
from kernel_tasks import init_with_profiler
init_with_profiler("cpu")
import taichi as ti
from taichi_gs.kernels import launch_budget
x = ti.ndarray(ti.f32, (10,))
@ti.kernel
def two_loops(x: ti.types.ndarray()):
    for i in x:
        x[i] = i
    for i in x:
        x[i] += 1
two_loops(x)
with launch_budget.counting() as budget:
    two_loops(x)
    two_loops(x)
print(json.dumps(budget.summary()))
"""
    (tmp_path / "tasks.py").write_text(script)  # Taichi reads a kernel's source from its file
    done = subprocess.run([sys.executable, str(tmp_path / "tasks.py"), str(BENCH.parent)], capture_output=True,
                          text=True, check=True)
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["launches"] == 2 and summary["tasks"] == 6
    # named as the profiler names them (the offline cache may hand back an identical kernel's name)
    tasks = {name.split(":")[1]: count for name, count in summary["tasks_by_name"].items()}
    assert tasks == {"0 serial": 2, "1 range_for": 2, "2 range_for": 2}


def test_tasks_are_none_without_the_profiler(toy):
    array, write_rows = toy
    with launch_budget.counting() as budget:
        write_rows(array)
    assert budget.tasks is None and budget.summary()["tasks"] is None


def _counted(arch: str, cases: tuple[str, ...]) -> dict[str, dict]:
    """bench/launch_budget.py's counts of ``cases`` on ``arch`` (tasks too on the CPU), in a process of its own."""
    n, (width, height) = COMBO
    tasks = ["--tasks"] if arch == "cpu" else []
    done = subprocess.run([sys.executable, str(BENCH), "--arch", arch, "--combo", f"{n}:{width}x{height}", *tasks,
                           "--json", "--cases", *cases], check=False, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout)["cases"]


def _within(counted: dict[str, dict], ceilings: dict[str, dict[str, int]]) -> None:
    over = {case: {key: (counted[case][key], limit) for key, limit in limits.items() if counted[case][key] > limit}
            for case, limits in ceilings.items() if case in counted}
    assert not any(over.values()), f"over today's budget ((counted, ceiling) per case): {over}"


def test_cpu_render_and_default_steps_stay_within_todays_budget():
    cases = ("render", "stage 3 fast", "stage 2")
    counted = _counted("cpu", cases)
    assert set(counted) == set(cases) and all(c["tasks"] >= c["launches"] > 0 for c in counted.values())
    _within(counted, CPU_CEILINGS)


@pytest.mark.slow
def test_cpu_paper_step_stays_within_todays_budget():
    """The rendered exposure (k = 15, SH degree 3: its compile alone takes longer than the fast tests)."""
    _within(_counted("cpu", ("stage 3 paper",)), CPU_CEILINGS)


@pytest.mark.gpu
@pytest.mark.skipif(ARCH != "vulkan", reason="set TAICHI_GS_ARCH=vulkan (after `source scripts/vulkan.sh`) to run")
def test_vulkan_path_stays_within_todays_budget():
    _within(_counted("vulkan", tuple(VULKAN_CEILINGS)), VULKAN_CEILINGS)


def test_gpu_scans_take_the_levels_their_size_needs():
    """Each scan level is a few GPU dispatches (block scan, offset add): 1 level up to 255 elements, 2 up to 65,279
    (the depth sort's digit table up to 260,096 Gaussians), never more than 4 for an i32 count."""
    from taichi_gs.kernels import scan

    assert [scan.scan_levels_for(n) for n in (0, 255, 256, 65_279, 65_280, 2**31 - 1)] == [1, 1, 2, 2, 3, 4]
    assert scan.scan_levels_for(scan.digit_table_size(260_096)) == 2
    assert scan.scan_levels_for(scan.digit_table_size(260_097)) == 3


@pytest.mark.gpu
@pytest.mark.skipif(ARCH != "vulkan", reason="set TAICHI_GS_ARCH=vulkan (after `source scripts/vulkan.sh`) to run")
def test_vulkan_deferred_renders_rerun_after_an_overflow():
    """tests/test_deferred_render.py on the GPU path (its own process, on the backend this one runs)."""
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           str(Path(__file__).with_name("test_deferred_render.py"))],
                          check=False, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-3000:]
