"""Exact ray casting of the synthetic room used by :mod:`taichi_gs.synth`.

The scene is a list of primitives, one row of ``PRIM_COLUMNS`` float32 values each:

- ``0`` kind: ``ROOM`` (seen from inside), ``SPHERE``, ``CYLINDER`` (vertical, capped) or ``BOX``
  (turned by a yaw angle about the world y axis);
- ``1:4`` centre (world); ``4:7`` half extents (sphere: r, r, r; cylinder: r, half height, r);
- ``7, 8`` cos and sin of the yaw (room, sphere and cylinder: 1, 0);
- ``9`` texture tile size in metres; ``10`` tiles around a sphere or cylinder (an even number, so
  mirrored tiling closes without a seam);
- ``11:17`` texture index per face ``-x, +x, -y, +y, -z, +z`` (spheres and cylinders use ``11``).

Textures are mirrored-repeat tiles sampled bilinearly. Pixel (u, v) looks along the camera ray
``((u - cx) / fx, (v - cy) / fy, 1)``, so the ray parameter of a hit is its camera z-depth.
"""


import numpy as np
import taichi as ti

from . import runtime

ROOM, SPHERE, CYLINDER, BOX = 0, 1, 2, 3
PRIM_COLUMNS = 17
_FAR = 1e30
_EPS = 1e-5
_TINY = 1e-12

vec2 = ti.math.vec2
vec3 = ti.math.vec3


@ti.func
def _slab(o: vec3, d: vec3, lo: vec3, hi: vec3) -> vec2:
    """Entry and exit ray parameters of an axis-aligned box (entry > exit: missed)."""
    t_in, t_out = -_FAR, _FAR
    for i in ti.static(range(3)):
        di = d[i]
        if ti.abs(di) < _TINY:
            di = _TINY
        t1 = (lo[i] - o[i]) / di
        t2 = (hi[i] - o[i]) / di
        t_in = ti.max(t_in, ti.min(t1, t2))
        t_out = ti.min(t_out, ti.max(t1, t2))
    return vec2(t_in, t_out)


@ti.func
def _unyaw(prims: ti.types.ndarray(ndim=2), row: ti.i32, x: vec3) -> vec3:
    """A world vector in the primitive's axes (its yaw undone)."""
    c, s = prims[row, 7], prims[row, 8]
    return vec3(c * x.x - s * x.z, x.y, s * x.x + c * x.z)


@ti.func
def _local_point(prims: ti.types.ndarray(ndim=2), row: ti.i32, p: vec3) -> vec3:
    """A world point in the primitive's frame (centre at the origin, yaw undone)."""
    return _unyaw(prims, row, p - vec3(prims[row, 1], prims[row, 2], prims[row, 3]))


@ti.func
def _half(prims: ti.types.ndarray(ndim=2), row: ti.i32) -> vec3:
    return vec3(prims[row, 4], prims[row, 5], prims[row, 6])


@ti.func
def _hit_sphere(o: vec3, d: vec3, r: ti.f32) -> ti.f32:
    t = _FAR
    a, b, c = d.dot(d), o.dot(d), o.dot(o) - r * r
    disc = b * b - a * c
    if disc > 0.0:
        root = (-b - ti.sqrt(disc)) / a
        if root > _EPS:
            t = root
    return t


@ti.func
def _hit_cylinder(o: vec3, d: vec3, r: ti.f32, h: ti.f32) -> ti.f32:
    t = _FAR
    a = d.x * d.x + d.z * d.z
    b = o.x * d.x + o.z * d.z
    c = o.x * o.x + o.z * o.z - r * r
    disc = b * b - a * c
    if disc > 0.0 and a > _TINY:
        root = (-b - ti.sqrt(disc)) / a
        if root > _EPS and ti.abs(o.y + root * d.y) <= h:
            t = root
    if ti.abs(d.y) > _TINY:
        for side in ti.static((-1.0, 1.0)):
            root = (side * h - o.y) / d.y
            px, pz = o.x + root * d.x, o.z + root * d.z
            if root > _EPS and px * px + pz * pz <= r * r:
                t = ti.min(t, root)
    return t


@ti.func
def _hit(prims: ti.types.ndarray(ndim=2), row: ti.i32, o: vec3, d: vec3) -> ti.f32:
    """Ray parameter of the first hit with one primitive, ``_FAR`` when missed."""
    kind = ti.cast(prims[row, 0], ti.i32)
    lo, ld = _local_point(prims, row, o), _unyaw(prims, row, d)
    half = _half(prims, row)
    t = _FAR
    if kind == ROOM:
        t = _slab(lo, ld, -half, half)[1]
    elif kind == SPHERE:
        t = _hit_sphere(lo, ld, half.x)
    elif kind == CYLINDER:
        t = _hit_cylinder(lo, ld, half.x, half.y)
    else:
        span = _slab(lo, ld, -half, half)
        if span[0] <= span[1] and span[0] > _EPS:
            t = span[0]
    return t


