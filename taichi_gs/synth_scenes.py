"""The ray-castable scenes of :mod:`taichi_gs.synth`: a room kind, a seed, and primitives + textures.

Every scene is a closed box seen from inside (walls, floor, ceiling) holding spheres, cylinders and
boxes (:mod:`taichi_gs.kernels.raycast`), with every object kept outside the disc of radius
``CAMERA_DISC_RADIUS_M`` around the centre in which all camera paths run. World y points down; the
floor is at ``y = +room_half[1]``. Kinds, so that a benchmark cannot be tuned to one look:

- ``room``: a 5.6-6.6 m square room whose surfaces all carry photos mixed with value noise, and nine
  spheres, cylinders and boxes around the camera disc (the original generator, unchanged);
- ``office``: random room sizes (4.8-9 m a side), painted walls, and furniture: tables on legs with
  clutter on top, cabinets against the walls, posters;
- ``plain``: planar-dominant and low-texture: plain painted walls, floor and ceiling (a few percent
  of shading noise), flat posters and two boxes the only strong texture;
- ``corridor``: 3.4-3.8 m wide and 9-12 m long; the ends lie beyond the sensor's range, cabinets and
  doors line the long walls.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from .choices import SCENES

TEXTURE_SIZE = 256
WALL_TILE_M = 2.0
OBJECT_TILE_M = 0.8
CAMERA_DISC_RADIUS_M = 1.15  # every camera path stays within this distance of the room's centre
OBJECT_KEEP_OUT_M = 1.5  # objects stay this far from the centre
N_OBJECTS = 9
PHOTOS = (
    "astronaut", "coffee", "chelsea", "rocket", "immunohistochemistry", "hubble_deep_field", "retina",
    "colorwheel", "brick", "grass", "gravel", "camera", "moon", "coins", "cell", "page", "text",
)
PAINT_CONTRAST = 0.08  # plain surfaces: shading noise of +-4% around the paint colour
POSTER_DEPTH_M = 0.005
TABLE_HEIGHT_M = 0.75


@dataclass(frozen=True)
class Scene:
    """Ray-castable room: primitive rows (see :mod:`taichi_gs.kernels.raycast`) and textures."""

    prims: np.ndarray  # (n, PRIM_COLUMNS) float32
    textures: np.ndarray  # (n_textures, S, S, 3) float32 in [0, 1]
    room_half: np.ndarray  # (3,) half extents of the room, centred at the world origin


@functools.lru_cache(maxsize=None)
def _photo(name: str) -> np.ndarray:
    """A bundled scikit-image photo as a square float32 RGB texture."""
    from skimage import data

    image = np.asarray(getattr(data, name)())
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    image = image[..., :3].astype(np.float32) / 255.0
    h, w = image.shape[:2]
    side = min(h, w)
    top, left = (h - side) // 2, (w - side) // 2
    square = image[top:top + side, left:left + side]
    return cv2.resize(square, (TEXTURE_SIZE, TEXTURE_SIZE), interpolation=cv2.INTER_AREA)


def _value_noise(rng: np.random.Generator) -> np.ndarray:
    """Smooth multi-octave noise stretched to [0, 1] on the texture grid (coarse blobs to ~4-texel grain)."""
    noise = np.zeros((TEXTURE_SIZE, TEXTURE_SIZE), np.float32)
    for cells, weight in ((4, 0.45), (16, 0.3), (64, 0.25)):
        grid = rng.random((cells, cells)).astype(np.float32)
        noise += weight * cv2.resize(grid, (TEXTURE_SIZE, TEXTURE_SIZE), interpolation=cv2.INTER_CUBIC)
    return (noise - noise.min()) / (noise.max() - noise.min())


def _surface_texture(name: str, rng: np.random.Generator) -> np.ndarray:
    """A photo tinted and mixed with procedural noise, so even its flat or dark parts carry detail."""
    photo = _photo(name) * rng.uniform(0.6, 1.0, 3).astype(np.float32)
    noise = _value_noise(rng)[..., None]
    tint = rng.uniform(0.3, 1.0, 3).astype(np.float32)
    return np.clip(0.7 * photo * (0.75 + 0.5 * noise) + 0.3 * noise * tint, 0.0, 1.0)


def _paint_texture(rng: np.random.Generator) -> np.ndarray:
    """A painted surface: one light colour with faint shading noise (little to track)."""
    colour = rng.uniform(0.45, 0.9, 3).astype(np.float32)
    noise = _value_noise(rng)[..., None]
    return np.clip(colour * (1.0 - 0.5 * PAINT_CONTRAST + PAINT_CONTRAST * noise), 0.0, 1.0)


def _prim_row(kind: int, centre, half, tile: float, textures, yaw: float = 0.0) -> np.ndarray:
    from .kernels.raycast import PRIM_COLUMNS

    row = np.zeros(PRIM_COLUMNS, np.float32)
    row[0] = kind
    row[1:4] = centre
    row[4:7] = half
    row[7:9] = math.cos(yaw), math.sin(yaw)
    row[9] = tile
    row[10] = max(2, 2 * round(math.pi * half[0] / tile))  # even tile count around the axis
    row[11:17] = textures
    return row


def _bearing(angle: float) -> np.ndarray:
    """Unit (x, z) direction of a bearing from the room's centre."""
    return np.array([math.sin(angle), math.cos(angle)])


