"""python -m baselines.export: per-time 3DGS PLYs (read back independently), tracks, bad input,
and the tracks-versus-ground-truth-flow evaluation on the simulator's exact geometry."""
from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from plyfile import PlyData

from baselines.export.cli import main as export_main
from baselines.export.track_eval import track_flow_errors
from baselines.export.tracks import Tracks, load_tracks
from baselines.fourdgs.app import load_run, run_cli
from baselines.fourdgs.renderer import render
from baselines.metrics import psnr
from baselines.render import rasterize
from baselines.synthetic import get_scene
from baselines.synthetic.raycast import cast
from baselines.synthetic.scene import BuiltScene
from baselines.synthetic.simulate import frame_cameras
from reflow_plugin.separation import TIME_CENTER, TIME_LOG_SCALE

INRIA_NAMES = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
SH_C0, SH_C1 = 0.28209479177387814, 0.4886025119029199  # 3DGS's constants


def read_3dgs_ply(path: Path) -> dict[str, np.ndarray]:
    """A minimal 3DGS PLY reader written from the format alone (no project code): activated values."""
    vertex = PlyData.read(str(path))["vertex"]
    names = [p.name for p in vertex.properties]
    column = lambda name: np.asarray(vertex[name], np.float64)  # noqa: E731
    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    count = len(rest) // 3  # coefficients per channel beyond DC, stored channel-major (R..., G..., B...)
    f_rest = np.stack([column(n) for n in rest], 1).reshape(-1, 3, count).transpose(0, 2, 1)
    quats = np.stack([column(f"rot_{i}") for i in range(4)], 1)
    return {
        "names": names,
        "means": np.stack([column(a) for a in "xyz"], 1),
        "sh": np.concatenate([np.stack([column(f"f_dc_{i}") for i in range(3)], 1)[:, None], f_rest], 1),
        "opacity": 1.0 / (1.0 + np.exp(-column("opacity"))),
        "scales": np.exp(np.stack([column(f"scale_{i}") for i in range(3)], 1)),
        "quats": quats / np.linalg.norm(quats, axis=1, keepdims=True),
    }


def sh_colour(sh: np.ndarray, means: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """View-dependent colour of degree <= 3 SH coefficients [N, K, 3] (3DGS's real SH basis and
    its "+ 0.5, clamp at 0" convention), written out term by term."""
    d = means - centre
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x, y, z = d[:, :1], d[:, 1:2], d[:, 2:3]
    xx, yy, zz = x * x, y * y, z * z
    basis = [np.full_like(x, SH_C0), -SH_C1 * y, SH_C1 * z, -SH_C1 * x,
             1.0925484305920792 * x * y, -1.0925484305920792 * y * z, 0.31539156525252005 * (2 * zz - xx - yy),
             -1.0925484305920792 * x * z, 0.5462742152960396 * (xx - yy),
             -0.5900435899266435 * y * (3 * xx - yy), 2.890611442640554 * x * y * z,
             -0.4570457994644658 * y * (4 * zz - xx - yy), 0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy),
             -0.4570457994644658 * x * (4 * zz - xx - yy), 1.445305721320277 * z * (xx - yy),
             -0.5900435899266435 * x * (xx - 3 * yy)]
    colour = sum(basis[k] * sh[:, k] for k in range(sh.shape[1]))
    return np.maximum(colour + 0.5, 0.0)


def _export(*argv: str) -> None:
    assert export_main(list(argv)) == 0


