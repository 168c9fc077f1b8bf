"""Backend choice without starting Taichi: the arch request, auto's order, software Vulkan devices,
absent backends as errors, the per-buffer limit."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import types

import pytest

from taichi_gs.errors import BackendError
from taichi_gs.kernels import devices, runtime
from taichi_gs.machine import available_cores
from taichi_gs.stages.pose import DEFAULT_MAX_THREADS


def vk(index: int, device_type: int, api_minor: int = 3, name: str = "dev") -> devices.VulkanDevice:
    return devices.VulkanDevice(index, name, device_type, api_minor, 2**27, 32)


LAVAPIPE = vk(0, 4, 4, "llvmpipe (LLVM 15.0.6, 256 bits)")
DISCRETE = vk(1, 2, 3, "Some GPU")


@pytest.fixture
def no_cuda_no_metal(monkeypatch):
    monkeypatch.setattr(runtime, "cuda_available", lambda: False)
    monkeypatch.setattr(runtime, "metal_available", lambda: False)
    monkeypatch.delenv("TI_VISIBLE_DEVICE", raising=False)


def test_requested_arch_reads_the_environment(monkeypatch) -> None:
    monkeypatch.delenv(runtime.ARCH_ENV, raising=False)
    assert runtime.requested_arch() == "auto"
    monkeypatch.setenv(runtime.ARCH_ENV, "Vulkan")
    assert runtime.requested_arch() == "vulkan"
    assert runtime.requested_arch("cpu") == "cpu"  # an explicit request wins
    monkeypatch.setenv(runtime.ARCH_ENV, "opengl")
    with pytest.raises(BackendError, match="TAICHI_GS_ARCH"):
        runtime.requested_arch()


def test_taichi_takes_the_best_scored_vulkan_device(monkeypatch) -> None:
    monkeypatch.delenv("TI_VISIBLE_DEVICE", raising=False)
    assert devices.taichi_vulkan_pick([LAVAPIPE, DISCRETE]) == DISCRETE
    assert devices.taichi_vulkan_pick([LAVAPIPE]) == LAVAPIPE
    assert devices.taichi_vulkan_pick([]) is None
    monkeypatch.setenv("TI_VISIBLE_DEVICE", "0")
    assert devices.taichi_vulkan_pick([LAVAPIPE, DISCRETE]) == LAVAPIPE


def test_auto_never_picks_a_software_vulkan_device(monkeypatch, no_cuda_no_metal) -> None:
    # the choice among listed devices, whether or not this machine has a Vulkan loader yet
    monkeypatch.setattr(runtime, "_core", lambda: types.SimpleNamespace(with_vulkan=lambda: True))
    monkeypatch.setattr(devices, "vulkan_devices", lambda: [LAVAPIPE])
    assert runtime._resolve("auto")[0] == "cpu"
    arch, device, max_buffer = runtime._resolve("vulkan")  # by name it is fine: tests use it
    assert arch == "vulkan" and "llvmpipe" in device and "CPU (software)" in device and max_buffer == 2**27
    monkeypatch.setattr(devices, "vulkan_devices", lambda: [LAVAPIPE, DISCRETE])
    assert runtime._resolve("auto")[:2] == ("vulkan", "Some GPU [Vulkan 1.3 discrete GPU]")


def test_auto_prefers_cuda(monkeypatch) -> None:
    monkeypatch.setattr(runtime, "cuda_available", lambda: True)
    monkeypatch.setattr(devices, "cuda_device_name", lambda: "NVIDIA H100")
    assert runtime._resolve("auto")[:2] == ("cuda", "NVIDIA H100")


def test_absent_backends_are_errors(monkeypatch, no_cuda_no_metal) -> None:
    monkeypatch.setattr(devices, "vulkan_devices", lambda: [])
    with pytest.raises(BackendError, match="no Vulkan device"):
        runtime._resolve("vulkan")
    with pytest.raises(BackendError, match="macOS"):
        runtime._resolve("metal")
    with pytest.raises(BackendError, match="no CUDA GPU"):
        runtime._resolve("cuda")
    assert runtime._resolve("auto")[0] == "cpu"


def test_buffer_limit_is_an_error_not_a_silent_overread(monkeypatch) -> None:
    backend = runtime.Backend("vulkan", "vulkan", "f32", "", 2, "llvmpipe [Vulkan]", 2**27)
    monkeypatch.setattr(runtime, "_backend", backend)
    runtime.check_buffer(2**27, "entries")
    with pytest.raises(BackendError, match="entries needs 129 MiB"):
        runtime.check_buffer(2**27 + 2**20, "entries")
    with pytest.raises(BackendError, match="CPU or CUDA"):
        runtime.require_f64()


@pytest.mark.skipif(platform.system() != "Linux", reason="points the Linux Vulkan loader at nothing")
def test_cli_vulkan_without_a_driver_exits_2() -> None:
    env = dict(os.environ, VK_ICD_FILENAMES="/nonexistent/icd.json")
    env.pop(runtime.ARCH_ENV, None)
    result = subprocess.run([sys.executable, "-m", "taichi_gs.cli", "--arch", "vulkan", "info"],
                            capture_output=True, text=True, env=env)
    assert result.returncode == 2 and "no Vulkan device" in result.stderr, result.stderr[-2000:]
    assert "arch obtained" not in result.stdout


@pytest.mark.parametrize("setting", [None, "3"])
def test_the_cpu_backend_runs_two_threads_per_core_unless_told(setting) -> None:
    """[ours] `info` reports the thread count obtained: two per core this process may use, or what
    TI_CPU_MAX_NUM_THREADS says; and stage 1's threads, one per core up to a cap."""
    env = {k: v for k, v in os.environ.items() if k not in (runtime.ARCH_ENV, runtime.CPU_THREADS_ENV)}
    if setting is not None:
        env[runtime.CPU_THREADS_ENV] = setting
    result = subprocess.run([sys.executable, "-m", "taichi_gs.cli", "--arch", "cpu", "info"],
                            capture_output=True, text=True, env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    threads = next(line.split()[-1] for line in result.stdout.splitlines() if line.startswith("cpu threads"))
    assert int(threads) == (runtime.cpu_threads() if setting is None else int(setting))
    pose_threads = next(line.split()[-1] for line in result.stdout.splitlines() if line.startswith("stage 1 threads"))
    assert int(pose_threads) == min(available_cores(), DEFAULT_MAX_THREADS)  # Taichi's variable leaves it alone
    assert runtime.cpu_threads() == runtime.CPU_THREADS_PER_CORE * available_cores()
