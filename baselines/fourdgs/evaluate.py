"""Evaluation and rendering outputs in 4DGS's layout.

    <model>/<split>/ours_<iter>/renders/00000.png   rendered test (or train) views
    <model>/<split>/ours_<iter>/gt/00000.png        ground truth
    <model>/<split>/ours_<iter>/depth/00000.png     expected depth, colour-mapped (near = bright)
    <model>/<split>/ours_<iter>/views.json          ours: each PNG's camera, {"00000.png": image_name}
    <model>/video/ours_<iter>/video_rgb.mp4         novel-time video (scene.video_cameras)
    <model>/results.json, per_view.json             metrics as 4DGS's metrics.py writes them

results.json = {"ours_<iter>": {"PSNR", "SSIM", "LPIPS-vgg", "LPIPS-alex"}} and per_view.json the
same keys mapping image name -> value. LPIPS is null when the lpips package or its weights are
unavailable, and results.json then says why under "LPIPS_unavailable"; it is never faked.

Dynamic-region metrics (ours): when the dataset has motion masks (or ground-truth masks for
evaluation only, `Camera.evaluation_mask`), "PSNR-dynamic" / "SSIM-dynamic"
are computed inside each test view's mask and "PSNR-static" / "SSIM-static" outside it (SSIM: the
3DGS SSIM map averaged over those pixels). Full-image PSNR is dominated by the static background;
these say whether the moving object is there at all. A view whose mask is empty (or full) has
null for the region it lacks; the means are over the views that have the region.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from baselines.metrics import lpips_or_reason, psnr, ssim, ssim_map

from .renderer import render

if TYPE_CHECKING:
    from baselines.data import Camera

    from .gaussian_model import GaussianModel


@dataclass
class EvalResult:
    """Per-view and mean metrics of one split."""

    per_view: dict[str, dict[str, float | None]] = field(default_factory=dict)
    mean: dict[str, float | None] = field(default_factory=dict)
    lpips_unavailable: str | None = None
    render_ms: float = 0.0


def _synchronize(like: Tensor | None) -> None:
    """Wait for the GPU when `like` lives on CUDA (timing); nothing on the CPU."""
    if like is not None and like.device.type == "cuda":
        torch.cuda.synchronize(like.device)


def to_uint8(image: Tensor) -> np.ndarray:
    """[H, W, 3] float in [0, 1] -> [H, W, 3] uint8 BGR for OpenCV."""
    rgb = (image.detach().clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
    return np.ascontiguousarray(rgb[..., ::-1])


def pad_to_even(frame: np.ndarray) -> np.ndarray:
    """[H, W, C] -> [H + H % 2, W + W % 2, C], the last row/column repeated (video encoders need even sizes)."""
    h, w = frame.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return frame
    return cv2.copyMakeBorder(frame, 0, h % 2, 0, w % 2, cv2.BORDER_REPLICATE)


def depth_to_color(depth: Tensor, alpha: Tensor) -> np.ndarray:
    """Colour-mapped inverse depth ([H, W, 1] each) -> [H, W, 3] uint8 BGR; empty pixels black."""
    inv = torch.where(alpha > 0.5, 1.0 / depth.clamp(min=1e-6), torch.zeros_like(depth))[..., 0]
    valid = inv[alpha[..., 0] > 0.5]
    lo, hi = (float(valid.min()), float(valid.max())) if valid.numel() else (0.0, 1.0)
    norm = ((inv - lo) / max(hi - lo, 1e-12)).clamp(0, 1)
    gray = (norm * 255).to(torch.uint8).cpu().numpy()
    colored = cv2.applyColorMap(gray, cv2.COLORMAP_TURBO)
    colored[(alpha[..., 0] <= 0.5).cpu().numpy()] = 0
    return colored


def write_png(path: Path, image_bgr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image_bgr):
        raise OSError(f"could not write {path}")


@torch.no_grad()
def evaluate_cameras(
    model: GaussianModel,
    cameras: Sequence[Camera],
    stage: str,
    background: Tensor,
    backend: str = "auto",
    out_dir: Path | None = None,
) -> EvalResult:
    """Render every camera, compute PSNR/SSIM/LPIPS against its image, optionally save PNGs.

    Args:
        out_dir: when given, renders/, gt/ and depth/ are written inside it (00000.png, ...).
    `render_ms` is the mean wall time per view after one untimed warm-up render (a fresh process
    otherwise counts loading the compiled kernel and first allocations as render time).
    """
    result = EvalResult()
    sums: dict[str, list[float]] = {"PSNR": [], "SSIM": [], "LPIPS-vgg": [], "LPIPS-alex": []}
    if cameras:
        render(model, cameras[0], stage, background, backend)
    elapsed = 0.0
    for idx, cam in enumerate(cameras):
        _synchronize(background)  # on CUDA the clock must wait for the kernels it times
        start = time.perf_counter()
        view = render(model, cam, stage, background, backend)
        _synchronize(background)
        elapsed += time.perf_counter() - start
        image = view.image.clamp(0, 1)
        gt = cam.image
        name = f"{idx:05d}.png"
        row: dict[str, float | None] = {"PSNR": float(psnr(image, gt)), "SSIM": float(ssim(image, gt))}
        for net in ("vgg", "alex"):
            value, reason = lpips_or_reason(image, gt, net=net)
            row[f"LPIPS-{net}"] = None if value is None else float(value)  # a 0-dim tensor: not JSON
            result.lpips_unavailable = reason or result.lpips_unavailable
        if cam.evaluation_mask is not None:
            row.update(region_metrics(image, gt, cam.evaluation_mask))
        result.per_view[name] = row
        for key, value in row.items():
            if value is not None:
                sums.setdefault(key, []).append(value)
        if out_dir is not None:
            write_png(out_dir / "renders" / name, to_uint8(image))
            write_png(out_dir / "gt" / name, to_uint8(gt))
            write_png(out_dir / "depth" / name, depth_to_color(view.depth, view.alpha))
    result.mean = {k: (sum(v) / len(v) if v else None) for k, v in sums.items()}
    for row in result.per_view.values():  # every view lists every metric (null where it has none)
        for key in result.mean:
            row.setdefault(key, None)
    result.render_ms = 1000.0 * elapsed / max(1, len(cameras))
    if out_dir is not None and cameras:  # the PNGs are numbered: say which view each one is
        _write_json(out_dir / VIEWS_FILE, {f"{idx:05d}.png": cam.image_name for idx, cam in enumerate(cameras)})
    return result


REGIONS = ("dynamic", "static")
VIEWS_FILE = "views.json"


def region_metrics(image: Tensor, gt: Tensor, mask: Tensor) -> dict[str, float | None]:
    """PSNR and SSIM inside (dynamic) and outside (static) a [H, W] motion mask (1 = dynamic).

    image, gt: [H, W, 3] in [0, 1]. SSIM is the 3DGS SSIM map averaged over the region's pixels.
    A region with no pixel gets None.
    """
    dynamic = mask.to(image.device) > 0.5
    ssim_values = ssim_map(image, gt).mean(dim=-1)  # [H, W]
    out: dict[str, float | None] = {}
    for region, selected in zip(REGIONS, (dynamic, ~dynamic)):
        if not bool(selected.any()):
            out[f"PSNR-{region}"] = out[f"SSIM-{region}"] = None
            continue
        out[f"PSNR-{region}"] = float(psnr(image, gt, mask=selected))
        out[f"SSIM-{region}"] = float(ssim_values[selected].mean())
    return out


def write_metrics(model_path: Path, method: str, result: EvalResult) -> None:
    """Merge one method's metrics into results.json / per_view.json (atomic writes)."""
    summary = _read_json(model_path / "results.json")
    per_view = _read_json(model_path / "per_view.json")
    summary[method] = dict(result.mean)
    summary[method]["render_ms_per_view"] = result.render_ms
    if result.lpips_unavailable:
        summary[method]["LPIPS_unavailable"] = result.lpips_unavailable
    metrics = list(result.mean)
    per_view[method] = {m: {name: row[m] for name, row in result.per_view.items()} for m in metrics}
    _write_json(model_path / "results.json", summary)
    _write_json(model_path / "per_view.json", per_view)


