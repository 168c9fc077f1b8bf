"""`taichi-gs view`: the run folder read per stage, the viser scene built from it, bad input, and the page in a
real headless Chromium (loads, the Gaussians the client received, a camera click, a screenshot that is not blank)."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from taichi_gs import geometry as g
from taichi_gs.cli import app
from taichi_gs.errors import InputError
from taichi_gs.io.images import to_uint8, write_png
from taichi_gs.io.load import load_sequence
from taichi_gs.io.ply import write_point_cloud, write_splats
from taichi_gs.io.trajectory import write_tum
from taichi_gs.pipeline import write_run_info
from taichi_gs.splats import Splats, splats_from_points
from taichi_gs.synth import SynthConfig, generate
from taichi_gs.viewer.run_scene import gaussian_arrays, open_run

runner = CliRunner()
FRAMES = 4
REFINE_GAUSSIANS = 900
DEBLUR_GAUSSIANS = 1500
# CI sets this: there a missing browser fails the browser test instead of skipping it.
REQUIRE_BROWSER = "TAICHI_GS_REQUIRE_BROWSER"


def _scene_points(sequence, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` world points of the frames' depth, coloured from their sharp images."""
    points, colours = [], []
    for i in range(len(sequence)):
        depth = sequence.depth(i)
        valid = depth > 0
        camera = g.backproject(depth, sequence.K())[valid]
        points.append(g.transform(sequence.gt_poses[i], camera))
        colours.append(sequence.sharp(i)[valid])
    points, colours = np.concatenate(points), np.concatenate(colours)
    keep = np.random.default_rng(seed).choice(len(points), count, replace=False)
    return points[keep], colours[keep]


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory) -> Path:
    """A run folder with every stage's outputs, made from a synthetic sequence's ground truth (no training): pose/
    (trajectory, fused points), refine/ and deblur/ (trajectory, splats; deblur also exposure.txt and sharp
    renders: the ground-truth sharp frames)."""
    root = tmp_path_factory.mktemp("view")
    seq_dir = generate(SynthConfig(width=64, height=48, frames=FRAMES, trajectory="handheld", blur="extreme", seed=3),
                       root / "seq")
    sequence = load_sequence(seq_dir)
    run = root / "run"
    write_run_info(run, sequence)
    for stage in ("pose", "refine", "deblur"):
        write_tum(run / stage / "trajectory.txt", sequence.timestamps, sequence.gt_poses)
    write_point_cloud(run / "pose" / "points.ply", *_scene_points(sequence, 2000, 0))
    write_splats(run / "refine" / "splats.ply", splats_from_points(*_scene_points(sequence, REFINE_GAUSSIANS, 1), 0.03))
    write_splats(run / "deblur" / "splats.ply", splats_from_points(*_scene_points(sequence, DEBLUR_GAUSSIANS, 2), 0.03,
                                                                   opacity=0.9))
    shutil.copyfile(seq_dir / "exposure.txt", run / "deblur" / "exposure.txt")  # the true exposures, same layout
    for i, name in enumerate(sequence.names):
        write_png(run / "deblur" / "renders" / "sharp" / f"{name}.png", to_uint8(sequence.sharp(i)))
    return run


def _copy_without(run: Path, tmp_path: Path, *stages: str) -> Path:
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    for stage in stages:
        shutil.rmtree(copy / stage)
    return copy


def test_run_is_read_per_stage(run_folder):
    scene = open_run(run_folder)
    assert scene.stages == ["pose", "refine", "deblur"]
    deblur, refine, pose = (scene.views[stage] for stage in ("deblur", "refine", "pose"))
    assert (deblur.gaussian_count, refine.gaussian_count, pose.gaussian_count) == (DEBLUR_GAUSSIANS, REFINE_GAUSSIANS, 0)
    assert pose.splats is None and len(pose.points[0]) == 2000
    assert deblur.exposures.shape == (FRAMES, 2, 4, 4) and refine.exposures is None and pose.exposures is None
    np.testing.assert_allclose(deblur.exposures, scene.sequence.exposure_poses, atol=1e-6)
    np.testing.assert_allclose(refine.poses, scene.sequence.gt_poses, atol=1e-6)
    assert scene.stored_render(deblur, 1).shape == (48, 64, 3) and scene.stored_render(refine, 1) is None
    assert scene.input_image(1).dtype == np.uint8 and scene.input_image(1).shape == (48, 64, 3)


