"""Adam on device parameter buffers (one fused kernel launch per parameter tensor)."""

import functools
import math
from types import SimpleNamespace

import taichi as ti


@functools.cache
def _kernels(dt) -> SimpleNamespace:
    arr = ti.types.ndarray(dtype=dt)

    @ti.kernel
    def adam_step(param: arr, grad: arr, m: arr, v: arr, n: ti.i32, lr_t: dt, beta1: dt, beta2: dt, eps_t: dt):
        for I in ti.grouped(param):
            if I[0] < n:
                g = grad[I]
                m[I] = beta1 * m[I] + (1 - beta1) * g
                v[I] = beta2 * v[I] + (1 - beta2) * g * g
                param[I] = param[I] - lr_t * m[I] / (ti.sqrt(v[I]) + eps_t)

    return SimpleNamespace(adam_step=adam_step)


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
            k.adam_step(p, self.grads[name], m, v, rows, lr * math.sqrt(c2) / c1, self.beta1, self.beta2,
                        self.eps * math.sqrt(c2))
