"""The viser web viewer of a run: the splats (stage 1: the fused points), each camera's frustum (stage 3: also
its exposure start and end), the trajectory, a stage switch, and a camera's blurred input beside the render.

viser is the optional extra ``taichi-gs[viewer]``; this module imports it when a viewer starts.
"""

from __future__ import annotations

import contextlib
import io
import math
import socket
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import InputError
from ..geometry import rotmat_to_quat
from .run_scene import RunScene, StageView, gaussian_arrays, open_run

NO_CAMERA = "none"
MID_COLOUR = (40, 90, 200)  # a camera's frustum (stage 3: at mid-exposure)
SELECTED_COLOUR = (255, 140, 0)
START_COLOUR = (40, 170, 60)  # stage 3: exposure start
END_COLOUR = (210, 50, 50)  # stage 3: exposure end
TRAJECTORY_COLOUR = (230, 230, 230)  # light on the black background
POINT_SIZE_SHARE = 0.004  # stage 1's points: this share of the scene's extent
FRUSTUM_SHARE = 0.02  # a camera's frustum: this share of the scene's extent deep
THUMBNAIL_WIDTH = 96  # the input frame drawn on its frustum, pixels


def import_viser() -> Any:
    """The viser module, or a one-line error naming the extra to install."""
    try:
        import viser
    except ImportError:
        raise InputError(None, "the viewer needs viser, an optional dependency",
                         "pip install 'taichi-gs[viewer]'") from None
    return viser


def check_address(host: str, port: int) -> None:
    """Refuse an address this machine cannot serve on (unknown host, port taken) before starting the server,
    which would otherwise try the following ports."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind(address)
    except OSError as err:
        raise InputError(None, f"cannot serve on {host}:{port} ({err.strerror or err})",
                         "give another --port, or a --host of this machine (127.0.0.1: this machine only)") from None


def frustum_segments(poses: np.ndarray, fov: float, aspect: float, depth: float) -> np.ndarray:
    """Wireframe frustums of camera-to-world ``poses`` (N, 4, 4; OpenCV axes) with vertical field of view ``fov``
    (radians) and width / height ``aspect``, ``depth`` deep: (8 N, 2, 3) line segments, apex to each image corner
    and the image's four edges."""
    half_h = depth * math.tan(fov / 2.0)
    half_w = half_h * aspect
    corners = np.array([[-half_w, -half_h, depth], [half_w, -half_h, depth], [half_w, half_h, depth],
                        [-half_w, half_h, depth]])
    world = corners @ poses[:, :3, :3].swapaxes(-1, -2) + poses[:, None, :3, 3]  # (N, 4, 3)
    apex = np.broadcast_to(poses[:, None, :3, 3], world.shape)
    rays = np.stack([apex, world], axis=2)
    edges = np.stack([world, np.roll(world, -1, axis=1)], axis=2)
    return np.concatenate([rays, edges], axis=1).reshape(-1, 2, 3)


def _quiet() -> contextlib.AbstractContextManager:
    """Keep viser's own banner and stop notice off stdout (the command prints the URL itself)."""
    return contextlib.redirect_stdout(io.StringIO())


