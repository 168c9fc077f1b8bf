"""Adam on device parameter buffers: one kernel launch updates up to five parameter tensors (the
Gaussians' means, rotations, scales, opacities and colours) in one loop over chunks of their rows."""

import functools
import math
from types import SimpleNamespace

import taichi as ti

from .. import profiling
from . import runtime

SLOTS = 5  # parameter tensors per launch; a step over fewer fills the rest with an empty placeholder
CPU_CHUNK_ROWS = 64  # rows a loop index updates in order on the CPU (a loop index per row costs a call per row;
# 256 measured slower on four threads: docs/notebook/launch-budget.md)


@functools.cache
def _kernels(dt) -> SimpleNamespace:
    @ti.func
    def update(param: ti.template(), grad: ti.template(), m: ti.template(), v: ti.template(), index, lr_t, betas,
               eps_t):
        # every read before the first write: a write between reads makes the compiler reload each array's address
        g, m_old, v_old, p_old = grad[index], m[index], v[index], param[index]
        # betas: (beta1, 1 - beta1, beta2, 1 - beta2), the complements from the host: with 1 - beta written here the
        # compiled update (fast math) was off the formula by up to 5e-5 of v after one step, as if it had cancelled
        m_new = betas[0] * m_old + betas[1] * g
        v_new = betas[2] * v_old + betas[3] * g * g
        m[index] = m_new
        v[index] = v_new
        param[index] = p_old - lr_t * m_new / (ti.sqrt(v_new) + eps_t)

    @ti.func
    def update_rows(param: ti.template(), grad: ti.template(), m: ti.template(), v: ti.template(), first, end,
                    lr_t, betas, eps_t):
        # rows first .. end - 1 in a serial loop inside one task (not a task per row); a row's elements inside,
        # by rank (compiled per rank): a flat index over every element would cost integer divisions per element
        for r in range(first, end):
            if ti.static(len(param.shape) == 1):
                update(param, grad, m, v, r, lr_t, betas, eps_t)
            elif ti.static(len(param.shape) == 2):
                for c in range(param.shape[1]):
                    update(param, grad, m, v, (r, c), lr_t, betas, eps_t)
            else:
                for a in range(param.shape[1]):
                    for b in range(param.shape[2]):
                        update(param, grad, m, v, (r, a, b), lr_t, betas, eps_t)

    arr = ti.types.ndarray(dtype=dt)
    per_slot = ti.types.vector(SLOTS, dt)
    vec4 = ti.types.vector(4, dt)
    rows_per_slot = ti.types.vector(SLOTS, ti.i32)

    @ti.kernel
    def adam_step(p0: arr, g0: arr, m0: arr, v0: arr, p1: arr, g1: arr, m1: arr, v1: arr,
                  p2: arr, g2: arr, m2: arr, v2: arr, p3: arr, g3: arr, m3: arr, v3: arr,
                  p4: arr, g4: arr, m4: arr, v4: arr,
                  rows: rows_per_slot, n: ti.i32, chunk_rows: ti.i32, lr_t: per_slot, betas: vec4, eps_t: dt):
        for chunk in range((n + chunk_rows - 1) // chunk_rows):
            first = chunk * chunk_rows
            update_rows(p0, g0, m0, v0, first, ti.min(rows[0], first + chunk_rows), lr_t[0], betas, eps_t)
            update_rows(p1, g1, m1, v1, first, ti.min(rows[1], first + chunk_rows), lr_t[1], betas, eps_t)
            update_rows(p2, g2, m2, v2, first, ti.min(rows[2], first + chunk_rows), lr_t[2], betas, eps_t)
            update_rows(p3, g3, m3, v3, first, ti.min(rows[3], first + chunk_rows), lr_t[3], betas, eps_t)
            update_rows(p4, g4, m4, v4, first, ti.min(rows[4], first + chunk_rows), lr_t[4], betas, eps_t)

    return SimpleNamespace(adam_step=adam_step, per_slot=per_slot, rows_per_slot=rows_per_slot, vec4=vec4)


@functools.cache
def _placeholder(dt) -> ti.Ndarray:
    """A one-element tensor standing in for an unused slot (0 rows: never read)."""
    return ti.ndarray(dt, (1,))


class Adam:
    """Adam (Kingma & Ba, with bias correction) over named ndarrays sharing their first axis.

    ``params`` and ``grads`` map names to ndarrays (e.g. ``DeviceGaussians.params`` / ``.grads``);
    ``lrs`` maps the names to optimise to learning rates (others are left alone). ``step(n)``
    updates the first n rows (default: all). Moments live on device.
    """

    def __init__(self, params: dict, grads: dict, lrs: dict[str, float], betas=(0.9, 0.999), eps: float = 1e-15):
        self.params, self.grads, self.lrs = params, grads, dict(lrs)
        self.beta1, self.beta2 = betas
        self.eps = eps
        self.t = 0
        self.moments = {}
        for name in self.lrs:
            p = params[name]
            m, v = ti.ndarray(p.dtype, p.shape), ti.ndarray(p.dtype, p.shape)
            m.fill(0.0)
            v.fill(0.0)
            self.moments[name] = (m, v)

    @profiling.timed("Adam (Gaussians)")
    def step(self, n: int | None = None) -> None:
        """One Adam update of every parameter in ``lrs``."""
        self.t += 1
        c1 = 1 - self.beta1**self.t
        c2 = 1 - self.beta2**self.t
        names = list(self.lrs)
        for first in range(0, len(names), SLOTS):
            self._launch(names[first:first + SLOTS], n, c1, c2)

    def _launch(self, names: list[str], n: int | None, c1: float, c2: float) -> None:
        """One kernel launch over the rows of up to :data:`SLOTS` parameters."""
        dt = self.params[names[0]].dtype
        k = _kernels(dt)
        tensors, rows, lrs = [], [], []
        for name in names:
            p = self.params[name]
            m, v = self.moments[name]
            tensors += [p, self.grads[name], m, v]
            rows.append(p.shape[0] if n is None else n)
            # lr * m_hat / (sqrt(v_hat) + eps) == (lr sqrt(c2) / c1) * m / (sqrt(v) + eps sqrt(c2))
            lrs.append(self.lrs[name] * math.sqrt(c2) / c1)
        unused = SLOTS - len(names)
        tensors += [_placeholder(dt)] * (4 * unused)
        rows += [0] * unused
        lrs += [0.0] * unused
        chunk_rows = CPU_CHUNK_ROWS if runtime.current().arch == "cpu" else 1  # GPUs: a thread per row
        betas = k.vec4(self.beta1, 1 - self.beta1, self.beta2, 1 - self.beta2)
        k.adam_step(*tensors, k.rows_per_slot(rows), max(rows), chunk_rows, k.per_slot(lrs), betas,
                    self.eps * math.sqrt(c2))
