"""The viewer's server: one viser server, its controls, and the pictures each browser receives.

    app = ViewerApp([run_a, run_b], port=8080, max_side=512)     # ViewerRun objects (runs.py)
    app.start()            # binds 127.0.0.1:port (ValueError if taken), prints the URL
    app.wait()             # until Ctrl-C / app.stop()

Controls (viser's side panel): time slider (one step = one video frame) with Play/Pause, render
mode (RGB, depth, alpha, plus the runs' plugin modes: ReFlow's "full flow"), Gaussians (both /
static only / dynamic only, when a run has both kinds), maximum resolution, camera frustums on
or off. The training cameras (grey) and test cameras (orange) are drawn as wireframe
frustums; a click on one moves the clicking browser's camera there and the time to its frame.
With two runs the picture is split: run A left, run B right, the same camera (each half keeps
the browser's vertical field of view), named in the picture; a mode only one run's plugins
provide (ReFlow's flow beside a baseline) is rendered for both with that plugin's renderer, and
"colour scale" gives both flow pictures one saturation speed. Mode captions (depth range, flow
scale) are shown under the frame statistics.
"""
from __future__ import annotations

import socket
import threading
import time
from typing import Sequence

import cv2
import numpy as np
import torch
import viser

from .camera import intrinsics, pose_from_view, scene_up, vertical_fov, view_from_pose
from .frame import ViewerMode
from .render_loop import ClientRenderer
from .runs import SELECTIONS, ViewerRun

MAX_SIDE_RANGE = (64, 4096)  # px, the still picture's longer side: --max_res and the GUI slider alike

HOST = "127.0.0.1"  # localhost only: the viewer has no authentication
SEPARATOR = 4  # px between the two runs' halves
PLAY_FPS = 8.0
TRAIN_COLOR, TEST_COLOR = (120, 120, 120), (255, 140, 0)


def check_port_free(port: int, host: str = HOST) -> None:
    """ValueError naming the port when something listens on it (viser would silently take the next)."""
    if not 0 <= port <= 65535:
        raise ValueError(f"--port must be in [0, 65535], got {port}")
    if port == 0:
        return
    probe = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: TIME_WAIT is no conflict
    try:
        probe.bind((host, port))
    except OSError as exc:
        raise ValueError(f"port {port} on {host} is in use ({exc.strerror}); choose another with --port") from None
    finally:
        probe.close()


def label(picture: np.ndarray, text: str) -> np.ndarray:
    """Write a run's name at the top left of its picture (white on a dark outline), in place."""
    scale = max(0.3, picture.shape[0] / 700.0)
    y = int(18 * scale) + 3
    for colour, width in (((0, 0, 0), 3), ((255, 255, 255), 1)):
        cv2.putText(picture, text, (4, y), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, width, cv2.LINE_AA)
    return picture


