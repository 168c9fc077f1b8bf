"""The one place Taichi is initialised: arch choice, offline cache, and a report of what we got.

Backends: ``cpu``, ``cuda``, ``vulkan``, ``metal`` (macOS). ``auto`` (the default, or the
``TAICHI_GS_ARCH`` environment variable) takes CUDA when an NVIDIA GPU is usable, then Metal on
macOS, then Vulkan on a hardware device, then the CPU. A software Vulkan device (lavapipe) is
never picked by ``auto``: it runs the GPU kernels on the CPU, slower than the CPU kernels; ask for
it by name (``--arch vulkan``) to test the GPU execution model. Asking for a backend that is not
there raises :class:`BackendError` (Taichi itself would fall back to the CPU silently).
float64 kernels need CPU or CUDA: Taichi's SPIR-V code generator (Vulkan, Metal) has no 64-bit
``exp``. [ours] The CPU backend is started with :data:`CPU_THREADS_PER_CORE` threads per core the process may
use (``TI_CPU_MAX_NUM_THREADS`` sets the count instead): measured at 0.88-0.94x the time of one per core. Taichi
1.7.4 then holds that many pool threads, though on 2 cores only two of them take work; what the count buys is
finer pieces, since Taichi cuts each parallel loop into that many contiguous ones (docs/notebook/benchmarks-2026-11.md,
"Which of Taichi's threads take work" and "A parallel loop is cut into as many contiguous pieces ...").
"""

from __future__ import annotations

import contextlib
import functools
import os
import platform
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import taichi as ti

from ..choices import ARCH_CHOICES
from ..errors import BackendError
from ..machine import available_cores
from . import devices

ARCH_ENV = "TAICHI_GS_ARCH"
CPU_THREADS_ENV = "TI_CPU_MAX_NUM_THREADS"  # Taichi's own setting of the CPU thread count
# measured on 2 cores: renders 0.93x the time (docs/notebook/benchmarks-2026-11.md, "Two CPU threads per core")
CPU_THREADS_PER_CORE = 2
F64_ARCHS = ("cpu", "cuda")


@dataclass(frozen=True)
class Backend:
    """The backend Taichi actually started on."""

    arch: str  # "cpu", "cuda", "vulkan" or "metal"
    requested: str
    default_fp: str
    cache_dir: str
    cpu_threads: int
    device: str = ""
    # Largest ndarray (bytes) the device can bind as one storage buffer; 0 = no limit known.
    max_buffer_bytes: int = 0

    @property
    def gpu_kernels(self) -> bool:
        """True when the GPU-structured kernels run (every backend but the CPU)."""
        return self.arch != "cpu"

    @property
    def has_f64(self) -> bool:
        return self.arch in F64_ARCHS


_backend: Backend | None = None


def cache_dir() -> Path:
    """Offline kernel cache location (override with TAICHI_GS_CACHE)."""
    default = Path.home() / ".cache" / "taichi_gs" / "ticache"
    return Path(os.environ.get("TAICHI_GS_CACHE", default))


def _core():
    from taichi._lib import core as _ti_core

    return _ti_core


def cuda_available() -> bool:
    """True when Taichi can start its CUDA backend here (checked without ti.init)."""
    try:
        return devices.cuda_device_name() is not None and bool(_core().with_cuda())
    except Exception:  # pragma: no cover - depends on the taichi build
        return False


def metal_available() -> bool:
    """True on macOS with a Taichi build that has Metal."""
    try:
        return platform.system() == "Darwin" and bool(_core().with_metal())
    except Exception:  # pragma: no cover - depends on the taichi build
        return False


def _stdout_to_stderr(function: Callable[..., Backend]) -> Callable[..., Backend]:
    """Run ``function`` with Python's stdout sent to stderr: ``ti.init`` prints "[Taichi] Starting
    on arch=..." there, and stdout carries results (``info``, ``--json``)."""

    @functools.wraps(function)
    def wrapper(*args: Any, **kwargs: Any) -> Backend:
        with contextlib.redirect_stdout(sys.stderr):
            return function(*args, **kwargs)

    return wrapper


def vulkan_device(hardware_only: bool = False) -> devices.VulkanDevice | None:
    """The Vulkan device Taichi would take (None without one, or when ``hardware_only`` and it is
    a software device)."""
    try:
        if not _core().with_vulkan():
            return None
    except Exception:  # pragma: no cover - depends on the taichi build
        return None
    picked = devices.taichi_vulkan_pick(devices.vulkan_devices())
    if picked is None or (hardware_only and picked.software):
        return None
    return picked


def requested_arch(arch: str | None = None) -> str:
    """``arch``, else ``TAICHI_GS_ARCH``, else "auto"; checked against :data:`ARCH_CHOICES`."""
    name = (arch or os.environ.get(ARCH_ENV) or "auto").strip().lower()
    if name not in ARCH_CHOICES:
        source = "arch" if arch else ARCH_ENV
        raise BackendError(f"unknown {source} {name!r}: choose one of {', '.join(ARCH_CHOICES)}")
    return name


