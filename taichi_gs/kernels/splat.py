"""Device-resident Gaussians and the Rasterizer that launches the fused render / backward kernels
(the CPU path's are in :mod:`~taichi_gs.kernels.splat_cpu`, the GPU path's in :mod:`~taichi_gs.kernels.raster_gpu`).

:class:`DeviceGaussians` keeps parameters and gradients in Taichi ndarrays between iterations;
:class:`Rasterizer` renders a camera into a :class:`View` (its buffers are reused per view index,
so k views can be alive at once for blur averaging) and back-propagates image gradients into the
Gaussians' gradient buffers (accumulating, so k views sum) and a 6-vector pose gradient.

Per forward: three kernel launches (project + per-Gaussian slot offsets; binning + per-tile depth
sort + gather of tile-ordered records; blending). The slot buffers hold the Rasterizer's slot capacity
(sized from an earlier count with headroom, grown geometrically, never shrunk; ndarray arguments never
trigger recompiles); the slot count stays on the device. A view whose slots do not fit renders nothing:
a checked forward (the default) reads its count and renders again; a ``deferred`` one reads nothing.
Per backward: one launch (tile replay, per-Gaussian reduction + projection backward, pose sum); the pose
gradient is read back (a checked backward), or left with the view's slot count and overflow flag in a pose
row of a training step's values (``pose_into``, :mod:`~taichi_gs.kernels.step_values`), so that a step's k
views come back in the step's one read; :meth:`Rasterizer.pose_gradients` of the rows read also says whether
any of them overflowed.
That is the CPU path (one thread per tile); on GPU backends the Rasterizer hands both passes to
:class:`~taichi_gs.kernels.raster_gpu.GpuPipeline` (block per tile, thread per pixel).
``forward(..., with_colour=False)`` blends depth and alpha only (stage 2): the CPU path skips the
colour sums, forward and backward; the GPU path renders colour anyway.
"""

import functools
import math
import time
from dataclasses import dataclass

import numpy as np
import taichi as ti

from .. import profiling
from . import host_copy, raster_gpu, runtime, scan, tiles
from .project import P_WIDTH
from .rasterize import B_WIDTH, E_WIDTH, F_WIDTH, N_SLOT_GRADS
from .splat_cpu import COUNT_RUNS, POSE_CHUNK, POSE_COLUMNS, SCAN_CHUNK, cpu_kernels
from .step_values import Slot, StepValues
from .tiles import TILE


def float_type(precision: str):
    """Taichi float type of "f32" or "f64"."""
    return {"f32": ti.f32, "f64": ti.f64}[precision]


def to_device(arr: np.ndarray, dtype) -> ti.Ndarray:
    """A new ndarray of Taichi float type ``dtype`` holding ``arr``."""
    if dtype == ti.f64:
        runtime.require_f64("float64 arrays")
    arr = np.asarray(arr)
    nd = ti.ndarray(dtype, arr.shape)
    host_copy.write(nd, arr)  # casts to the ndarray's type
    return nd


@functools.cache
def _zero_kernel(dt):
    """One launch that zeroes five arrays of any rank (the Gaussians' gradient buffers), row by row."""

    @ti.func
    def zero_row(a: ti.template(), r):
        if r < a.shape[0]:  # the rank's loops inside (compiled per rank): no integer division per element
            if ti.static(len(a.shape) == 1):
                a[r] = 0.0
            elif ti.static(len(a.shape) == 2):
                for c in range(a.shape[1]):
                    a[r, c] = 0.0
            else:
                for i in range(a.shape[1]):
                    for j in range(a.shape[2]):
                        a[r, i, j] = 0.0

    arr = ti.types.ndarray(dtype=dt)

    @ti.kernel
    def zero_rows(a0: arr, a1: arr, a2: arr, a3: arr, a4: arr, rows: ti.i32):
        for r in range(rows):
            zero_row(a0, r)
            zero_row(a1, r)
            zero_row(a2, r)
            zero_row(a3, r)
            zero_row(a4, r)

    return zero_rows