class ViewerApp:
    """See the module docstring."""

    def __init__(self, runs: Sequence[ViewerRun], port: int = 8080, max_side: int = 512, mode: str = "RGB",
                 start_time: float | None = None, frustums: bool = True, color_scale: float = 0.0) -> None:
        if not 1 <= len(runs) <= 2:
            raise ValueError(f"the viewer shows one or two runs side by side, got {len(runs)}")
        self.runs = list(runs)
        self.port = port
        self.initial_max_side = max_side
        self.mode_fns: dict[str, ViewerMode] = {}
        for run in self.runs:
            for name, fn in run.modes.items():
                self.mode_fns.setdefault(name, fn)
        if mode not in self.mode_fns:
            raise ValueError(f"--mode {mode!r}: these runs have the modes {', '.join(map(repr, self.mode_fns))}")
        self.initial_mode, self.initial_time, self.initial_frustums = mode, start_time, frustums
        self.initial_color_scale = color_scale
        self.captions: dict[str, str] = {}
        self.dt = min(run.dt for run in self.runs)
        self.server: viser.ViserServer | None = None
        self.renderers: dict[int, ClientRenderer] = {}
        self.playing = False
        self._stop = threading.Event()

    # ------------------------------------------------------------------ pictures
    def draw(self, client: viser.ClientHandle, width: int, height: int) -> np.ndarray:
        """The picture for a client's current camera and the controls' settings."""
        cam = client.camera
        viewmat = view_from_pose(cam.wxyz, cam.position)
        time_value, mode, selection = float(self.time.value), str(self.mode.value), str(self.selection.value)
        count = len(self.runs)
        panel_width = max(8, (width - SEPARATOR * (count - 1)) // count)
        K = intrinsics(cam.fov, panel_width, height)
        panels = []
        for letter, run in zip("AB", self.runs):
            picture, caption = run.render(viewmat, K, panel_width, height, time_value, mode, selection,
                                          mode_fn=None if mode in run.modes else self.mode_fns[mode],
                                          color_scale=float(self.color_scale.value))
            self.captions[f"{letter}: {run.name}" if count > 1 else run.name] = caption
            picture = np.ascontiguousarray(picture)
            panels.append(label(picture, f"{letter}: {run.name}") if count > 1 else picture)
            panels.append(np.full((height, SEPARATOR, 3), 40, np.uint8))
        return np.concatenate(panels[:-1], axis=1)

    # ------------------------------------------------------------------ set-up
    def start(self) -> str:
        """Bind the server, build the controls and the frustums; returns the URL."""
        check_port_free(self.port)
        server = viser.ViserServer(host=HOST, port=self.port, label="4DGS viewer", verbose=False)
        if self.port and server.get_port() != self.port:  # taken between the check and the bind
            server.stop()
            raise ValueError(f"port {self.port} on {HOST} is in use; choose another with --port")
        # localhost only: no share button, and a client's share request (a public tunnel) is refused
        server.request_share_url = lambda verbose=True: None  # type: ignore[method-assign]
        self.server = server
        self._build_gui(server)
        self._add_cameras(server)
        server.on_client_connect(self._connect)
        server.on_client_disconnect(self._disconnect)
        threading.Thread(target=self._tick, daemon=True, name="viewer-tick").start()
        return f"http://{HOST}:{server.get_port()}"

    def _build_gui(self, server: viser.ViserServer) -> None:
        first = self.runs[0]
        start_time = float(first.train_cameras[0].time) if first.train_cameras else 0.0
        start_time = start_time if self.initial_time is None else self.initial_time
        server.gui.configure_theme(dark_mode=True, show_share_button=False)
        server.gui.add_markdown("  \n".join(("**A:** " if len(self.runs) > 1 and i == 0 else "**B:** " if i else "")
                                            + run.summary() for i, run in enumerate(self.runs)))
        with server.gui.add_folder("Time"):
            self.time = server.gui.add_slider("time", min=0.0, max=1.0, step=self.dt, initial_value=start_time)
            self.play = server.gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
        with server.gui.add_folder("Render"):
            self.mode = server.gui.add_dropdown("mode", tuple(self.mode_fns), initial_value=self.initial_mode)
            self.selection = server.gui.add_dropdown("Gaussians", SELECTIONS, initial_value="both",
                                                     visible=any(run.has_split for run in self.runs),
                                                     hint="static / dynamic split of the deformation table")
            self.max_side = server.gui.add_slider("max resolution", min=MAX_SIDE_RANGE[0], max=MAX_SIDE_RANGE[1], step=32,
                                                  initial_value=self.initial_max_side,
                                                  hint="longer side of the still picture, in pixels")
            self.color_scale = server.gui.add_number("colour scale", initial_value=self.initial_color_scale,
                                                     min=0.0, step=0.1,
                                                     hint="speed (px) at full colour in the flow mode; 0 = each picture's own")
            self.show_cameras = server.gui.add_checkbox("camera frustums", initial_value=self.initial_frustums)
        self.stats = server.gui.add_markdown("waiting for the first frame")

        def refresh(_) -> None:
            self._request_all(moving=False)

        for handle in (self.time, self.mode, self.selection, self.max_side, self.color_scale):
            handle.on_update(refresh)

        @self.play.on_click
        def _(_) -> None:
            self.playing = not self.playing
            self.play.label = "Pause" if self.playing else "Play"
            self.play.icon = viser.Icon.PLAYER_PAUSE if self.playing else viser.Icon.PLAYER_PLAY
            self._request_all(moving=False)

        @self.show_cameras.on_update
        def _(_) -> None:
            for frustum in self.frustums:
                frustum.visible = bool(self.show_cameras.value)

    def _add_cameras(self, server: viser.ViserServer) -> None:
        run = self.runs[0]
        cameras = [(c, False) for c in run.train_cameras] + [(c, True) for c in run.test_cameras]
        centres = np.stack([pose_from_view(c.viewmat)[1] for c, _ in cameras])
        spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).max()) if len(centres) > 1 else 0.0
        depth = self._scene_depth(run)
        scale = 0.05 * max(spread, 0.2 * depth)
        up = scene_up([c.viewmat for c, _ in cameras])
        server.scene.set_up_direction(up)
        self.frustums = []
        for camera, is_test in cameras:
            wxyz, position = pose_from_view(camera.viewmat)
            # wireframes only: a frustum textured with its image would cover the render when the
            # browser's camera sits on it (after a click, or at start)
            frustum = server.scene.add_camera_frustum(
                f"/cameras/{'test' if is_test else 'train'}/{camera.image_name}", fov=vertical_fov(camera.K, camera.height),
                aspect=camera.width / camera.height, scale=scale, wxyz=wxyz, position=position,
                thickness=1.5, thickness_units="screen",
                color=TEST_COLOR if is_test else TRAIN_COLOR, visible=self.initial_frustums)
            frustum.on_click(lambda event, cam=camera: self.jump(event.client, cam))
            self.frustums.append(frustum)
        first = cameras[0][0]
        wxyz, position = pose_from_view(first.viewmat)
        forward = np.linalg.inv(first.viewmat.detach().cpu().double().numpy())[:3, 2]
        server.initial_camera.position = position
        server.initial_camera.look_at = position + forward * depth
        server.initial_camera.up = up
        server.initial_camera.fov = vertical_fov(first.K, first.height)

    @staticmethod
    def _scene_depth(run: ViewerRun) -> float:
        """Median camera depth of the Gaussians in the first training camera (orbit distance)."""
        cam = run.train_cameras[0]
        with torch.no_grad():
            means = run.model.get_xyz.detach()
            z = means @ cam.viewmat[:3, 2].to(means) + float(cam.viewmat[2, 3])
        z = z[z > 0]
        return float(z.median()) if z.numel() else 1.0

    # ------------------------------------------------------------------ clients
    def jump(self, client: viser.ClientHandle, camera) -> None:
        """Move a client's camera to a dataset camera and the time to its frame."""
        wxyz, position = pose_from_view(camera.viewmat)
        with client.atomic():
            client.camera.fov = vertical_fov(camera.K, camera.height)
            client.camera.wxyz = wxyz
            client.camera.position = position
        self.time.value = float(camera.time)
        self._request_all(moving=False)

    def _connect(self, client: viser.ClientHandle) -> None:
        renderer = ClientRenderer(client, lambda w, h: self.draw(client, w, h),
                                  max_side=lambda: int(self.max_side.value), playing=lambda: self.playing)
        self.renderers[client.client_id] = renderer
        renderer.start()
        client.camera.on_update(lambda _: renderer.request(moving=True))
        renderer.request(moving=False)

    def _disconnect(self, client: viser.ClientHandle) -> None:
        renderer = self.renderers.pop(client.client_id, None)
        if renderer is not None:
            renderer.stop()

    def _request_all(self, moving: bool) -> None:
        for renderer in list(self.renderers.values()):
            renderer.request(moving)

    def _tick(self) -> None:
        """Advance the time while playing; refresh the frame statistics twice a second."""
        last_stats = 0.0
        while not self._stop.is_set():
            if self.playing:
                value = float(self.time.value) + self.dt
                self.time.value = 0.0 if value > 1.0 + 1e-6 else round(value, 6)
            now = time.perf_counter()
            if now - last_stats > 0.5:
                last_stats = now
                self._show_stats()
            self._stop.wait(1.0 / PLAY_FPS)

    def _show_stats(self) -> None:
        records = [r for renderer in list(self.renderers.values()) for r in list(renderer.records)[-10:]]
        if not records:
            return
        last = records[-1]
        ms = np.median([r.seconds for r in records]) * 1e3
        captions = [f"{name}: {text}" if len(self.runs) > 1 else text
                    for name, text in list(self.captions.items()) if text]
        self.stats.content = "  \n".join([f"last frame {last.width}x{last.height} ({'full' if last.full else 'moving'}), "
                                          f"median render {ms:.0f} ms ({1e3 / max(ms, 1e-3):.1f} fps)", *captions])

    # ------------------------------------------------------------------ life cycle
    def wait(self) -> None:
        """Serve until interrupted (Ctrl-C) or `stop()`."""
        try:
            while not self._stop.wait(0.5):
                pass
        except KeyboardInterrupt:
            print("[view] stopped", flush=True)
        finally:
            self.stop()

    def stop(self) -> None:
        self._stop.set()
        for renderer in list(self.renderers.values()):
            renderer.stop()
        if self.server is not None:
            self.server.stop()
            self.server = None