def test_only_stages_with_outputs_are_offered(run_folder, tmp_path):
    assert open_run(_copy_without(run_folder, tmp_path, "refine", "deblur")).stages == ["pose"]


def test_gaussian_arrays_are_the_covariance_colour_and_opacity():
    angle = 0.7
    rotation = g.so3_exp(np.array([0.0, 0.0, angle]))
    splats = Splats(means=np.array([[1.0, 2.0, 3.0]], np.float32),
                    quats=np.array([[np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)]], np.float32) * 2.0,  # unnormalised
                    log_scales=np.log(np.array([[0.1, 0.2, 0.05]], np.float32)),
                    opacity_logits=np.array([0.0], np.float32), sh=np.full((1, 4, 3), 1.0, np.float32))
    centres, covariances, colours, opacities = gaussian_arrays(splats)
    expected = rotation @ np.diag([0.01, 0.04, 0.0025]) @ rotation.T
    np.testing.assert_allclose(covariances[0], expected, atol=1e-7)
    np.testing.assert_allclose(centres, [[1, 2, 3]])
    np.testing.assert_allclose(colours, np.full((1, 3), 0.28209479177387814 + 0.5), atol=1e-6)
    np.testing.assert_allclose(opacities, [[0.5]])


def test_frustum_segments_reach_the_image_corners():
    from taichi_gs.viewer.app import frustum_segments

    intr = SynthConfig(width=64, height=48)  # fx = fy; the principal point at the image centre
    fy = 0.5 * intr.width / np.tan(np.radians(intr.fov_deg) / 2)
    pose = g.pose_from_rt(g.so3_exp(np.array([0.1, -0.4, 0.2])), np.array([1.0, 2.0, -0.5]))
    segments = frustum_segments(pose[None], 2 * np.arctan(intr.height / 2 / fy), intr.width / intr.height, 0.3)
    assert segments.shape == (8, 2, 3)
    np.testing.assert_allclose(segments[:4, 0], np.tile(pose[:3, 3], (4, 1)))  # from the camera centre
    camera = g.transform(g.invert(pose), segments[:4, 1])
    np.testing.assert_allclose(camera[:, 2], 0.3)
    pixels = camera[:, :2] / camera[:, 2:] * fy + [intr.width / 2, intr.height / 2]
    np.testing.assert_allclose(pixels, [[0, 0], [64, 0], [64, 48], [0, 48]], atol=1e-9)  # the image's corners
    np.testing.assert_allclose(segments[4:, 0], segments[:4, 1])  # then its edges
    np.testing.assert_allclose(segments[4:, 1], np.roll(segments[:4, 1], -1, axis=0))


def test_view_of_a_folder_that_is_no_run_fails_with_one_line(tmp_path):
    pytest.importorskip("viser")
    result = runner.invoke(app, ["view", str(tmp_path), "--port", "0"])
    assert result.exit_code == 2, result.output
    assert "run.json" in result.output and len(result.output.strip().splitlines()) == 1


def test_view_of_a_run_without_stage_output_fails_with_one_line(run_folder, tmp_path):
    pytest.importorskip("viser")
    bare = _copy_without(run_folder, tmp_path, "pose", "refine", "deblur")
    result = runner.invoke(app, ["view", str(bare), "--port", "0"])
    assert result.exit_code == 2, result.output
    assert "no stage output" in result.output and len(result.output.strip().splitlines()) == 1


def test_view_of_a_run_with_a_corrupt_stage_file_fails_with_one_line(run_folder, tmp_path):
    pytest.importorskip("viser")
    broken = _copy_without(run_folder, tmp_path)
    (broken / "refine" / "splats.ply").write_bytes(b"ply\nnot a header\n")
    result = runner.invoke(app, ["view", str(broken), "--port", "0"])
    assert result.exit_code == 2, result.output
    assert "splats.ply" in result.output and len(result.output.strip().splitlines()) == 1


def test_view_without_the_extra_names_it(run_folder, monkeypatch):
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser raises ImportError
    result = runner.invoke(app, ["view", str(run_folder)])
    assert result.exit_code == 2, result.output
    assert "pip install 'taichi-gs[viewer]'" in result.output


def test_view_refuses_a_port_in_use(run_folder):
    pytest.importorskip("viser")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = runner.invoke(app, ["view", str(run_folder), "--port", str(port)])
    assert result.exit_code == 2, result.output
    assert f"127.0.0.1:{port}" in result.output and "--port" in result.output