def _distance_range(direction: np.ndarray, reach: float, room_half: np.ndarray) -> tuple[float, float]:
    """Nearest and farthest distance along ``direction`` at which an object of horizontal ``reach``
    stays clear of the camera disc and inside the walls."""
    near = OBJECT_KEEP_OUT_M + reach
    far = min((room_half[0] - 0.05 - reach) / max(abs(direction[0]), 1e-6),
              (room_half[2] - 0.05 - reach) / max(abs(direction[1]), 1e-6))
    return near, max(near, far)


def _fitted(half: np.ndarray, direction: np.ndarray, room_half: np.ndarray) -> np.ndarray:
    """Half extents of a box, shrunk where needed so that its footprint (any yaw) fits between the
    camera keep-out and the walls along ``direction``."""
    _, wall = _distance_range(direction, 0.0, room_half)
    reach = float(np.hypot(half[0], half[2]))
    return half * min(1.0, (wall - OBJECT_KEEP_OUT_M) / (2.0 * reach))


def _object_row(kind: int, angle: float, room_half: np.ndarray, texture: int, rng: np.random.Generator) -> np.ndarray:
    """One object on a bearing from the centre, kept out of the camera disc and inside the room."""
    from .kernels.raycast import CYLINDER, SPHERE

    floor_y = room_half[1]
    if kind == SPHERE:
        r = rng.uniform(0.2, 0.42)
        half, reach, yaw = np.array([r, r, r]), r, 0.0
        y = rng.uniform(-0.6, floor_y - r)
    elif kind == CYLINDER:
        r, h = rng.uniform(0.15, 0.32), rng.uniform(0.4, 1.0)
        half, reach, yaw = np.array([r, h, r]), r, 0.0
        y = floor_y - h
    else:
        half = rng.uniform([0.18, 0.15, 0.18], [0.4, 0.45, 0.4])
        reach, yaw = float(np.hypot(half[0], half[2])), rng.uniform(0.0, math.pi)
        y = rng.uniform(-0.5, floor_y - half[1])
    direction = _bearing(angle)
    distance = rng.uniform(*_distance_range(direction, reach, room_half))
    centre = [distance * direction[0], y, distance * direction[1]]
    return _prim_row(kind, centre, half, OBJECT_TILE_M, [texture] * 6, yaw)


