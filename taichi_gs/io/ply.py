"""PLY files: coloured point clouds (xyz + uchar rgb) and the standard 3D Gaussian Splatting layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..splats import Splats
from .atomic import atomic_path

_PLY_TYPES = {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "uchar": "u1", "uint8": "u1",
              "char": "i1", "int8": "i1", "ushort": "u2", "uint16": "u2", "short": "i2", "int16": "i2",
              "uint": "u4", "uint32": "u4", "int": "i4", "int32": "i4"}
_NUMPY_TO_PLY = {"f4": "float", "f8": "double", "u1": "uchar", "i1": "char", "u2": "ushort", "i2": "short", "u4": "uint", "i4": "int"}


def write_ply(path: str | Path, vertices: np.ndarray) -> None:
    """Write a structured array as the vertex element of a binary little-endian PLY, atomically."""
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}"]
    for name in vertices.dtype.names:
        header.append(f"property {_NUMPY_TO_PLY[vertices.dtype[name].str[1:]]} {name}")
    header.append("end_header")
    data = vertices.astype(vertices.dtype.newbyteorder("<"), copy=False)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(data.tobytes())


def read_ply(path: str | Path) -> np.ndarray:
    """The vertex element of a binary little-endian PLY as a structured array."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "PLY file not found", "give the path of an existing .ply file")
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise InputError(path, "not a PLY file", "give a .ply file")
        fields, count, in_vertex, fmt = [], None, False, None
        while True:
            line = f.readline()
            if not line:
                raise InputError(path, "PLY header has no end_header", "re-export the file")
            words = line.decode("ascii", errors="replace").split()
            if not words:
                continue
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                in_vertex = words[1] == "vertex"
                if in_vertex:
                    count = int(words[2])
                elif count is None:
                    raise InputError(path, "the vertex element must come first", "export the vertices first")
            elif words[0] == "property" and in_vertex:
                if words[1] == "list":
                    raise InputError(path, "list properties in the vertex element are not supported", "export plain vertex properties")
                fields.append((words[2], "<" + _PLY_TYPES[words[1]]))
            elif words[0] == "end_header":
                break
        if fmt != "binary_little_endian":
            raise InputError(path, f"PLY format {fmt} is not supported", "export as binary_little_endian")
        if count is None:
            raise InputError(path, "PLY has no vertex element", "export a point cloud or splat PLY")
        dtype = np.dtype(fields)
        data = np.frombuffer(f.read(dtype.itemsize * count), dtype=dtype, count=count)
    return data.copy()


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


def write_splats(path: str | Path, splats: Splats) -> None:
    """Standard 3DGS PLY: x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3 (w x y z)."""
    n, m = len(splats), splats.sh.shape[1]
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
