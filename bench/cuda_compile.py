"""CUDA compile check without a GPU: every kernel through Taichi's CUDA code generator, the PTX
assembled by ptxas, registers / spills / shared memory per kernel task.

    python bench/cuda_compile.py --ptxas /path/to/ptxas [--sm sm_90] [--markdown]

How: a stub ``libcuda.so`` (C source below, built with the system ``cc`` into a temporary folder)
answers Taichi's driver calls (device "stub sm_90", compute capability 9.0, fake device pointers,
launches that do nothing) and writes every PTX module Taichi loads (``cuModuleLoadDataEx``) to a
folder. A child process starts Taichi on CUDA through :mod:`taichi_gs.kernels.runtime` with that
stub first on ``LD_LIBRARY_PATH`` and an empty offline cache, and runs each kernel family once
(GPU rasterizer f32 and f64, anisotropic and isotropic; scans and radix sort; losses; blur; Adam;
ray caster; canary). Nothing is computed (reads return zeros), but Taichi compiles every kernel it
launches. Taichi 1.7 caps the PTX target at sm_86; ptxas assembles it for ``--sm``.

ptxas comes from PyPI's ``nvidia-cuda-nvcc-cu12`` (keep it out of the project's venv), e.g.
``pip download nvidia-cuda-nvcc-cu12 --no-deps -d /tmp/nvcc && python -m zipfile -e /tmp/nvcc/*.whl
/tmp/nvcc/x && chmod +x /tmp/nvcc/x/nvidia/cuda_nvcc/bin/ptxas``.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

STUB_C = r"""
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <stddef.h>
static unsigned long long next_ptr = 0x700000000000ULL;
static int n_modules = 0;
static void *fake(size_t n) { void *p = (void *)next_ptr; next_ptr += ((n + 0xffff) & ~0xffffULL) + 0x10000; return p; }
int cuInit(int f) { return 0; }
int cuDriverGetVersion(int *v) { *v = 12040; return 0; }
int cuGetErrorName(int e, const char **s) { *s = "CUDA_STUB"; return 0; }
int cuGetErrorString(int e, const char **s) { *s = "stub driver"; return 0; }
int cuDeviceGetCount(int *n) { *n = 1; return 0; }
int cuDeviceGet(int *d, int i) { *d = 0; return 0; }
int cuDeviceGetName(char *s, int n, int d) { snprintf(s, n, "stub sm_90"); return 0; }
int cuDeviceGetAttribute(int *v, int a, int d) {
  switch (a) {
    case 75: *v = 9; break;        /* compute capability major */
    case 76: *v = 0; break;        /* minor */
    case 16: *v = 132; break;      /* multiprocessors */
    case 1: *v = 1024; break;      /* max threads per block */
    case 8: *v = 49152; break;     /* shared memory per block */
    case 97: *v = 232448; break;   /* shared memory per block, opt-in */
    case 115: *v = 0; break;       /* memory pools: no */
    default: *v = 1;
  }
  return 0;
}
int cuDeviceGetDefaultMemPool(void **p, int d) { *p = fake(1); return 0; }
int cuMemPoolSetAttribute(void *p, int a, void *v) { return 0; }
int cuCtxCreate_v2(void **c, int f, int d) { *c = (void *)0x1000; return 0; }
int cuCtxSetCurrent(void *c) { return 0; }
int cuCtxGetCurrent(void **c) { *c = (void *)0x1000; return 0; }
int cuDevicePrimaryCtxRetain(void **c, int d) { *c = (void *)0x1000; return 0; }
int cuCtxSetLimit(int l, size_t v) { return 0; }
int cuStreamCreate(void **s, unsigned f) { *s = (void *)0x2000; return 0; }
int cuStreamSynchronize(void *s) { return 0; }
int cuMemcpyHtoD_v2(void *d, void *s, size_t n) { return 0; }
int cuMemcpyDtoH_v2(void *d, void *s, size_t n) { memset(d, 0, n); return 0; }
int cuMemcpyDtoD_v2(void *d, void *s, size_t n) { return 0; }
int cuMemcpyHtoDAsync_v2(void *d, void *s, size_t n, void *st) { return 0; }
int cuMemcpyDtoHAsync_v2(void *d, void *s, size_t n, void *st) { memset(d, 0, n); return 0; }
int cuMemAlloc_v2(void **p, size_t n) { *p = fake(n); return 0; }
int cuMemAllocAsync(void **p, size_t n, void *s) { *p = fake(n); return 0; }
int cuMemAllocManaged(void **p, size_t n, unsigned f) { *p = calloc(1, n ? n : 1); return 0; }
int cuMemsetD8_v2(void *p, unsigned char v, size_t n) { return 0; }
int cuMemsetD32_v2(void *p, unsigned v, size_t n) { return 0; }
int cuMemFree_v2(void *p) { return 0; }
int cuMemFreeAsync(void *p, void *s) { return 0; }
int cuMemAdvise(void *p, size_t n, unsigned a, unsigned d) { return 0; }
int cuMemGetInfo_v2(size_t *f, size_t *t) { *f = 70ULL << 30; *t = 80ULL << 30; return 0; }
int cuPointerGetAttribute(void *v, unsigned a, void *p) { memset(v, 0, 8); return 0; }
int cuModuleLoadDataEx(void **m, const char *img, unsigned n, unsigned *o, void **ov) {
  const char *dir = getenv("CUDA_STUB_PTX_DIR");
  if (dir) {
    char path[4096];
    snprintf(path, sizeof path, "%s/module_%05d.ptx", dir, n_modules);
    FILE *f = fopen(path, "w");
    if (f) { fputs(img, f); fclose(f); }
  }
  n_modules++;
  *m = fake(1);
  return 0;
}
int cuModuleGetFunction(void **f, void *m, const char *name) { *f = fake(1); return 0; }
int cuLaunchKernel(void *f, unsigned a, unsigned b, unsigned c, unsigned d, unsigned e, unsigned g,
                   unsigned sm, void *s, void **p, void **x) { return 0; }