class RunViewer:
    """A viser server showing one stage of a run at a time; a frustum click or the camera dropdown shows that
    frame's blurred input beside the stage's render (stage 3's stored sharp render, else one rendered now)."""

    def __init__(self, scene: RunScene, host: str = "127.0.0.1", port: int = 8080, arch: str = "auto"):
        viser = import_viser()
        check_address(host, port)
        self.scene, self.arch = scene, arch
        with _quiet():
            self.server = viser.ViserServer(host=host, port=port, label="taichi-gs", verbose=False)
        if port and self.server.get_port() != port:  # taken between the check and the bind
            self.stop()
            raise InputError(None, f"port {port} is in use", "give another --port")
        self.server.gui.configure_theme(dark_mode=True, show_share_button=False)  # no link through viser's relay
        # black behind the splats, as the stages render and train them: what their opacities leave shows as black
        self.server.scene.set_background_image(np.zeros((1, 1, 3), dtype=np.uint8), format="png")
        self.host, self.port = host, self.server.get_port()
        self._lock = threading.RLock()
        self._nodes: list[Any] = []
        self._frustums: list[Any] = []
        self._thumbs: list[np.ndarray] | None = None
        self._shown: tuple[str, int] | None = None
        self.stage_name = ""
        self._build_gui()
        self.show_stage(scene.stages[-1])

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"http://{f'[{host}]' if ':' in host else host}:{self.port}"

    def stop(self) -> None:
        with _quiet():
            self.server.stop()

    def _build_gui(self) -> None:
        gui, names = self.server.gui, self.scene.sequence.names
        gui.add_markdown(f"**run** `{self.scene.run_dir.name}`: {len(names)} frames")
        self.stage_menu = gui.add_dropdown("stage", tuple(self.scene.stages), initial_value=self.scene.stages[-1],
                                           hint="pose: stage 1's fused points; refine, deblur: their splats")
        self.counts = gui.add_markdown("")
        self.camera_menu = gui.add_dropdown("camera", (NO_CAMERA, *names), initial_value=NO_CAMERA,
                                            hint="a frame's blurred input beside the render (or click a camera)")
        self.caption = gui.add_markdown("", visible=False)
        self.image = gui.add_image(np.zeros((8, 16, 3), dtype=np.uint8), visible=False)

        @self.stage_menu.on_update
        def _(_: Any) -> None:
            self.show_stage(self.stage_menu.value)

        @self.camera_menu.on_update
        def _(_: Any) -> None:
            if self.camera_menu.value != NO_CAMERA:
                self.show_camera(names.index(self.camera_menu.value))

    def show_stage(self, name: str) -> None:
        """Replace the scene with stage ``name``'s splats (or points), cameras and trajectory."""
        with self._lock:
            if name == self.stage_name:
                return
            view = self.scene.views[name]
            for node in self._nodes:
                node.remove()
            self._nodes, self._frustums, self.stage_name = [], [], name
            with self.server.atomic():
                extent = self._add_geometry(view)
                self._add_cameras(view, extent)
            self.stage_menu.value = name
            what = (f"Gaussians: {view.gaussian_count}" if view.splats is not None
                    else f"points: {len(view.points[0])}")
            exposures = "; exposures: start green, end red" if view.exposures is not None else ""
            self.counts.content = f"{what} · cameras: {len(view.poses)}{exposures}"
            if self._shown is not None:
                self.show_camera(self._shown[1])

    def _add_geometry(self, view: StageView) -> float:
        """The stage's splats or points; returns the scene's extent (metres), which sizes the cameras."""
        scene = self.server.scene
        centres = view.splats.means if view.splats is not None else view.points[0]
        spread = np.concatenate([centres, view.poses[:, :3, 3]]) if len(centres) else view.poses[:, :3, 3]
        low, high = np.percentile(spread, [2, 98], axis=0)
        extent = max(float(np.linalg.norm(high - low)), 1e-3)
        if view.splats is not None:
            self._nodes.append(scene.add_gaussian_splats(f"/{view.name}/splats", *gaussian_arrays(view.splats)))
        else:
            points, colours = view.points
            self._nodes.append(scene.add_point_cloud(f"/{view.name}/points", points, colours,
                                                     point_size=POINT_SIZE_SHARE * extent))
        self._place_camera(view, centres)
        return extent

    def _place_camera(self, view: StageView, centres: np.ndarray) -> None:
        """Up is the cameras' image up; a new page (and Reset View) looks through the first camera, from a little
        behind it, at the scene's median depth: how the capture began."""
        up = -np.median(view.poses[:, :3, 1], axis=0)  # OpenCV cameras: -y
        self.server.scene.set_up_direction(up / max(float(np.linalg.norm(up)), 1e-9))
        first, forward = view.poses[0, :3, 3], view.poses[0, :3, 2]
        depths = (centres - first) @ forward
        depth = float(np.median(depths[depths > 0])) if np.any(depths > 0) else 1.0
        self.server.initial_camera.position = first - 0.2 * depth * forward
        self.server.initial_camera.look_at = first + depth * forward

    def _add_cameras(self, view: StageView, extent: float) -> None:
        """The trajectory, each camera's frustum (its input on it; clickable) and, in stage 3, its exposure's
        start and end."""
        scene, intr = self.server.scene, self.scene.sequence.intrinsics
        fov, aspect = 2.0 * math.atan(intr.height / (2.0 * intr.fy)), intr.width / intr.height
        size = FRUSTUM_SHARE * extent
        centres = view.poses[:, :3, 3]
        self._nodes.append(scene.add_line_segments(
            f"/{view.name}/trajectory", np.stack([centres[:-1], centres[1:]], axis=1), TRAJECTORY_COLOUR,
            thickness=2.0, thickness_units="screen"))
        for i, (pose, thumbnail) in enumerate(zip(view.poses, self._thumbnails())):
            frustum = scene.add_camera_frustum(f"/{view.name}/cameras/{i:05d}", fov, aspect, scale=size,
                                               thickness=2.0, thickness_units="screen", color=MID_COLOUR,
                                               image=thumbnail, wxyz=rotmat_to_quat(pose[:3, :3]), position=pose[:3, 3])
            frustum.on_click(lambda _, frame=i: self.show_camera(frame))
            self._frustums.append(frustum)
            self._nodes.append(frustum)
        if view.exposures is not None:  # every start and end frustum in one node: one message, however many frames
            segments = [frustum_segments(view.exposures[:, end], fov, aspect, 0.6 * size) for end in (0, 1)]
            colours = [np.broadcast_to(np.array(colour, np.uint8), part.shape) for part, colour
                       in zip(segments, (START_COLOUR, END_COLOUR))]
            self._nodes.append(scene.add_line_segments(f"/{view.name}/exposures", np.concatenate(segments),
                                                       np.concatenate(colours), thickness=1.5,
                                                       thickness_units="screen"))

    def _thumbnails(self) -> list[np.ndarray]:
        """Each input frame, at most THUMBNAIL_WIDTH pixels wide, read once."""
        if self._thumbs is None:
            self._thumbs = []
            for i in range(len(self.scene.sequence)):
                image = self.scene.input_image(i)
                scale = min(1.0, THUMBNAIL_WIDTH / image.shape[1])
                size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
                self._thumbs.append(cv2.resize(image, size, interpolation=cv2.INTER_AREA))
        return self._thumbs

    def show_camera(self, frame: int) -> None:
        """Show frame ``frame``'s blurred input beside the shown stage's render, and mark its frustum."""
        with self._lock:
            if self._shown == (self.stage_name, frame):
                return
            view = self.scene.views[self.stage_name]
            render, what = self.scene.stored_render(view, frame), "sharp render"
            if render is None and view.splats is not None:
                render, what = self._render_now(view, frame), "render"
            panels = [self.scene.input_image(frame)] + ([] if render is None else [render])
            name = self.scene.sequence.names[frame]
            self.caption.content = (f"**{name}**: blurred input" + (f" | {what} ({view.name})" if render is not None
                                                                   else f" (stage {view.name} has no splats)"))
            self.image.image = np.concatenate(panels, axis=1)
            self.caption.visible = self.image.visible = True
            for i, frustum in enumerate(self._frustums):
                frustum.color = SELECTED_COLOUR if i == frame else MID_COLOUR  # unchanged colours are not sent
            self._shown = (view.name, frame)
            self.camera_menu.value = name

    def _render_now(self, view: StageView, frame: int) -> np.ndarray:
        from ..kernels import runtime

        runtime.init(self.arch)
        return self.scene.live_render(view, frame)


def serve(run_dir: Path, host: str, port: int, arch: str = "auto") -> RunViewer:
    """Open ``run_dir`` and start its viewer (the server runs on its own threads until ``stop()``)."""
    import_viser()  # before reading the run: the missing extra is the first thing to fix
    return RunViewer(open_run(run_dir), host, port, arch)
