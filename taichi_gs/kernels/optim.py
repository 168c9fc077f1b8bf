"""Adam on device parameter buffers (one fused kernel launch per parameter tensor)."""

import functools
import math
from types import SimpleNamespace

import taichi as ti


@functools.cache
def _kernels(dt) -> SimpleNamespace:
    @ti.func
    def update(param: ti.template(), grad: ti.template(), m: ti.template(), v: ti.template(), index, lr_t, beta1,
               beta2, eps_t):
        g = grad[index]
        m[index] = beta1 * m[index] + (1 - beta1) * g
        v[index] = beta2 * v[index] + (1 - beta2) * g * g
        param[index] = param[index] - lr_t * m[index] / (ti.sqrt(v[index]) + eps_t)

    arr = ti.types.ndarray(dtype=dt)

    @ti.kernel
    def adam_step(param: arr, grad: arr, m: arr, v: arr, n: ti.i32, lr_t: dt, beta1: dt, beta2: dt, eps_t: dt):
        # one loop over the first n rows with the rest inside, by rank (compiled per rank): a flat index over
        # every element would cost integer divisions per element on the CPU backend
        for r in range(n):
            if ti.static(len(param.shape) == 1):
                update(param, grad, m, v, r, lr_t, beta1, beta2, eps_t)
            elif ti.static(len(param.shape) == 2):
                for c in range(param.shape[1]):
                    update(param, grad, m, v, (r, c), lr_t, beta1, beta2, eps_t)
            else:
                for a in range(param.shape[1]):
                    for b in range(param.shape[2]):
                        update(param, grad, m, v, (r, a, b), lr_t, beta1, beta2, eps_t)

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
