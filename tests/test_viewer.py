"""view.py: camera conversions, the pictures of every mode and selection, two runs side by side,
the server in a subprocess (page over HTTP, bad input) and a real headless Chromium."""
from __future__ import annotations

import contextlib
import socket
import time
import types
import urllib.request

import cv2
import numpy as np
import pytest
import torch

from baselines.fourdgs.app import run_cli
from baselines.fourdgs.evaluate import to_uint8
from baselines.fourdgs.renderer import render
from baselines.viewer.app import MAX_SIDE_RANGE, ViewerApp
from baselines.viewer.camera import image_size, intrinsics, pose_from_view, vertical_fov, view_from_pose
from baselines.viewer.cli import main as viewer_main
from baselines.viewer.render_loop import ClientRenderer
from baselines.viewer.runs import ViewerRun
from benchmarks.headless_browser import HeadlessChromium, ViewerProcess, blank_reason, chromium_binary

WHITE = 255


@pytest.fixture(scope="module")
def run(tiny_reflow_run) -> ViewerRun:
    return ViewerRun.load(tiny_reflow_run)


def test_camera_conversions_round_trip():
    rng = np.random.default_rng(0)
    q = rng.normal(size=4)
    viewmat = view_from_pose(q / np.linalg.norm(q), rng.normal(size=3))
    wxyz, position = pose_from_view(viewmat)
    torch.testing.assert_close(view_from_pose(wxyz, position), viewmat, atol=1e-5, rtol=0)
    assert np.allclose(np.linalg.inv(viewmat.double().numpy())[:3, 3], position)
    K = intrinsics(0.9, 640, 360)
    assert vertical_fov(K, 360) == pytest.approx(0.9) and K[0, 2] == 320 and K[1, 2] == 180
    assert image_size(16 / 9, 512) == (512, 288) and image_size(0.5, 512) == (256, 512)


def test_pictures_of_every_mode_and_selection(run):
    cam = run.train_cameras[3]
    picture, _ = run.render(cam.viewmat, cam.K, cam.width, cam.height, cam.time, "RGB")
    # the viewer draws what render.py draws from the same camera at the same time
    assert np.array_equal(picture, to_uint8(render(run.model, cam, "fine", run.background).image)[..., ::-1])
    assert run.has_split and set(run.modes) == {"RGB", "depth", "alpha", "full flow"}
    for mode in run.modes:
        picture, caption = run.render(cam.viewmat, cam.K, 40, 30, cam.time, mode)
        assert picture.shape == (30, 40, 3) and picture.dtype == np.uint8 and picture.std() > 0, mode
    dynamic = run.states(cam.time, "dynamic only").means.shape[0]
    static = run.states(cam.time, "static only").means.shape[0]
    assert dynamic == run.num_dynamic and dynamic + static == run.num_gaussians
    # static Gaussians never move: their full flow (camera held still) is white wherever it is valid
    flow, caption = run.render(cam.viewmat, cam.K, cam.width, cam.height, cam.time, "full flow", "static only")
    covered = flow.max(-1) > 0
    assert covered.mean() > 0.3 and (flow[covered] >= WHITE - 1).all() and "full colour = 0.05 px" in caption
    fixed = run.render(cam.viewmat, cam.K, cam.width, cam.height, cam.time, "full flow", color_scale=2.0)[1]
    assert "full colour = 2.00 px" in fixed  # one scale for pictures side by side
    alpha_static = run.render(cam.viewmat, cam.K, cam.width, cam.height, cam.time, "alpha", "static only")[0]
    alpha_both = run.render(cam.viewmat, cam.K, cam.width, cam.height, cam.time, "alpha", "both")[0]
    assert (alpha_both.astype(int) >= alpha_static.astype(int) - 1).all() and (alpha_both > alpha_static + 2).any()


def test_two_runs_side_by_side_share_the_camera(run):
    app = ViewerApp([run, run], port=0, max_side=MAX_SIDE_RANGE[1])  # every --max_res view.py accepts fits the GUI
    app.start()
    try:
        assert app.max_side.value == MAX_SIDE_RANGE[1]
        cam = run.train_cameras[0]
        wxyz, position = pose_from_view(cam.viewmat)
        client = types.SimpleNamespace(camera=types.SimpleNamespace(wxyz=wxyz, position=position,
                                                                    fov=vertical_fov(cam.K, cam.height)))
        app.time.value = cam.time
        picture = app.draw(client, 84, 40)
        half = (84 - 4) // 2
        left, right = picture[:, :half], picture[:, half + 4:]
        below_label = slice(20, None)  # "A: name" and "B: name" are written in the top rows
        assert picture.shape == (40, 84, 3) and np.array_equal(left[below_label], right[below_label])
        assert not np.array_equal(left[:20], right[:20])
        expected, _ = run.render(cam.viewmat, intrinsics(vertical_fov(cam.K, cam.height), half, 40), half, 40, cam.time)
        assert np.array_equal(left[below_label], expected[below_label])
        # a click on a frustum moves the clicking browser's camera there and the time to its frame
        target = run.test_cameras[-1]
        client.atomic = contextlib.nullcontext
        app.jump(client, target)
        torch.testing.assert_close(view_from_pose(client.camera.wxyz, client.camera.position), target.viewmat,
                                   atol=1e-5, rtol=0)
        assert client.camera.fov == pytest.approx(vertical_fov(target.K, target.height))
        assert app.time.value == pytest.approx(target.time)
        app.playing = True  # Play advances the time one frame at a time
        assert _wait_until(lambda: app.time.value != pytest.approx(target.time))
        app.playing = False
    finally:
        app.stop()


