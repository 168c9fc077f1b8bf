"""Adam on device parameter buffers (one fused kernel launch per parameter tensor)."""

import functools
import math
from types import SimpleNamespace

import taichi as ti


@functools.cache
def _kernels(dt) -> SimpleNamespace:
    """Adam kernels for (N,), (N, C) and (N, A, B) parameters: one loop over the N rows with the rest
    inside (a flat index over every element would cost integer divisions per element on the CPU)."""

    @ti.func
    def update(param: ti.template(), grad: ti.template(), m: ti.template(), v: ti.template(), index, lr_t, beta1,
               beta2, eps_t):
        g = grad[index]
        m[index] = beta1 * m[index] + (1 - beta1) * g
        v[index] = beta2 * v[index] + (1 - beta2) * g * g
        param[index] = param[index] - lr_t * m[index] / (ti.sqrt(v[index]) + eps_t)

    def arr(ndim):
        return ti.types.ndarray(dtype=dt, ndim=ndim)

    @ti.kernel
    def adam_1d(param: arr(1), grad: arr(1), m: arr(1), v: arr(1), n: ti.i32, lr_t: dt, beta1: dt, beta2: dt,
                eps_t: dt):
        for r in range(n):
            update(param, grad, m, v, r, lr_t, beta1, beta2, eps_t)

    @ti.kernel
    def adam_2d(param: arr(2), grad: arr(2), m: arr(2), v: arr(2), n: ti.i32, lr_t: dt, beta1: dt, beta2: dt,
                eps_t: dt):
        for r in range(n):
            for c in range(param.shape[1]):
                update(param, grad, m, v, (r, c), lr_t, beta1, beta2, eps_t)

    @ti.kernel
    def adam_3d(param: arr(3), grad: arr(3), m: arr(3), v: arr(3), n: ti.i32, lr_t: dt, beta1: dt, beta2: dt,
                eps_t: dt):
        for r in range(n):
            for a in range(param.shape[1]):
                for b in range(param.shape[2]):
                    update(param, grad, m, v, (r, a, b), lr_t, beta1, beta2, eps_t)

    return SimpleNamespace(adam_step={1: adam_1d, 2: adam_2d, 3: adam_3d})


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

    def step(self, n: int | None = None) -> None:
        """One Adam update of every parameter in ``lrs``."""
        self.t += 1
        c1 = 1 - self.beta1**self.t
        c2 = 1 - self.beta2**self.t
        for name, lr in self.lrs.items():
            p = self.params[name]
            k = _kernels(p.dtype)
            m, v = self.moments[name]
            rows = p.shape[0] if n is None else n
            # lr * m_hat / (sqrt(v_hat) + eps) == (lr sqrt(c2) / c1) * m / (sqrt(v) + eps sqrt(c2))
            k.adam_step[len(p.shape)](p, self.grads[name], m, v, rows, lr * math.sqrt(c2) / c1, self.beta1,
                                      self.beta2, self.eps * math.sqrt(c2))