int cuFuncGetAttribute(int *v, int a, void *f) { *v = 0; return 0; }
int cuFuncSetAttribute(void *f, int a, int v) { return 0; }
int cuOccupancyMaxActiveBlocksPerMultiprocessor(int *n, void *f, int b, size_t s) { *n = 1; return 0; }
int cuEventCreate(void **e, unsigned f) { *e = fake(1); return 0; }
int cuEventDestroy(void *e) { return 0; }
int cuEventRecord(void *e, void *s) { return 0; }
int cuEventSynchronize(void *e) { return 0; }
int cuEventElapsedTime(float *t, void *a, void *b) { *t = 0; return 0; }
/* Vulkan interop: not supported by the stub */
int cuImportExternalMemory(void *a, void *b) { return 1; }
int cuExternalMemoryGetMappedBuffer(void *a, void *b, void *c) { return 1; }
int cuExternalMemoryGetMappedMipmappedArray(void *a, void *b, void *c) { return 1; }
int cuMipmappedArrayGetLevel(void *a, void *b, unsigned c) { return 1; }
int cuSurfObjectCreate(void *a, void *b) { return 1; }
int cuSignalExternalSemaphoresAsync(void *a, void *b, unsigned c, void *d) { return 1; }
int cuWaitExternalSemaphoresAsync(void *a, void *b, unsigned c, void *d) { return 1; }
int cuImportExternalSemaphore(void *a, void *b) { return 1; }
"""

# Taichi's own helper modules (runtime, ndarray copies) are not ours: left out of the table.
TAICHI_INTERNAL = ("runtime_", "ndarray_to_ext_arr", "ext_arr_to_ndarray", "fill_ndarray", "ndarray_to_ndarray")


def exercise() -> None:
    """Child process: start Taichi on (stub) CUDA and launch every kernel family once."""
    import numpy as np
    import taichi as ti

    from taichi_gs.kernels import blur, canary, losses, runtime, scan
    from taichi_gs.kernels.optim import Adam
    from taichi_gs.kernels.raycast import render as raycast
    from taichi_gs.render import Camera, DeviceGaussians, Rasterizer, to_device
    from taichi_gs.synth import build_scene

    got = runtime.init("cuda")
    assert got.arch == "cuda" and got.gpu_kernels, got
    rng = np.random.default_rng(0)
    n, width, height = 64, 64, 48
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    means = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(2, 4, n)]
    for dtype in (ti.f32, ti.f64):
        for iso in (False, True):
            scales = np.full((n, 1 if iso else 3), -3.0)
            gs = DeviceGaussians.from_numpy(means, rng.normal(size=(n, 4)), scales, np.zeros(n),
                                            rng.normal(size=(n, 16, 3)), isotropic=iso, dtype=dtype)
            rast = Rasterizer(dtype)
            assert rast.gpu is not None
            view = rast.forward(gs, Camera(K, np.eye(4), width, height))
            ones = [to_device(np.ones(s), dtype) for s in ((height, width, 3), (height, width), (height, width))]
            rast.backward(gs, view, *ones)
    scratch = scan.Scratch()
    keys, vals, out = ti.ndarray(ti.i32, (5000,)), ti.ndarray(ti.i32, (5000,)), ti.ndarray(ti.i32, (5001,))
    scan.exclusive_scan(keys, out, 5000, scratch)
    scan.radix_sort(keys, vals, 5000, 31, scratch)
    for dtype in (ti.f32, ti.f64):
        img = [to_device(np.ones((height, width, 3)), dtype) for _ in range(3)]
        dep = [to_device(np.ones((height, width)), dtype) for _ in range(3)]
        losses.l1(img[0], img[1], img[2])
        losses.dssim(img[0], img[1], img[2])
        losses.masked_depth_l1(dep[0], dep[1], dep[2])
        logits = to_device(np.zeros(100), dtype)
        losses.opacity_binarization(logits, to_device(np.zeros(100), dtype), 100)
        blur.average(img[:2], img[2])
        blur.spread(img[0], 2, img[1])
        params, grads = {"x": to_device(np.zeros((10, 3)), dtype)}, {"x": to_device(np.zeros((10, 3)), dtype)}
        Adam(params, grads, {"x": 0.01}).step()
    room = build_scene(0)
    raycast(np.eye(4)[None], K, width, height, room.prims, room.textures)
    canary.atomic_loop_counts()


def kernel_name(entry: str) -> tuple[str, str]:
    """('blend_forward', '1 range_for') from 'blend_forward_c84_0_kernel_1_range_for' (Taichi's task
    names: kernel, compile id, offloaded task index, task type)."""
    m = re.match(r"(.+?)_c\d+_\d+_kernel_(\d+)_(\w+)$", entry)
    return (m.group(1), f"{m.group(2)} {m.group(3)}") if m else (entry, "")


def assemble(ptxas: str, sm: str, ptx_dir: Path) -> list[dict]:
    """Per task of our kernels: registers, spills, stack, shared memory, barriers (ptxas -v)."""
    rows = []
    for path in sorted(ptx_dir.glob("*.ptx")):
        result = subprocess.run([ptxas, f"-arch={sm}", "-v", str(path), "-o", os.devnull],
                                capture_output=True, text=True)
        if result.returncode != 0:
            raise SystemExit(f"ptxas failed on {path}:\n{result.stderr[-3000:]}")
        current = None
        for line in result.stderr.splitlines():
            if m := re.search(r"Compiling entry function '([^']+)'", line):
                current = {"task": m.group(1), "module": path.name, "stack": 0, "spill_st": 0, "spill_ld": 0,
                           "regs": 0, "smem": 0, "barriers": 0}
                rows.append(current)
            elif current and (m := re.search(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes "
                                             r"spill loads", line)):
                current["stack"], current["spill_st"], current["spill_ld"] = map(int, m.groups())
            elif current and "Used" in line:
                current["regs"] = int(re.search(r"Used (\d+) registers", line).group(1))
                if m := re.search(r"(\d+) bytes smem", line):
                    current["smem"] = int(m.group(1))
                if m := re.search(r"used (\d+) barriers", line):
                    current["barriers"] = int(m.group(1))
    return [r for r in rows if not r["task"].startswith(TAICHI_INTERNAL)]


def dtype_of(module_text: str) -> str:
    """The widest float type the module touches ('f64', 'f32' or 'int')."""
    for name in ("f64", "f32"):
        if re.search(rf"\.{name}\b", module_text):
            return name
    return "int"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ptxas", required=True, help="ptxas from PyPI nvidia-cuda-nvcc-cu12")
    parser.add_argument("--sm", default="sm_90", help="target of ptxas (default sm_90, H100)")
    parser.add_argument("--markdown", action="store_true", help="print a BENCHMARKS.md table")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        exercise()
        return
    with tempfile.TemporaryDirectory(prefix="cuda-compile-") as tmp:
        tmp = Path(tmp)
        (tmp / "stub.c").write_text(STUB_C)
        subprocess.run(["cc", "-shared", "-fPIC", "-O1", "-o", str(tmp / "libcuda.so"), str(tmp / "stub.c")],
                       check=True)
        (tmp / "libcuda.so.1").symlink_to("libcuda.so")
        ptx_dir = tmp / "ptx"
        ptx_dir.mkdir()
        env = dict(os.environ, CUDA_STUB_PTX_DIR=str(ptx_dir), TAICHI_GS_CACHE=str(tmp / "cache"),
                   LD_LIBRARY_PATH=f"{tmp}:{os.environ.get('LD_LIBRARY_PATH', '')}",
                   PYTHONPATH=f"{REPO}:{os.environ.get('PYTHONPATH', '')}")
        env.pop("TAICHI_GS_ARCH", None)
        child = subprocess.run([sys.executable, __file__, "--child", "--ptxas", args.ptxas], env=env,
                               capture_output=True, text=True)
        if child.returncode != 0:
            raise SystemExit(f"the CUDA compile run failed:\n{child.stderr[-4000:]}")
        rows = assemble(args.ptxas, args.sm, ptx_dir)
        for r in rows:
            r["dtype"] = dtype_of((ptx_dir / r["module"]).read_text())
    version = subprocess.run([args.ptxas, "--version"], capture_output=True, text=True).stdout.strip().splitlines()
    seen = set()
    table = []
    for r in rows:
        kernel, kind = kernel_name(r["task"])
        key = (kernel, kind, r["dtype"], r["regs"], r["spill_st"], r["smem"])
        if kind.endswith("serial") or key in seen:  # Taichi's one-thread prologue tasks; identical variants
            continue
        seen.add(key)
        table.append((kernel, kind, r))
    table.sort(key=lambda t: (t[0], t[2]["dtype"], t[2]["regs"]))
    n_spill = sum(1 for _, _, r in table if r["spill_st"] or r["spill_ld"])
    print(f"ptxas: {version[-1] if version else '?'}; target {args.sm} (Taichi emits sm_86 PTX); "
          f"{len(rows)} tasks of {len({t[0] for t in table})} kernels, {n_spill} rows with spills")
    if args.markdown:
        print("\n| kernel | task | dtype | registers | spill st/ld (B) | stack (B) | shared (B) | barriers |")
        print("|---|---|---|---:|---:|---:|---:|---:|")
    for kernel, kind, r in table:
        if args.markdown:
            print(f"| `{kernel}` | {kind} | {r['dtype']} | {r['regs']} | {r['spill_st']}/{r['spill_ld']} | "
                  f"{r['stack']} | {r['smem']} | {r['barriers']} |")
        else:
            print(f"{kernel:28s} {kind:10s} {r['dtype']} regs {r['regs']:3d} spill {r['spill_st']}/{r['spill_ld']} "
                  f"stack {r['stack']} smem {r['smem']} barriers {r['barriers']}")


if __name__ == "__main__":
    main()