def _wait_until(condition, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


def test_low_resolution_while_moving_then_full_once_still():
    sent = []
    client = types.SimpleNamespace(
        client_id=7, camera=types.SimpleNamespace(aspect=4 / 3, update_timestamp=1.0),
        scene=types.SimpleNamespace(set_background_image=lambda image, **_: sent.append(image.shape[:2])))
    renderer = ClientRenderer(client, lambda w, h: np.zeros((h, w, 3), np.uint8), max_side=lambda: 512,
                              playing=lambda: False)
    renderer.start()
    try:
        renderer.request(moving=True)
        assert _wait_until(lambda: len(sent) >= 2)
        assert sent[0] == (144, 192), "while moving, before any speed is known: a small frame"
        assert sent[-1] == (384, 512), "once still: the full size"
        assert renderer.first_frame_s is not None and renderer.records[-1].full
    finally:
        renderer.stop()


# ---------------------------------------------------------------------- the server in a subprocess
@pytest.fixture(scope="module")
def viewer(tiny_reflow_run):
    proc = ViewerProcess("-m", str(tiny_reflow_run), "--port", "0", "--max_res", "256")
    try:
        proc.url = proc.wait_for(r"open (http://127\.0\.0\.1:\d+) ").group(1)
        yield proc
    finally:
        proc.stop()


def test_page_is_served_on_localhost(viewer):
    with urllib.request.urlopen(viewer.url, timeout=30) as response:
        page = response.read().decode("utf-8", "replace")
    assert response.status == 200 and "<html" in page.lower() and "<script" in page.lower()


def _one_error_line(capsys, args: list[str]) -> str:
    """view.py's main through the CLI wrapper (in-process: the checks come before any loading)."""
    with pytest.raises(SystemExit) as exc:
        run_cli(lambda: viewer_main(args))
    lines = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


def test_bad_input_gives_one_error_line(tiny_reflow_run, tmp_path, capsys):
    assert "is not a trained run" in _one_error_line(capsys, ["-m", str(tmp_path)])
    assert "side by side" in _one_error_line(capsys, ["-m", str(tiny_reflow_run), "-m", str(tiny_reflow_run),
                                                      "-m", str(tiny_reflow_run)])
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        line = _one_error_line(capsys, ["-m", str(tiny_reflow_run), "--port", str(port)])
    assert f"port {port}" in line and "in use" in line


@pytest.mark.skipif(chromium_binary() is None, reason="no chromium on PATH: `apt-get install chromium` (Debian) "
                    "enables the browser test; .ci/run installs it where apt works")
def test_headless_chromium_shows_the_rendered_scene(viewer, run, tmp_path):
    width, height = 800, 600
    with HeadlessChromium(viewer.url, width, height) as browser:
        sent = viewer.wait_for(r"first frame \((\d+)x(\d+)\) sent", timeout=120)
        # the canvas left of the control panel, below viser's WebGL notice, above its axes widget
        region = (slice(int(0.3 * height), int(0.85 * height)), slice(int(0.12 * width), int(0.5 * width)))
        shot = browser.wait_for_picture(lambda p: blank_reason(p[region]) is None, timeout=90)
    cv2.imwrite(str(tmp_path / "viewer.png"), cv2.cvtColor(shot, cv2.COLOR_RGB2BGR))
    # and it is the scene: the first training camera's view, as the server rendered it, correlates
    w, h = int(sent.group(1)), int(sent.group(2))
    cam = run.train_cameras[0]
    wxyz, position = pose_from_view(cam.viewmat)
    expected, _ = run.render(cam.viewmat, intrinsics(vertical_fov(cam.K, cam.height), w, h), w, h, cam.time)
    expected = cv2.resize(expected, (width, height), interpolation=cv2.INTER_LINEAR)
    a = shot[region].astype(np.float64).mean(-1).ravel()
    b = expected[region].astype(np.float64).mean(-1).ravel()
    assert np.corrcoef(a, b)[0, 1] > 0.5