def test_ply_round_trip_renders_the_model_at_that_time(tiny_reflow_run, tmp_path):
    out = tmp_path / "ply"
    _export("-m", str(tiny_reflow_run), "--times", "0", "0.5", "1", "--format", "ply", "-o", str(out))
    loaded = load_run(["-m", str(tiny_reflow_run)])
    model, cam = loaded.trainer.ctx.model, loaded.trainer.test_cameras[-1]
    background = loaded.trainer.ctx.background
    for t in (0.0, 0.5, 1.0):
        ply = read_3dgs_ply(out / f"point_cloud_t{t:.4f}.ply")
        rest = ply["names"][9:-8]
        assert ply["names"][:9] == INRIA_NAMES and ply["names"][-8:] == [
            "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
        assert rest == [f"f_rest_{i}" for i in range(len(rest))]
        active = (model.active_sh_degree + 1) ** 2
        f = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
        colours = sh_colour(ply["sh"][:, :active], ply["means"], cam.camera_center.numpy())
        image = rasterize(f(ply["means"]), f(ply["quats"]), f(ply["scales"]), f(ply["opacity"]), f(colours),
                          cam.viewmat, cam.K, cam.width, cam.height, background=background)[0]
        timed = dataclasses.replace(cam, time=t)
        expected = render(model, timed, "fine", background).image
        assert psnr(image, expected) > 40.0
        with torch.no_grad():  # and it is the deformed model, not the canonical one, where things move
            moved = (model.deform(t, "fine").means - model.get_xyz).norm(dim=1).max()
        assert moved > 0 or t == 0.0


def test_tracks_follow_the_deformation_and_the_temporal_windows(tiny_reflow_run, tmp_path):
    out = tmp_path / "tracks"
    _export("-m", str(tiny_reflow_run), "--format", "tracks", "-o", str(out), "--video_views", "all")
    tracks = load_tracks(out / "tracks.npz")
    model = load_run(["-m", str(tiny_reflow_run)]).trainer.ctx.model
    dynamic = model.deformation_table.nonzero().squeeze(1).numpy()
    assert 0 < len(dynamic) < model.num_gaussians and np.array_equal(tracks.indices, dynamic)
    assert tracks.positions.shape == (12, len(dynamic), 3) and len(tracks.view_frame) == 12
    np.testing.assert_allclose(tracks.times, np.arange(12) / 11, atol=1e-6)
    buffers = model.gaussian_buffers
    centre = buffers[TIME_CENTER][dynamic, 0].numpy()
    sigma = buffers[TIME_LOG_SCALE][dynamic, 0].detach().exp().numpy()
    for k, t in enumerate(tracks.times):
        with torch.no_grad():
            state = model.deform(float(t), "fine")
        np.testing.assert_allclose(tracks.positions[k], state.means[dynamic].numpy(), atol=1e-6)
        held = np.clip(t, *model.time_span)  # outside the training span the deformation holds the edge's state
        window = np.exp(-0.5 * ((held - centre) / sigma) ** 2)  # keyframe copies live around their keyframe
        decided = np.abs(window - 0.5) > 1e-3
        assert np.array_equal(tracks.visible[k][decided], (window >= 0.5)[decided])
    assert tracks.visible.any(0).all() and not tracks.visible.all(), "some copy must be outside its window"
    video = cv2.VideoCapture(str(out / "tracks_all.mp4"))
    frames = int(video.get(cv2.CAP_PROP_FRAME_COUNT))
    ok, first = video.read()
    video.release()
    assert ok and frames == 12 and first.shape[:2] == (128, 128)  # 32x32 views drawn at 4x


def _exit_line(capsys, argv: list[str]) -> str:
    with pytest.raises(SystemExit) as exc:
        run_cli(lambda: export_main(argv))
    assert exc.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


def test_bad_input_gives_one_error_line(tiny_reflow_run, tmp_path, capsys):
    line = _exit_line(capsys, ["-m", str(tmp_path), "--format", "tracks", "-o", str(tmp_path / "o")])
    assert "is not a trained run" in line and str(tmp_path) in line
    line = _exit_line(capsys, ["-m", str(tiny_reflow_run), "--format", "ply", "-o", str(tmp_path / "o")])
    assert "--times" in line
    line = _exit_line(capsys, ["-m", str(tiny_reflow_run), "--format", "ply", "--times", "1.5", "-o", str(tmp_path)])
    assert "[0, 1]" in line
    static = tmp_path / "static_run"  # the same run with every Gaussian labelled static
    shutil.copytree(tiny_reflow_run, static)
    table = static / "point_cloud" / "iteration_30" / "deformation_table.pth"
    torch.save(torch.zeros_like(torch.load(table)), table)
    line = _exit_line(capsys, ["-m", str(static), "--format", "tracks", "-o", str(tmp_path / "o")])
    assert "deformation_table.pth is not the file the run saved there" in line  # the edit is caught
    (table.parent / "manifest.json").unlink()  # unchecked (as a folder from before manifests): the table is read
    line = _exit_line(capsys, ["-m", str(static), "--format", "tracks", "-o", str(tmp_path / "o")])
    assert "no dynamic part" in line
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("flags, message", [
    (["--fps", "0"], "--fps 0: must be >= 1"),
    (["--max_tracks", "-3"], "--max_tracks -3: must be >= 1"),
    (["--trail", "nan"], "--trail nan: must be >= 0"),
])
def test_a_bad_video_flag_is_named_alone(tmp_path, flags, message):
    """One message named --max_tracks, --fps and --trail together, whichever was wrong."""
    from baselines.export.cli import parse_args

    with pytest.raises(ValueError) as exc:
        parse_args(["-m", str(tmp_path), "--format", "tracks", "-o", str(tmp_path / "o"), *flags])
    assert str(exc.value) == message


def _oracle_tracks(scene_dir: Path, frames: list[int]) -> Tracks:
    """Exact surface points seen at the pixel centres of `frames`, moved with their objects over
    every frame (the simulator's own geometry), with the simulator's cameras."""
    spec = get_scene("balloon", frames=12, width=32, height=32, seed=0)
    scene, cams = BuiltScene(spec), frame_cameras(spec)
    placements = [{p.index: p for p in scene.placements(c.time)} for c in cams]
    index, local = [], []
    for f in frames:
        hits = cast(scene.placements(cams[f].time), cams[f].center, cams[f].directions(cams[f].pixel_grid()))
        keep = hits.index >= 0
        index.append(hits.index[keep])
        local.append(hits.local[keep])
    index, local = np.concatenate(index), np.concatenate(local)
    positions = np.zeros((len(cams), len(index), 3))
    for k, by_index in enumerate(placements):
        for obj in np.unique(index):
            rows = index == obj
            m = by_index[int(obj)].to_world
            positions[k, rows] = local[rows] @ m[:3, :3].T + m[:3, 3]
    meta = json.loads((scene_dir / "gt" / "cameras.json").read_text())["frames"]
    test = set(json.loads((scene_dir / "gt" / "split.json").read_text())["test"])
    n = len(index)
    return Tracks(times=np.array([c.time for c in cams], np.float32), positions=positions.astype(np.float32),
                  visible=np.ones((len(cams), n), bool), opacity=np.ones((len(cams), n), np.float32),
                  indices=np.arange(n), colors=np.zeros((n, 3), np.float32), dynamic=np.ones(n, bool),
                  view_frame=np.array([m["frame"] for m in meta]), view_time=np.array([m["time"] for m in meta]),
                  view_test=np.array([m["frame"] in test for m in meta]), view_K=np.array([m["K"] for m in meta]),
                  view_viewmat=np.array([m["viewmat"] for m in meta]),
                  view_size=np.array([(m["width"], m["height"]) for m in meta]))


def test_track_evaluation_on_the_simulators_exact_tracks(tiny_scene):
    tracks = _oracle_tracks(tiny_scene, [0, 8])
    exact = track_flow_errors(tracks, tiny_scene, split="test")
    assert exact["available"] and exact["tracks"] > 20 and [p["frame"] for p in exact["pairs"]] == [0, 8]
    # the surface points at the pixel centres are where the ground-truth flow says they go
    assert exact["median_epe"] < 0.02, exact
    frozen = Tracks(**{**tracks.__dict__, "positions": np.repeat(tracks.positions[:1], len(tracks.times), 0)})
    # static tracks of a moving object explain only the camera's motion: the object's flow is missing
    still = track_flow_errors(frozen, tiny_scene, split="test")
    assert still["median_epe"] > 0.1 and still["median_epe"] > 10 * exact["median_epe"], (still, exact)
    everywhere = track_flow_errors(tracks, tiny_scene, split="test", region="all")
    assert everywhere["tracks"] > exact["tracks"]  # the mask restricts to the moving object
