"""The one place Taichi is initialised: arch choice, offline cache, and a report of what we got."""

from __future__ import annotations

import contextlib
import functools
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import taichi as ti

from ..errors import BackendError

ARCH_CHOICES = ("auto", "cpu", "cuda")


@dataclass(frozen=True)
class Backend:
    """The backend Taichi actually started on."""

    arch: str  # "cpu" or "cuda"
    requested: str
    default_fp: str
    cache_dir: str
    cpu_threads: int


_backend: Backend | None = None


def cache_dir() -> Path:
    """Offline kernel cache location (override with TAICHI_GS_CACHE)."""
    default = Path.home() / ".cache" / "taichi_gs" / "ticache"
    return Path(os.environ.get("TAICHI_GS_CACHE", default))


def cuda_available() -> bool:
    """True when Taichi can start its CUDA backend here (checked without ti.init)."""
    try:
        from taichi._lib import core as _ti_core

        return _has_nvidia_driver() and bool(_ti_core.with_cuda())
    except Exception:  # pragma: no cover - depends on the taichi build
        return False


def _has_nvidia_driver() -> bool:
    import ctypes

    try:
        lib = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return False
    count = ctypes.c_int(0)
    if lib.cuInit(0) != 0 or lib.cuDeviceGetCount(ctypes.byref(count)) != 0:
        return False
    return count.value > 0


def _stdout_to_stderr(function: Callable[..., Backend]) -> Callable[..., Backend]:
    """Run ``function`` with Python's stdout sent to stderr: ``ti.init`` prints "[Taichi] Starting
    on arch=..." there, and stdout carries results (``info``, ``--json``)."""

    @functools.wraps(function)
    def wrapper(*args: Any, **kwargs: Any) -> Backend:
        with contextlib.redirect_stdout(sys.stderr):
            return function(*args, **kwargs)

    return wrapper


@_stdout_to_stderr
def init(arch: str = "auto", default_fp: str = "f32", debug: bool = False) -> Backend:
    """Initialise Taichi once and return the backend obtained.

    ``arch``: ``auto`` picks CUDA only if a GPU is present, else CPU; ``cuda`` without a GPU raises
    :class:`BackendError` instead of Taichi's silent CPU fallback; ``ti.gpu`` is never used.
    Calling again with the same request returns the existing backend; a different request raises.
    """
    global _backend
    if arch not in ARCH_CHOICES:
        raise BackendError(f"unknown arch {arch!r}: choose one of {', '.join(ARCH_CHOICES)}")
    if _backend is not None:
        if arch in ("auto", _backend.arch, _backend.requested) and default_fp == _backend.default_fp:
            return _backend
        raise BackendError(
            f"Taichi already runs on {_backend.arch} ({_backend.default_fp}); "
            f"cannot switch to {arch} ({default_fp}) in the same process"
        )
    want_cuda = arch == "cuda" or (arch == "auto" and cuda_available())
    if arch == "cuda" and not cuda_available():
        raise BackendError("--arch cuda asked for, but no CUDA GPU is usable here; use --arch cpu")
    fp = {"f32": ti.f32, "f64": ti.f64}[default_fp]
    cache = cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    ti.init(
        arch=ti.cuda if want_cuda else ti.cpu,
        default_fp=fp,
        offline_cache=True,
        offline_cache_file_path=str(cache),
        debug=debug,
        log_level=ti.WARN,
    )
    got = ti.lang.impl.current_cfg().arch
    got_name = "cuda" if got == ti.cuda else "cpu"
    if want_cuda and got_name != "cuda":
        raise BackendError("Taichi fell back to the CPU although CUDA was requested; use --arch cpu")
    threads = int(ti.lang.impl.current_cfg().cpu_max_num_threads)
    _backend = Backend(got_name, arch, default_fp, str(cache), threads)
    return _backend


def current() -> Backend | None:
    """The backend started by :func:`init`, or None before it."""
    return _backend