def _resolve(requested: str) -> tuple[str, str, int]:
    """(arch, device description, max buffer bytes) for a request; raises when it is absent."""
    if requested in ("cuda", "auto") and cuda_available():
        return "cuda", devices.cuda_device_name() or "CUDA device", 0
    if requested == "cuda":
        raise BackendError("--arch cuda asked for, but no CUDA GPU is usable here; use --arch auto or cpu")
    if requested in ("metal", "auto") and metal_available():
        return "metal", f"Apple GPU ({platform.machine()}) [Metal]", 0
    if requested == "metal":
        raise BackendError("--arch metal asked for, but Metal needs macOS and a Taichi build with Metal; "
                           "use --arch auto or cpu")
    if requested in ("vulkan", "auto"):
        vk = vulkan_device(hardware_only=requested == "auto")
        if vk is not None:
            return "vulkan", vk.describe(), vk.max_storage_buffer_bytes
    if requested == "vulkan":
        raise BackendError("--arch vulkan asked for, but no Vulkan device was found (install a Vulkan driver; "
                           "for tests, `source scripts/vulkan.sh` sets up a CPU one); use --arch auto or cpu")
    return "cpu", f"{devices.cpu_model()} [CPU]", 0


@_stdout_to_stderr
def init(arch: str | None = None, default_fp: str = "f32", debug: bool = False) -> Backend:
    """Initialise Taichi once and return the backend obtained.

    ``arch``: one of :data:`ARCH_CHOICES`; None reads ``TAICHI_GS_ARCH`` (default "auto").
    A named backend that is absent raises :class:`BackendError` instead of Taichi's silent CPU
    fallback; ``ti.gpu`` is never used. Calling again with the same request (or "auto"/None)
    returns the existing backend; a different request raises.
    """
    global _backend
    requested = requested_arch(arch)
    if _backend is not None:
        if requested in ("auto", _backend.arch, _backend.requested) and default_fp == _backend.default_fp:
            return _backend
        raise BackendError(
            f"Taichi already runs on {_backend.arch} ({_backend.default_fp}); "
            f"cannot switch to {requested} ({default_fp}) in the same process"
        )
    name, device, max_buffer = _resolve(requested)
    if default_fp == "f64" and name not in F64_ARCHS:
        raise BackendError(f"float64 needs the CPU or CUDA backend (Taichi's {name} backend has no 64-bit exp); "
                           "use --arch cpu or float32")
    fp = {"f32": ti.f32, "f64": ti.f64}[default_fp]
    cache = cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    threads = {} if os.environ.get(CPU_THREADS_ENV) else {"cpu_max_num_threads": cpu_threads()}
    ti.init(
        arch=getattr(ti, name),
        default_fp=fp,
        offline_cache=True,
        offline_cache_file_path=str(cache),
        debug=debug,
        log_level=ti.WARN,
        **threads,
    )
    got = ti.lang.impl.current_cfg().arch
    if got != getattr(ti, name):
        raise BackendError(f"Taichi fell back to {got.name} although {name} was requested; use --arch cpu")
    if name == "vulkan":
        _check_atomic_loops(device)
    threads = int(ti.lang.impl.current_cfg().cpu_max_num_threads)
    _backend = Backend(name, requested, default_fp, str(cache), threads, device, max_buffer)
    return _backend


def _check_atomic_loops(device: str) -> None:
    """Refuse a Vulkan driver that drops loop iterations containing an atomic (Mesa 22 lavapipe)."""
    from . import canary

    for got, want in canary.atomic_loop_counts():
        if got != want:
            raise BackendError(f"the Vulkan driver of {device} drops loop iterations that contain an atomic "
                               f"({got} of {want} counted; Mesa < 25 lavapipe does); update the driver "
                               "(for a CPU one: source scripts/vulkan.sh) or use --arch cpu")


def cpu_threads() -> int:
    """Threads for Taichi's CPU backend: :data:`CPU_THREADS_PER_CORE` per core this process may run on."""
    return CPU_THREADS_PER_CORE * available_cores()


def current() -> Backend | None:
    """The backend started by :func:`init`, or None before it."""
    return _backend


CPU_LOOP_SPREAD = 64


def loop_spread() -> int:
    """Loop indices per item for a parallel loop over a few hundred items (image rows, tiles).

    Taichi's CPU backend runs a range-for that short on one thread, so such loops iterate over
    ``spread x items`` indices and work on every spread-th one (64 on the CPU); 1 on GPU backends."""
    backend = current()
    return CPU_LOOP_SPREAD if backend is None or backend.arch == "cpu" else 1


def kernel_types(dt) -> tuple:
    """The types a kernel builder annotates with, for float type ``dt``: (mat4, vec4, vec3, float ndarray of a
    rank, i32 ndarray of a rank, i64 ndarray of a rank); the ndarray ones are functions of the rank."""
    def arrays(dtype):
        return lambda ndim: ti.types.ndarray(dtype=dtype, ndim=ndim)

    return (ti.types.matrix(4, 4, dt), ti.types.vector(4, dt), ti.types.vector(3, dt), arrays(dt), arrays(ti.i32),
            arrays(ti.i64))


def require_f64(what: str = "float64 kernels") -> None:
    """Raise :class:`BackendError` when the running backend cannot run float64 kernels."""
    if _backend is not None and not _backend.has_f64:
        raise BackendError(f"{what} need the CPU or CUDA backend: Taichi's {_backend.arch} backend has no "
                           "64-bit exp; use --arch cpu (or float32)")


def check_buffer(nbytes: int, what: str) -> None:
    """Raise :class:`BackendError` when one ndarray of ``nbytes`` exceeds what the device binds
    (lavapipe: 128 MiB per storage buffer), instead of reading past it silently."""
    if _backend is not None and _backend.max_buffer_bytes and nbytes > _backend.max_buffer_bytes:
        raise BackendError(
            f"{what} needs {nbytes / 2**20:.0f} MiB in one buffer, more than the {_backend.device} binds "
            f"({_backend.max_buffer_bytes / 2**20:.0f} MiB); use fewer Gaussians, a smaller image, or --arch cpu"
        )