@ti.func
def _face_coords(q: vec3, half: vec3, prims: ti.types.ndarray(ndim=2), row: ti.i32) -> vec3:
    """(u, v) in metres on the box face holding local point ``q``, and that face's texture."""
    ratio = ti.abs(q) / half
    axis = 0
    if ratio.y >= ratio.x and ratio.y >= ratio.z:
        axis = 1
    elif ratio.z >= ratio.x and ratio.z >= ratio.y:
        axis = 2
    uv = vec2(q.z, q.y)
    if axis == 1:
        uv = vec2(q.x, q.z)
    elif axis == 2:
        uv = vec2(q.x, q.y)
    positive = 1 if q[axis] > 0.0 else 0
    return vec3(uv.x, uv.y, prims[row, 11 + 2 * axis + positive])


@ti.func
def _surface_coords(prims: ti.types.ndarray(ndim=2), row: ti.i32, p: vec3) -> vec3:
    """Texture coordinates (in tiles) of a surface point and the texture index."""
    kind = ti.cast(prims[row, 0], ti.i32)
    q = _local_point(prims, row, p)
    half = _half(prims, row)
    tile, around = prims[row, 9], prims[row, 10]
    angle = (ti.atan2(q.z, q.x) / (2.0 * ti.math.pi) + 0.5) * around
    coords = vec3(0.0, 0.0, prims[row, 11])
    if kind == SPHERE:
        polar = ti.acos(ti.math.clamp(q.y / half.x, -1.0, 1.0))
        coords = vec3(angle, polar * half.x / tile, prims[row, 11])
    elif kind == CYLINDER:
        radial = ti.sqrt(q.x * q.x + q.z * q.z)
        if ti.abs(ti.abs(q.y) - half.y) < ti.abs(radial - half.x):
            coords = vec3(q.x / tile, q.z / tile, prims[row, 11])
        else:
            coords = vec3(angle, q.y / tile, prims[row, 11])
    else:
        face = _face_coords(q, half, prims, row)
        coords = vec3(face.x / tile, face.y / tile, face.z)
    return coords


@ti.func
def _mirror(x: ti.f32) -> ti.f32:
    """Mirrored repeat of a tile coordinate into [0, 1]."""
    m = x - 2.0 * ti.floor(x / 2.0)
    return 2.0 - m if m > 1.0 else m


@ti.func
def _sample(textures: ti.types.ndarray(ndim=4), coords: vec3) -> vec3:
    """Bilinear lookup in a mirrored-repeat texture."""
    size = textures.shape[1]
    tex = ti.cast(coords.z, ti.i32)
    x = _mirror(coords.x) * (size - 1)
    y = _mirror(coords.y) * (size - 1)
    x0 = ti.min(ti.cast(ti.floor(x), ti.i32), size - 2)
    y0 = ti.min(ti.cast(ti.floor(y), ti.i32), size - 2)
    fx, fy = x - x0, y - y0
    out = vec3(0.0)
    for ch in ti.static(range(3)):
        top = (1.0 - fx) * textures[tex, y0, x0, ch] + fx * textures[tex, y0, x0 + 1, ch]
        bottom = (1.0 - fx) * textures[tex, y0 + 1, x0, ch] + fx * textures[tex, y0 + 1, x0 + 1, ch]
        out[ch] = (1.0 - fy) * top + fy * bottom
    return out


@ti.kernel
def _render(
    poses: ti.types.ndarray(ndim=3),
    fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32,
    prims: ti.types.ndarray(ndim=2),
    textures: ti.types.ndarray(ndim=4),
    rgb: ti.types.ndarray(ndim=3),
    depth: ti.types.ndarray(ndim=2),
):
    n_poses, n_prims = poses.shape[0], prims.shape[0]
    for v, u in ti.ndrange(rgb.shape[0], rgb.shape[1]):
        cam = vec3((u - cx) / fx, (v - cy) / fy, 1.0)
        acc = vec3(0.0)
        for k in range(n_poses):
            o = vec3(poses[k, 0, 3], poses[k, 1, 3], poses[k, 2, 3])
            d = vec3(0.0)
            for i in ti.static(range(3)):
                d[i] = poses[k, i, 0] * cam.x + poses[k, i, 1] * cam.y + poses[k, i, 2]
            best_t, best_row = _FAR, -1
            for row in range(n_prims):
                t = _hit(prims, row, o, d)
                if t < best_t:
                    best_t, best_row = t, row
            if best_row >= 0:
                acc += _sample(textures, _surface_coords(prims, best_row, o + best_t * d))
            if k == 0:
                depth[v, u] = ti.select(best_row >= 0, best_t, 0.0)
        rgb[v, u, 0] = acc.x / n_poses
        rgb[v, u, 1] = acc.y / n_poses
        rgb[v, u, 2] = acc.z / n_poses


def render(
    poses: np.ndarray, K: np.ndarray, width: int, height: int, prims: np.ndarray, textures: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mean colour over camera-to-world ``poses`` (k x 4 x 4) and the z-depth seen from ``poses[0]``.

    Returns float32 ``rgb`` (H x W x 3) and ``depth`` (H x W, metres, 0 where nothing is hit).
    """
    runtime.init()
    rgb = np.zeros((height, width, 3), np.float32)
    depth = np.zeros((height, width), np.float32)
    _render(
        np.ascontiguousarray(poses, np.float32),
        float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
        np.ascontiguousarray(prims, np.float32),
        np.ascontiguousarray(textures, np.float32),
        rgb,
        depth,
    )
    return rgb, depth
