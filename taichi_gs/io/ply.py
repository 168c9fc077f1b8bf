"""PLY files: coloured point clouds (xyz + uchar rgb) and the standard 3D Gaussian Splatting layout."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from ..errors import InputError
from ..splats import Splats
from .atomic import atomic_path

def write_ply(path: str | Path, vertices: np.ndarray) -> None:
    """Write a structured array as the vertex element of a binary little-endian PLY, atomically."""
    element = PlyElement.describe(np.ascontiguousarray(vertices), "vertex")
    with atomic_path(path) as tmp:
        PlyData([element], text=False, byte_order="<").write(str(tmp))


def read_ply(path: str | Path) -> np.ndarray:
    """The vertex element of a PLY file (binary of either byte order, or ASCII; other elements and
    their order do not matter) as a structured array of scalar properties."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "PLY file not found", "give the path of an existing .ply file")
    try:
        ply = PlyData.read(str(path))
    except (PlyParseError, ValueError, UnicodeDecodeError, EOFError) as err:
        raise InputError(path, f"not a readable PLY file ({err})", "give a valid .ply file (re-export it)") from None
    if "vertex" not in ply:
        raise InputError(path, "PLY has no vertex element", "export a point cloud or splat PLY")
    data = ply["vertex"].data
    lists = [name for name in data.dtype.names if data.dtype[name].kind == "O"]
    if lists:
        raise InputError(path, f"list properties in the vertex element are not supported ({', '.join(lists)})",
                         "export plain vertex properties")
    return data.astype(data.dtype.newbyteorder("="), copy=True)


def write_point_cloud(path: str | Path, points: np.ndarray, colors: np.ndarray) -> None:
    """Coloured point cloud: xyz float32 + red/green/blue uchar (colours in [0,1] or uint8)."""
    colors = np.asarray(colors)
    if colors.dtype != np.uint8:
        colors = np.clip(np.round(colors * 255.0), 0, 255).astype(np.uint8)
    v = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    v["x"], v["y"], v["z"] = np.asarray(points, dtype=np.float32).T
    v["red"], v["green"], v["blue"] = colors.T
    write_ply(path, v)


def read_point_cloud(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) float32 and colours (N, 3) float32 in [0, 1] (grey 0.5 if the file has none)."""
    v = read_ply(path)
    points = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    if "red" in v.dtype.names:
        colors = np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.float32) / 255.0
    else:
        colors = np.full_like(points, 0.5)
    return points, colors


def write_splats(path: str | Path, splats: Splats, sh_degree: int | None = None) -> None:
    """Standard 3DGS PLY: x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3 (w x y z).

    ``sh_degree``: write this many SH bands, zero-padding the missing higher ones (the reference
    3DGS loader and SIBR viewer need degree 3, i.e. 45 ``f_rest`` values); default: the splats' own.
    """
    n, m = len(splats), splats.sh.shape[1]
    if sh_degree is not None:
        want = (sh_degree + 1) ** 2
        if want < m:
            raise ValueError(f"splats have {m} SH coefficients; cannot write them as degree {sh_degree}")
        sh = np.zeros((n, want, 3), dtype=np.float32)
        sh[:, :m] = splats.sh
        splats, m = dataclasses.replace(splats, sh=sh), want
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (m - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    # 3DGS stores the higher SH bands channel-major: f_rest_{c*(m-1)+k} = sh[:, 1+k, c].
    rest = splats.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)
    columns = [splats.means, np.zeros((n, 3)), splats.sh[:, 0, :], rest,
               splats.opacity_logits[:, None], splats.log_scales, splats.quats]
    table = np.concatenate([np.asarray(c, dtype=np.float32).reshape(n, -1) for c in columns], axis=1)
    v = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        v[name] = table[:, i]
    write_ply(path, v)


def read_splats(path: str | Path) -> Splats:
    """Read a standard 3DGS PLY (any SH degree 0..3)."""
    v = read_ply(path)
    names = v.dtype.names
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [r for r in required if r not in names]
    if missing:
        raise InputError(path, f"not a 3D Gaussian Splatting PLY (missing {', '.join(missing)})", "give a splats.ply written by 3DGS or taichi-gs")
    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    m = 1 + n_rest // 3
    if n_rest % 3 or m not in (1, 4, 9, 16):
        raise InputError(path, f"{n_rest} f_rest properties do not form SH degree 0-3", "re-export the splats")

    def cols(*keys: str) -> np.ndarray:
        return np.stack([v[k] for k in keys], axis=1).astype(np.float32)

    n = len(v)
    sh = np.zeros((n, m, 3), dtype=np.float32)
    sh[:, 0] = cols("f_dc_0", "f_dc_1", "f_dc_2")
    if m > 1:
        rest = cols(*[f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, m - 1)
        sh[:, 1:] = rest.transpose(0, 2, 1)
    return Splats(
        means=cols("x", "y", "z"),
        quats=cols("rot_0", "rot_1", "rot_2", "rot_3"),
        log_scales=cols("scale_0", "scale_1", "scale_2"),
        opacity_logits=v["opacity"].astype(np.float32),
        sh=sh,
    )
