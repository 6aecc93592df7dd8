"""Stage 5: `prepare_report.json` and the printed summary.

The report says what was extracted, which frames were registered, which were dropped and why,
the mean reprojection error (pixels), the number of 3D points, the shared camera, the parallax
check, which masks the dataset got ("stage": posed, pre-sfm or given) and their coverage, which stages were reused, and the options used.
"""
from __future__ import annotations

import json
from pathlib import Path


def model_statistics(model) -> dict:
    """Registered images, points, mean reprojection error and track length of a reconstruction."""
    camera = next(iter(model.cameras.values()))
    return {"registered_frames": int(model.num_reg_images()), "points": int(model.num_points3D()),
            "mean_reprojection_error_px": float(model.compute_mean_reprojection_error()),
            "mean_track_length": float(model.compute_mean_track_length()),
            "camera": {"model": getattr(camera.model, "name", str(camera.model)), "width": int(camera.width),
                       "height": int(camera.height), "params": [float(p) for p in camera.params]}}


def write_report(out: Path, report: dict) -> Path:
    """`out/prepare_report.json`."""
    path = out / "prepare_report.json"
    path.write_text(json.dumps(report, indent=1))
    return path


def _mapper_line(mapper: dict | None) -> str:
    """Which mapper gave the model, and what each one registered (frames, error)."""
    if not mapper:
        return "incremental"
    if mapper.get("fixed_centre") is not None:
        fixed = mapper["fixed_centre"]
        why = ("the camera does not move" if mapper.get("reason") == "static" else
               "the camera only turns; structure from motion placed "
               f"{(mapper.get('global') or mapper.get('incremental') or [0])[0]} frames")
        focal = "fitted to the turn" if fixed.get("focal_estimated") else "COLMAP's prior, 1.2 x the larger side"
        return (f"fixed centre ({why}): every frame at one centre, turning up to {fixed['max_rotation_deg']:.1f} "
                f"degrees, focal length {fixed['focal_px']:.1f} px ({focal}); depth unknown, so views away from "
                "the camera are not constrained")
    parts = [f"{mapper['used']} kept"]
    breaks = mapper.get("path_breaks", {})
    for name in ("incremental", "global"):
        if mapper.get(name) is not None:
            frames, error = mapper[name]
            parts.append(f"{name} {frames} frames" + (f" at {error:.3f} px" if frames else "")
                         + (f" (longest continuous path; {breaks[name]} jumps)" if breaks.get(name) else ""))
    line = "; ".join(parts) if mapper.get("global") is not None else f"{mapper['used']} ({parts[1]})"
    off_path = mapper.get("off_path") or []
    return line + (f"; {len(off_path)} frames off the camera path dropped" if off_path else "")


def _masks_line(masks: dict) -> str:
    """Which masks the dataset got, and the pre-SfM ones' coverage when the posed stage replaced them."""
    line = f"{masks['source']}"
    if masks.get("stage") == "background":
        along = "neighbouring frames' homographies" if masks.get("window") else "the fixed centre's homographies"
        line += f" (background subtraction along {along}; pre-SfM masks {masks['pre_sfm']['mean_coverage']:.1%})"
    elif masks.get("stage") == "posed":
        line += " (re-estimated with the cameras"
        if masks.get("pre_sfm"):
            line += f"; pre-SfM masks {masks['pre_sfm']['mean_coverage']:.1%}"
        line += ")"
    return f"{line}, mean coverage {masks['mean_coverage']:.1%}"


def summary_lines(report: dict) -> list[str]:
    """Human summary of a report (printed at the end of a run)."""
    lines = [f"prepare: {report['registered_frames']}/{report['extracted_frames']} frames registered, "
             f"mean reprojection error {report['mean_reprojection_error_px']:.3f} px, "
             f"{report['points']} points, camera {report['camera']['model']} "
             f"f={report['camera']['params'][0]:.1f} px ({report['camera']['width']}x{report['camera']['height']})",
             f"  mapper: {_mapper_line(report.get('mapper'))}",
             f"  masks: {_masks_line(report['masks'])}"]
    dropped = report["dropped"]
    if dropped:
        lines.append(f"  dropped {len(dropped)} frame(s): " + ", ".join(f"{d['frame']} ({d['reason']})" for d in dropped[:8])
                     + (" ..." if len(dropped) > 8 else ""))
    else:
        lines.append("  dropped: none")
    if report["reused_stages"]:
        lines.append(f"  reused: {', '.join(report['reused_stages'])}")
    lines.append(f"  dataset: {report['output']}  (python train.py -s {report['output']})")
    return lines