def _grown(arr, need: int, dtype, tail: tuple = ()):
    """``arr`` if it holds ``need`` rows, else a new ndarray with 1.5x headroom (less where the
    device's per-buffer limit says so; :class:`BackendError` when ``need`` rows exceed it)."""
    if arr is not None and arr.shape[0] >= need:
        return arr
    row_bytes = math.prod(tail) * (8 if dtype in (ti.f64, ti.i64) else 4)
    runtime.check_buffer(need * row_bytes, f"a rasterizer buffer of {need} x {tail or 1}")
    rows = max(int(need * 1.5), 16)
    backend = runtime.current()
    if backend is not None and backend.max_buffer_bytes:
        rows = max(need, min(rows, backend.max_buffer_bytes // row_bytes))
    return ti.ndarray(dtype, (rows,) + tail)


class DeviceGaussians:
    """Gaussian parameters and their gradients, resident in Taichi ndarrays.

    Shapes: means (N, 3); quats (N, 4) as w x y z (raw, normalised inside the renderer);
    log_scales (N, 3), or (N, 1) when ``isotropic`` (then scales and rotations are fixed: no
    gradients are computed for them and quats is a 1-row placeholder); opacity_logits (N,);
    colors (N, M, 3) SH coefficients, M in {1, 4, 9, 16}, DC first.
    ``params[name]`` and ``grads[name]`` are the ndarrays; gradients accumulate until
    :meth:`zero_grad`.
    """

    def __init__(self, n: int, n_sh: int = 1, isotropic: bool = False, dtype=ti.f32) -> None:
        if n_sh not in (1, 4, 9, 16):
            raise ValueError(f"number of SH coefficients must be 1, 4, 9 or 16, got {n_sh}")
        runtime.init()
        if dtype == ti.f64:
            runtime.require_f64("float64 Gaussians")
        self.n, self.n_sh, self.isotropic, self.dtype = n, n_sh, isotropic, dtype
        rows = max(n, 1)
        shapes = {
            "means": (rows, 3),
            "quats": (1 if isotropic else rows, 4),
            "log_scales": (rows, 1 if isotropic else 3),
            "opacity_logits": (rows,),
            "colors": (rows, n_sh, 3),
        }
        for name, shape in shapes.items():
            runtime.check_buffer(math.prod(shape) * (8 if dtype == ti.f64 else 4), f"Gaussian {name} {shape}")
        self.params = {k: ti.ndarray(dtype, s) for k, s in shapes.items()}
        self.grads = {k: ti.ndarray(dtype, s) for k, s in shapes.items()}
        self.params["quats"].fill(0.0)
        self.zero_grad()

    @classmethod
    def from_numpy(
        cls, means, quats, log_scales, opacity_logits, colors, isotropic: bool = False, dtype=ti.f32
    ) -> "DeviceGaussians":
        """Upload parameters (colors may be (N, 3) for SH degree 0)."""
        colors = np.asarray(colors)
        if colors.ndim == 2:
            colors = colors[:, None, :]
        log_scales = np.asarray(log_scales)
        if isotropic and log_scales.ndim == 1:
            log_scales = log_scales[:, None]
        model = cls(len(means), colors.shape[1], isotropic, dtype)
        model.upload(means=means, quats=None if isotropic else quats, log_scales=log_scales,
                     opacity_logits=opacity_logits, colors=colors)
        return model

    @property
    def view_dependent(self) -> bool:
        """True when colours depend on the view (SH degree above 0): the rasterizer kernels take it as a
        compile-time switch, so degree-0 scenes compile without the higher SH bands."""
        return self.n_sh > 1

    def upload(self, **arrays: np.ndarray | None) -> None:
        """Overwrite the named parameters from NumPy (None entries are skipped)."""
        for name, value in arrays.items():
            if value is None or self.n == 0:
                continue
            host_copy.write(self.params[name], value)

    def download(self, grads: bool = False) -> dict[str, np.ndarray]:
        """Parameters (or gradients) as NumPy arrays, trimmed to N rows."""
        source = self.grads if grads else self.params
        return {k: host_copy.read(v, self.n) for k, v in source.items()}

    def zero_grad(self) -> None:
        """Reset every gradient buffer to 0 (one launch)."""
        grads = list(self.grads.values())
        _zero_kernel(self.dtype)(*grads, max(g.shape[0] for g in grads))


@dataclass
class Camera:
    """Pinhole camera in the rasterizer's convention (pixel u samples image coordinate u + 0.5).

    ``K`` 3x3 intrinsics, ``cam_to_world`` 4x4 pose (OpenCV axes), image ``width`` x ``height``.
    """

    K: np.ndarray
    cam_to_world: np.ndarray
    width: int
    height: int


class View:
    """Buffers of one rendered view: images (``rgb`` (H, W, 3), ``depth`` (H, W),
    ``transmittance`` (H, W) = 1 - alpha, as ndarrays) and what the backward replays."""

    def __init__(self, dtype) -> None:
        self.dtype = dtype
        self.proj = self.rect = self.offsets = self.chunk_base = None
        self.slot_gid = self.slot_tile = self.keys = self.tmp_keys = self.order = None
        self.entries = None
        self.tile_cursor = self.tile_start = None
        self.scratch = scan.Scratch()  # the GPU path's per-view buffers (raster_gpu)
        self.depth_order = self.depth_offsets = self.tile_range = None
        self.rgb = self.depth = self.transmittance = self.last = None
        self.camera: Camera | None = None
        self.background = np.zeros(3)
        self.with_colour = True  # False: a depth-and-alpha render (rgb black, no colour gradients)
        self.n = 0
        self.n_slots: int | None = 0  # the slot count S (None after a deferred forward: see slot_count)
        self.cap = 0  # slots the buffers held when it was rendered
        self.size = (0, 0)

    def ensure_images(self, width: int, height: int) -> None:
        if self.size != (width, height):
            dt = self.dtype
            self.rgb = ti.ndarray(dt, (height, width, 3))
            self.depth = ti.ndarray(dt, (height, width))
            self.transmittance = ti.ndarray(dt, (height, width))
            self.last = ti.ndarray(ti.i32, (height, width))
            tiles_x, tiles_y = tiles.tile_grid(width, height)
            self.tile_cursor = ti.ndarray(ti.i32, (COUNT_RUNS, tiles_x * tiles_y))
            self.tile_start = ti.ndarray(ti.i32, (tiles_x * tiles_y + 1,))
            self.size = (width, height)

    def slot_count(self) -> int:
        """The slot count S of the last render (one Gaussian per tile it touches), read from the device."""
        offsets = self.offsets if self.depth_offsets is None else self.depth_offsets
        return int(offsets[self.n])

    def tiles_per_gaussian(self) -> np.ndarray:
        """How many 16x16 tiles each of the n Gaussians touched (0 when culled), from its pixel box."""
        rect = host_copy.read(self.rect, self.n).astype(np.int64)
        visible = rect[:, 0] <= rect[:, 2]
        tiles_x = rect[:, 2] // TILE - rect[:, 0] // TILE + 1
        tiles_y = rect[:, 3] // TILE - rect[:, 1] // TILE + 1
        return np.where(visible, tiles_x * tiles_y, 0)

    def to_numpy(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb, depth, alpha) as float32 NumPy arrays."""
        rgb = host_copy.read(self.rgb).astype(np.float32)
        depth = host_copy.read(self.depth).astype(np.float32)
        alpha = (1.0 - host_copy.read(self.transmittance)).astype(np.float32)
        return rgb, depth, alpha


def camera_args(camera: Camera, dtype) -> tuple:
    K = np.asarray(camera.K, dtype=np.float64)
    cam = ti.Matrix(np.asarray(camera.cam_to_world, dtype=np.float64).tolist(), dt=dtype)
    intr = ti.Vector([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], dt=dtype)
    return cam, intr


def sync() -> None:
    """Wait for every launched kernel to finish (for timers); nothing before the runtime starts."""
    if runtime.current() is not None:
        ti.sync()


class _PhaseClock:
    """Adds synchronised wall time per phase into a dict; does nothing without one."""

    def __init__(self, timings: dict | None) -> None:
        self.timings = timings
        self.last = time.perf_counter() if timings is not None else 0.0

    def __call__(self, phase: str) -> None:
        if self.timings is not None:
            ti.sync()
            now = time.perf_counter()
            self.timings[phase] = self.timings.get(phase, 0.0) + now - self.last
            self.last = now


class Rasterizer:
    """Renders :class:`DeviceGaussians` and back-propagates into their gradient buffers.

    ``forward(gaussians, camera, view=i)`` fills view buffer i (reused across calls);
    ``backward(gaussians, view, d_rgb, d_depth, d_alpha)`` adds dL/dparams into
    ``gaussians.grads`` and returns dL/d(pose) as a NumPy 6-vector [translation, rotation] for the
    left perturbation ``cam_to_world' = exp(delta) @ cam_to_world``. Image gradients are ndarrays
    of the rasterizer's dtype or None (zero).

    A training step reads nothing per view: ``forward(..., deferred=True)`` and ``backward(...,
    pose_into=rows.row(j, POSE_COLUMNS))`` (the pose gradient left in row j of a slot ``rows`` of the step's
    :class:`~taichi_gs.kernels.step_values.StepValues`), then once per step, on the rows read,
    :meth:`pose_gradients` (None when a view's slots did not fit its buffers: they are grown, run the step
    again).
    """

    def __init__(self, dtype=ti.f32) -> None:
        backend = runtime.init()
        if dtype == ti.f64:
            runtime.require_f64("the float64 rasterizer")
        self.dtype = dtype
        # block-per-tile kernels on GPU backends (shared memory does not compile on the CPU)
        self.gpu = raster_gpu.GpuPipeline(dtype) if backend.gpu_kernels else None
        self.k = None if self.gpu else cpu_kernels(dtype)
        self.views: dict[int, View] = {}
        self._zeros: dict[tuple, ti.Ndarray] = {}
        self._scratch: dict[object, ti.Ndarray] = {}
        self.slot_capacity = 0  # slots each view's buffers hold (0: not yet counted)
        self._sized_for = 0  # the Gaussian count the capacity was set for (it grows with them)
        self._own_pose = StepValues(dtype, POSE_COLUMNS)  # the pose row of a checked backward

    @profiling.timed("render forward", phases="timings")
    def forward(
        self, gaussians: DeviceGaussians, camera: Camera, view: int = 0, background=(0.0, 0.0, 0.0),
        timings: dict | None = None, with_colour: bool = True, deferred: bool = False,
    ) -> View:
        """Render ``camera`` into view buffer ``view`` and return it.

        ``timings``: when a dict is given, each phase is synchronised and its seconds added under
        "project", "sort" and "blend" (for benchmarks; costs a few syncs). ``with_colour=False``
        renders depth and alpha only (stage 2): the CPU path skips the colour sums and leaves ``rgb``
        black, and the view's backward takes no colour gradient (GPU backends render colour anyway).
        ``deferred``: no host read (the slot count stays on the device); the view holds the render once
        :meth:`pose_gradients` has taken its backward's row (before that it may be empty)."""
        if gaussians.dtype != self.dtype:
            raise ValueError("gaussians and rasterizer use different float types")
        v = self.views.setdefault(view, View(self.dtype))
        width, height = int(camera.width), int(camera.height)
        v.ensure_images(width, height)
        v.camera, v.background, v.n = camera, np.asarray(background, dtype=np.float64), gaussians.n
        v.with_colour = with_colour
        while True:
            self._render(v, gaussians, camera, background, _PhaseClock(timings), with_colour)
            if deferred and self.slot_capacity > 0:
                v.n_slots = None
                return v
            v.n_slots = v.slot_count()  # a checked forward: the count, read
            if v.n_slots <= v.cap:
                return v
            self._grow(v.n_slots, gaussians.n)

    def pose_gradients(self, rows: np.ndarray) -> np.ndarray | None:
        """The pose gradients (k, 6) float64 in the pose rows (k, POSE_COLUMNS) that k ``backward(...,
        pose_into=)`` calls left and the step read; None when one of those views had more tile slots than its
        buffers held (it rendered nothing): the capacity is then grown, and the step must be run again."""
        rows = np.asarray(rows, np.float64)
        if rows[:, 7].any():
            self._grow(int(rows[:, 6].max()) + 1, max(v.n for v in self.views.values()))
            return None
        return rows[:, :6]

    def _grow(self, slots: int, n: int) -> None:
        """Make room for ``slots`` slots (a view's count) with headroom, for ``n`` Gaussians."""
        self.slot_capacity = max(self.slot_capacity, int(slots * 1.25) + 256)
        self._sized_for = max(self._sized_for, n)

    def _capacity(self, n: int) -> int:
        """Slots per view for ``n`` Gaussians: the capacity, scaled up while the Gaussians outgrow what it was
        set for."""
        if self.slot_capacity and n > self._sized_for:
            self.slot_capacity = -(-self.slot_capacity * n // self._sized_for)
            self._sized_for = n
        return self.slot_capacity

    def _render(self, v: View, gaussians: DeviceGaussians, camera: Camera, background, clock, with_colour: bool):
        """One forward into ``v`` at the current capacity (``v.cap``)."""
        width, height = v.size
        n = gaussians.n
        v.cap = self._capacity(n)
        cam, intr = camera_args(camera, self.dtype)
        bg = ti.Vector([float(b) for b in background], dt=self.dtype)
        if self.gpu is not None:
            self.gpu.forward(v, gaussians, cam, intr, width, height, bg, clock, v.cap)
            return
        v.proj = _grown(v.proj, n, self.dtype, (P_WIDTH,))
        v.rect = _grown(v.rect, n, ti.i32, (4,))
        v.offsets = _grown(v.offsets, n + 1, ti.i32)
        v.chunk_base = _grown(v.chunk_base, n // SCAN_CHUNK + 2, ti.i32)
        p = gaussians.params
        self.k.project_and_count(
            p["means"], p["quats"], p["log_scales"], p["opacity_logits"], p["colors"], n, gaussians.n_sh,
            cam, intr, width, height, v.proj, v.rect, v.offsets, v.chunk_base, gaussians.isotropic,
            gaussians.view_dependent,
        )
        clock("project")
        slots = max(v.cap, 1)
        for name, dtype in (("slot_gid", ti.i32), ("slot_tile", ti.i32), ("keys", ti.i64), ("tmp_keys", ti.i64),
                            ("order", ti.i32)):
            setattr(v, name, _grown(getattr(v, name), slots, dtype))
        v.entries = _grown(v.entries, slots, self.dtype, (E_WIDTH,))
        tiles_x, tiles_y = tiles.tile_grid(width, height)
        n_tiles = tiles_x * tiles_y
        self.k.bin_and_sort(
            n, v.cap, tiles_x, n_tiles, v.proj, v.rect, v.offsets,
            v.slot_gid, v.slot_tile, v.tile_cursor, v.tile_start, v.keys, v.tmp_keys, v.order,
            v.entries,
        )
        clock("sort")
        self.k.blend(
            tiles_x, n_tiles, width, height, v.tile_start, v.entries, bg, self._state(F_WIDTH, width, height),
            v.rgb, v.depth, v.transmittance, v.last, bool(with_colour),
        )
        clock("blend")

    @profiling.timed("render backward")
    def backward(self, gaussians: DeviceGaussians, view: View, d_rgb=None, d_depth=None, d_alpha=None,
                 pose_into: Slot | None = None) -> np.ndarray | None:
        """Accumulate dL/dparams into ``gaussians.grads``; return dL/d(pose) (6,), or with ``pose_into`` (a slot
        of POSE_COLUMNS values) leave it there with the view's slot count and overflow flag (no read) and return
        None."""
        width, height = view.size
        n = gaussians.n
        if n != view.n:
            raise ValueError("the Gaussians changed size since this view was rendered")
        if d_rgb is not None and not view.with_colour:
            raise ValueError("a colour gradient for a view rendered without colour (with_colour=False)")
        d_rgb = self._zero_if_none(d_rgb, (height, width, 3))
        d_depth = self._zero_if_none(d_depth, (height, width))
        d_alpha = self._zero_if_none(d_alpha, (height, width))
        own = self._own_pose
        slot = pose_into or own.rows("pose", 1, POSE_COLUMNS)
        if slot.size != POSE_COLUMNS:
            raise ValueError(f"a pose row of {POSE_COLUMNS} values, not {slot.size}")
        cam, intr = camera_args(view.camera, self.dtype)
        bg = ti.Vector([float(b) for b in view.background], dt=self.dtype)
        if self.gpu is not None:
            self.gpu.backward(view, gaussians, cam, intr, bg, d_rgb, d_depth, d_alpha, slot.values, slot.at)
        else:
            self._backward_cpu(gaussians, view, cam, intr, bg, d_rgb, d_depth, d_alpha, slot.values, slot.at)
        if pose_into is not None:
            return None
        return own.read()["pose"][0, :6]

    def _backward_cpu(self, gaussians, view, cam, intr, bg, d_rgb, d_depth, d_alpha, pose_out, pose_at) -> None:
        width, height = view.size
        n = gaussians.n
        s = self._scratch
        s["slot_grad"] = _grown(s.get("slot_grad"), max(view.cap, 1), self.dtype, (N_SLOT_GRADS,))
        s["pose_part"] = _grown(s.get("pose_part"), n, self.dtype, (6,))
        s["pose_chunks"] = _grown(s.get("pose_chunks"), math.ceil(n / POSE_CHUNK) + 1, self.dtype, (6,))
        tiles_x, tiles_y = tiles.tile_grid(width, height)
        n_tiles = tiles_x * tiles_y
        p, g = gaussians.params, gaussians.grads
        self.k.backward(
            n, gaussians.n_sh, tiles_x, n_tiles, width, height, cam, intr, bg,
            p["means"], p["quats"], p["log_scales"], p["opacity_logits"], p["colors"],
            view.offsets, view.cap, view.tile_start, view.order, view.entries,
            view.transmittance, view.last, d_rgb, d_depth, d_alpha,
            self._state(B_WIDTH, width, height), s["slot_grad"],
            g["means"], g["quats"], g["log_scales"], g["opacity_logits"], g["colors"],
            s["pose_part"], s["pose_chunks"], pose_out, pose_at, gaussians.isotropic, gaussians.view_dependent,
            bool(view.with_colour),
        )

    def _state(self, columns: int, width: int, height: int) -> ti.Ndarray:
        """Per-pixel scratch of the blending passes, shared by all views: flat, ``columns`` values per pixel, each
        tile's TILE x TILE pixels in one contiguous block (``rasterize.pixel_record``)."""
        key = ("state", columns, width, height)
        if key not in self._scratch:
            tiles_x, tiles_y = tiles.tile_grid(width, height)
            self._scratch[key] = ti.ndarray(self.dtype, (tiles_x * tiles_y * TILE * TILE * columns,))
        return self._scratch[key]

    def _zero_if_none(self, arr, shape: tuple):
        if arr is not None:
            if tuple(arr.shape) != shape or arr.dtype != self.dtype:
                raise ValueError(f"image gradient has shape {tuple(arr.shape)} ({arr.dtype}), expected {shape}")
            return arr
        if shape not in self._zeros:
            self._zeros[shape] = ti.ndarray(self.dtype, shape)
            self._zeros[shape].fill(0.0)
        return self._zeros[shape]