def test_view_refuses_a_host_of_another_machine(run_folder):
    pytest.importorskip("viser")
    result = runner.invoke(app, ["view", str(run_folder), "--host", "203.0.113.7", "--port", "0"])  # TEST-NET-3
    assert result.exit_code == 2, result.output
    assert "cannot serve on 203.0.113.7:0" in result.output and "--host" in result.output


@pytest.fixture
def viewer(run_folder):
    pytest.importorskip("viser")
    from taichi_gs.viewer.app import RunViewer

    viewer = RunViewer(open_run(run_folder), "127.0.0.1", 0)
    yield viewer
    viewer.stop()


def test_the_scene_is_built_from_the_run(viewer):
    assert viewer.stage_name == "deblur" and viewer.port > 0 and viewer.url == f"http://127.0.0.1:{viewer.port}"
    assert len(viewer._frustums) == FRAMES
    assert len(viewer._nodes) == 1 + 1 + FRAMES + 1  # splats, trajectory, a frustum per camera, the exposures
    assert f"Gaussians: {DEBLUR_GAUSSIANS}" in viewer.counts.content and "exposures" in viewer.counts.content
    assert viewer.stage_menu.options == ("pose", "refine", "deblur")
    assert not viewer.image.visible
    viewer.show_camera(2)
    assert viewer.image.visible and viewer.image.image.shape == (48, 128, 3)  # input | sharp render
    assert "blurred input | sharp render (deblur)" in viewer.caption.content
    assert viewer.camera_menu.value == viewer.scene.sequence.names[2]
    assert tuple(viewer._frustums[2].color) != tuple(viewer._frustums[1].color)  # the chosen camera stands out

    viewer.stage_menu.value = "pose"  # the stage switch: its handler replaces the scene
    assert viewer.stage_name == "pose" and len(viewer._frustums) == FRAMES
    assert len(viewer._nodes) == 1 + 1 + FRAMES and "points: 2000" in viewer.counts.content
    assert viewer.image.image.shape == (48, 64, 3) and "has no splats" in viewer.caption.content  # input only

    viewer.camera_menu.value = viewer.scene.sequence.names[0]  # the camera dropdown: the frustum click's handler
    assert "**" + viewer.scene.sequence.names[0] + "**" in viewer.caption.content

    viewer.stage_menu.value = "refine"  # no stored renders: the splats are rendered at the frame's pose
    assert f"Gaussians: {REFINE_GAUSSIANS}" in viewer.counts.content and "exposures" not in viewer.counts.content
    assert "blurred input | render (refine)" in viewer.caption.content and viewer.image.image.shape == (48, 128, 3)
    render = viewer.image.image[:, 64:].astype(float)
    assert render.std() > 5 and render.mean() > 10  # the splats, not an empty frame