@torch.no_grad()
def render_video(
    model: GaussianModel, cameras: Sequence[Camera], stage: str, background: Tensor, path: Path,
    backend: str = "auto", fps: int = 30,
) -> Path:
    """Render cameras in order into an mp4 (see `write_video`)."""
    if not cameras:
        raise ValueError("render_video needs at least one camera")
    frames = (to_uint8(render(model, cam, stage, background, backend).image) for cam in cameras)
    return write_video(frames, path, fps)


def write_video(frames: Iterable[np.ndarray], path: Path, fps: int = 30) -> Path:
    """Write [H, W, 3] uint8 BGR frames (all one size) into an mp4 (OpenCV 'mp4v'), through a temp
    name renamed at the end.

    The encoder needs even sizes and would crop an odd row/column (240x135 -> 240x134): odd-sized
    frames are padded instead (edge pixels repeated), so every rendered pixel is in the video.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)
    writer, size = None, None
    try:
        for frame in frames:
            frame = pad_to_even(frame)
            if writer is None:
                size = (frame.shape[1], frame.shape[0])
                writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
                if not writer.isOpened():
                    raise OSError(f"OpenCV could not open a video writer for {path}")
            elif (frame.shape[1], frame.shape[0]) != size:
                raise ValueError(f"write_video: frame of size {frame.shape[1]}x{frame.shape[0]}, expected {size[0]}x{size[1]}")
            writer.write(frame)
    finally:
        if writer is not None:
            writer.release()
    if writer is None:
        raise ValueError(f"write_video: no frames for {path}")
    tmp.replace(path)
    return path


def _read_json(path: Path) -> dict:
    if not path.exists():
        return {}
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON ({exc}); move it away to re-create it") from exc


def _write_json(path: Path, obj: dict) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        tmp.write_text(json.dumps(obj, indent=1, sort_keys=True))
        tmp.replace(path)
    except OSError as err:  # a full disk: name the file (the OS error alone does not), leave no temporary
        tmp.unlink(missing_ok=True)
        raise OSError(err.errno, f"cannot write {path}: {err.strerror or err}") from None