class _Builder:
    """Collects textures and primitive rows of one scene."""

    def __init__(self, rng: np.random.Generator, room_half: np.ndarray) -> None:
        self.rng, self.room_half = rng, room_half
        self.textures: list[np.ndarray] = []
        self.rows: list[np.ndarray] = []

    def texture(self, image: np.ndarray) -> int:
        self.textures.append(image)
        return len(self.textures) - 1

    def photo(self) -> int:
        return self.texture(_surface_texture(PHOTOS[self.rng.integers(len(PHOTOS))], self.rng))

    def paint(self) -> int:
        return self.texture(_paint_texture(self.rng))

    def room(self, faces: list[int]) -> None:
        from .kernels.raycast import ROOM

        self.rows.append(_prim_row(ROOM, [0.0, 0.0, 0.0], self.room_half, WALL_TILE_M, faces))

    def box(self, centre, half, yaw: float, texture: int, tile: float = OBJECT_TILE_M) -> None:
        from .kernels.raycast import BOX

        self.rows.append(_prim_row(BOX, centre, half, tile, [texture] * 6, yaw))

    def cylinder(self, centre, radius: float, half_height: float, texture: int) -> None:
        from .kernels.raycast import CYLINDER

        self.rows.append(_prim_row(CYLINDER, centre, [radius, half_height, radius], OBJECT_TILE_M, [texture] * 6))

    def poster(self, wall: int, along: float, y: float, half_w: float, half_h: float, texture: int) -> None:
        """A flat picture ``POSTER_DEPTH_M`` deep on wall 0 (-x), 1 (+x), 2 (-z) or 3 (+z)."""
        axis, sign = (0, 2)[wall // 2], (-1.0, 1.0)[wall % 2]
        centre = np.zeros(3)
        centre[axis] = sign * (self.room_half[axis] - POSTER_DEPTH_M)
        centre[2 - axis] = along
        centre[1] = y
        half = np.array([half_w, half_h, half_w])
        half[axis] = POSTER_DEPTH_M
        self.box(centre, half, 0.0, texture, tile=2.0 * max(half_w, half_h))

    def scene(self) -> Scene:
        return Scene(np.stack(self.rows), np.stack(self.textures), self.room_half)


def _room(rng: np.random.Generator) -> Scene:
    """The original room (its random stream is kept so existing seeds render as before)."""
    from .kernels.raycast import BOX, CYLINDER, SPHERE

    room_half = np.array([rng.uniform(2.8, 3.3), rng.uniform(1.3, 1.45), rng.uniform(2.8, 3.3)])
    n_surfaces = 6 + N_OBJECTS
    names = [PHOTOS[i % len(PHOTOS)] for i in rng.permutation(max(n_surfaces, len(PHOTOS)))[:n_surfaces]]
    textures = np.stack([_surface_texture(name, rng) for name in names])
    builder = _Builder(rng, room_half)
    builder.textures = list(textures)
    builder.room(list(range(6)))
    kinds = rng.permutation([SPHERE, CYLINDER, BOX] * (N_OBJECTS // 3))
    sector = 2.0 * math.pi / N_OBJECTS
    for i, kind in enumerate(kinds):
        angle = i * sector + rng.uniform(-0.3, 0.3) * sector
        builder.rows.append(_object_row(int(kind), angle, room_half, 6 + i, rng))
    return builder.scene()


def _table(b: _Builder, angle: float) -> None:
    """A table on four legs on a bearing, sometimes with a vase on top."""
    rng, floor_y = b.rng, b.room_half[1]
    direction = _bearing(angle)
    half_top = _fitted(np.array([rng.uniform(0.35, 0.7), 0.02, rng.uniform(0.3, 0.45)]), direction, b.room_half)
    yaw = angle + rng.uniform(-0.3, 0.3)
    distance = rng.uniform(*_distance_range(direction, float(np.hypot(half_top[0], half_top[2])), b.room_half))
    x, z = distance * direction
    top_y = floor_y - TABLE_HEIGHT_M
    wood = b.photo()
    b.box([x, top_y, z], half_top, yaw, wood)
    leg_half = 0.5 * (TABLE_HEIGHT_M - 2 * half_top[1])
    c, s = math.cos(yaw), math.sin(yaw)
    for ox in (-1.0, 1.0):
        for oz in (-1.0, 1.0):
            lx, lz = ox * (half_top[0] - 0.04), oz * (half_top[2] - 0.04)
            b.box([x + c * lx + s * lz, floor_y - leg_half, z - s * lx + c * lz], [0.025, leg_half, 0.025], yaw, wood)
    if rng.random() < 0.6:
        radius, half_h = rng.uniform(0.05, 0.12), rng.uniform(0.08, 0.2)
        b.cylinder([x, top_y - half_top[1] - half_h, z], radius, half_h, b.photo())


def _cabinet(b: _Builder, angle: float, size_scale: float = 1.0) -> None:
    """A tall box standing on the floor against the wall on a bearing, facing the centre."""
    rng, floor_y = b.rng, b.room_half[1]
    direction = _bearing(angle)
    half = np.array([rng.uniform(0.3, 0.6), rng.uniform(0.5, 0.95), rng.uniform(0.18, 0.3)]) * size_scale
    half[[0, 2]] = _fitted(half, direction, b.room_half)[[0, 2]]
    _, far = _distance_range(direction, float(np.hypot(half[0], half[2])), b.room_half)
    x, z = far * direction
    b.box([x, floor_y - half[1], z], half, angle, b.photo())


def _office(rng: np.random.Generator) -> Scene:
    room_half = np.array([rng.uniform(2.4, 4.5), rng.uniform(1.2, 1.6), rng.uniform(2.4, 4.5)])
    b = _Builder(rng, room_half)
    b.room([b.paint(), b.paint(), b.paint(), b.photo(), b.paint(), b.paint()])  # floor (+y) textured
    n = int(rng.integers(5, 9))
    for i in range(n):
        angle = (i + rng.uniform(-0.25, 0.25)) * 2.0 * math.pi / n
        (_table if rng.random() < 0.5 else _cabinet)(b, angle)
    for wall in rng.choice(4, size=2, replace=False):
        along = rng.uniform(-0.5, 0.5) * room_half[2 - (0, 2)[wall // 2]]
        b.poster(int(wall), along, rng.uniform(-0.6, -0.2), rng.uniform(0.3, 0.6), rng.uniform(0.25, 0.45), b.photo())
    return b.scene()


def _plain(rng: np.random.Generator) -> Scene:
    room_half = np.array([rng.uniform(2.6, 3.6), rng.uniform(1.25, 1.5), rng.uniform(2.6, 3.6)])
    b = _Builder(rng, room_half)
    b.room([b.paint() for _ in range(6)])
    for wall in rng.choice(4, size=2, replace=False):
        along = rng.uniform(-0.4, 0.4) * room_half[2 - (0, 2)[wall // 2]]
        b.poster(int(wall), along, rng.uniform(-0.5, -0.1), rng.uniform(0.35, 0.7), rng.uniform(0.3, 0.5), b.photo())
    for angle in rng.uniform(0.0, 2.0 * math.pi) + np.array([0.0, math.pi]) + rng.uniform(-0.5, 0.5, 2):
        _cabinet(b, float(angle), size_scale=0.8)
    return b.scene()


def _corridor(rng: np.random.Generator) -> Scene:
    room_half = np.array([rng.uniform(1.7, 1.9), rng.uniform(1.25, 1.45), rng.uniform(4.5, 6.0)])
    b = _Builder(rng, room_half)
    wall = b.paint()
    b.room([wall, wall, b.paint(), b.photo(), b.photo(), b.photo()])  # long walls painted, floor and ends textured
    floor_y = room_half[1]
    for side in (-1.0, 1.0):
        z = -room_half[2] + rng.uniform(0.2, 0.8)
        while True:
            width = rng.uniform(0.35, 0.6)
            centre_z = z + width
            if centre_z + width > room_half[2] - 0.1:
                break
            if rng.random() < 0.65:  # a door: flat on the wall, so it may stand anywhere
                b.box([side * (room_half[0] - POSTER_DEPTH_M), floor_y - 1.0, centre_z],
                      [POSTER_DEPTH_M, 1.0, width], 0.0, b.photo(), tile=1.0)
            elif abs(centre_z) - width > OBJECT_KEEP_OUT_M:  # a cabinet, clear of the camera disc
                depth, height = rng.uniform(0.2, 0.35), rng.uniform(0.4, 0.9)
                b.box([side * (room_half[0] - depth), floor_y - height, centre_z], [depth, height, width], 0.0,
                      b.photo())
            z += 2.0 * width + rng.uniform(0.3, 1.0)
    return b.scene()


_BUILDERS = {"room": _room, "office": _office, "plain": _plain, "corridor": _corridor}


@functools.lru_cache(maxsize=8)
def build_scene(seed: int, kind: str = "room") -> Scene:
    """The scene of a kind for a seed (sizes, placement, photos and noise all seeded)."""
    if kind not in _BUILDERS:
        raise ValueError(f"unknown scene {kind!r}: choose one of {', '.join(SCENES)}")
    salt = [seed, 0x5CE7E] if kind == "room" else [seed, 0x5CE7E, SCENES.index(kind)]
    return _BUILDERS[kind](np.random.default_rng(salt))