def test_view_prints_the_url_and_serves_on_the_port_given(run_folder):
    pytest.importorskip("viser")
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    process = subprocess.Popen([sys.executable, "-m", "taichi_gs.cli", "view", str(run_folder), "--host", "127.0.0.1",
                                "--port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               # a shell's background job ignores SIGINT, and a child would inherit that: restore it
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        url = process.stdout.readline().strip()
        assert url == f"http://127.0.0.1:{port}", process.stderr.read() if not url else url
        with urllib.request.urlopen(url, timeout=10) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
    finally:
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=30)
    assert process.returncode == 0, stderr
    assert f"viewer of {run_folder} at {url}" in " ".join(stderr.split())


def _chromium() -> str:
    """The system's Chromium for Playwright, or a skip saying why (a failure where CI requires the browser)."""
    why = None
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        why = "Playwright is not installed (pip install -e '.[test]')"
    given = os.environ.get("TAICHI_GS_CHROMIUM")
    path = given if given and Path(given).is_file() else shutil.which("chromium") or shutil.which("chromium-browser")
    if why is None and path is None:
        why = "no Chromium found (Debian: apt-get install chromium; or set TAICHI_GS_CHROMIUM to its path)"
    if why is not None:
        if os.environ.get(REQUIRE_BROWSER):
            pytest.fail(f"{REQUIRE_BROWSER} is set but the browser test cannot run: {why}")
        pytest.skip(why)
    return path


CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage"]


def _gaussians_received(frames: list[bytes]) -> list[int]:
    """The Gaussian count of every splat message in the websocket frames the page received (viser's wire format:
    two little-endian sizes, zstd-compressed msgpack naming each binary buffer's length, then the buffers; a
    Gaussian is 8 uint32)."""
    import msgspec
    import zstandard

    counts = []
    for frame in frames:
        size, packed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
        body = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(frame[16:16 + packed],
                                                                               max_output_size=size))
        for message in body["messages"]:
            if message.get("type") == "GaussianSplatsMessage":
                counts.append(body["binaryBufferLengths"][message["props"]["buffer"]["__binary_index"]] // 32)
    return counts


def _wait_for(condition, timeout_s: float = 20.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.1)
    return condition()


def test_the_page_in_headless_chromium(viewer, tmp_path):
    executable = _chromium()
    from playwright.sync_api import sync_playwright

    frames: list[bytes] = []
    names = viewer.scene.sequence.names
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=executable, headless=True,
                                             args=CHROMIUM_FLAGS)  # a fresh profile each launch
        try:
            page = browser.new_page(viewport={"width": 1000, "height": 700})
            page.on("websocket", lambda ws: ws.on(
                "framereceived", lambda payload: frames.append(payload) if isinstance(payload, bytes) else None))
            page.goto(viewer.url)
            page.get_by_text(f"Gaussians: {DEBLUR_GAUSSIANS}").wait_for(timeout=30_000)  # the page loaded the run
            assert _wait_for(lambda: DEBLUR_GAUSSIANS in _gaussians_received(frames)), _gaussians_received(frames)
            assert _wait_for(lambda: len(viewer.server.get_clients()) == 1)
            canvas = max(page.locator("canvas").all(), key=lambda c: (c.bounding_box() or {"width": 0})["width"])
            shots: list[bytes] = []  # software WebGL fades the splats in over a few frames: until they are drawn
            assert _wait_for(lambda: _drawn_share(shots.append(canvas.screenshot()) or shots[-1]) > 0.1, 30.0), \
                _drawn_share(shots[-1])
            (tmp_path / "overview.png").write_bytes(shots[-1])

            # A click on the last camera's frustum (the cameras move forwards): the browser's camera is put in front
            # of it, looking back at its image plane, which lies ahead of every other frustum.
            last = FRAMES - 1
            pose = viewer.scene.views["deblur"].poses[last]
            client = next(iter(viewer.server.get_clients().values()))
            target = pose[:3, 3] + 0.5 * pose[:3, 2]
            client.camera.position, client.camera.look_at = target, pose[:3, 3]
            moved = time.time()
            assert _wait_for(lambda: client.camera.update_timestamp > moved  # the page reports its camera back
                             and np.allclose(client.camera.position, target, atol=1e-3))
            box = canvas.bounding_box()
            assert not viewer.image.visible
            page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
            page.get_by_text("blurred input | sharp render (deblur)").wait_for(timeout=15_000)
            assert viewer._shown == ("deblur", last)
            assert page.locator("img").count() >= 1
            page.screenshot(path=str(tmp_path / "clicked.png"))

            # The camera dropdown: the same handler as a click.
            camera_menu = page.get_by_role("combobox", name="camera")
            assert camera_menu.input_value() == names[last]  # the click set the dropdown too
            camera_menu.click()
            page.get_by_role("option", name=names[1]).click()
            assert _wait_for(lambda: viewer._shown == ("deblur", 1))
            page.get_by_text(names[1]).first.wait_for(timeout=15_000)
            page.screenshot(path=str(tmp_path / "chosen.png"))
        finally:
            browser.close()
    if os.environ.get("TAICHI_GS_VIEWER_SHOTS"):  # to look at them
        for name in ("overview.png", "clicked.png", "chosen.png"):
            shutil.copyfile(tmp_path / name, Path(os.environ["TAICHI_GS_VIEWER_SHOTS"]) / name)


def _drawn_share(png: bytes) -> float:
    """The share of the canvas's middle (clear of the GUI panel, top right, and notices, top left) that differs
    from its most common colour, the background."""
    import imageio.v3 as iio

    image = iio.imread(png)[..., :3].astype(int)
    h, w = image.shape[:2]
    middle = image[int(0.3 * h):int(0.9 * h), int(0.1 * w):int(0.6 * w)].reshape(-1, 3)
    colours, counts = np.unique(middle, axis=0, return_counts=True)
    return float(np.mean(np.abs(middle - colours[np.argmax(counts)]).sum(axis=1) > 30))
