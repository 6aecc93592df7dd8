"""Dataset readers (nvidia, dnerf, hypernerf, colmap, panoptic) producing cameras in our convention.

    scene = load_scene("data/nvidia/Balloon1", images="images_2", eval=True)
    points, source = initial_point_cloud(scene)   # "dataset" | "triangulated" | "random"

Every camera is world->camera with OpenCV axes and pixel centres at +0.5 (see `geometry.py`).
Every bad input raises `DatasetError` (a `ValueError`) naming the file, before the long work.
"""
from __future__ import annotations

import importlib

from .errors import DatasetError

# Names are imported on first use (PEP 562) so that torch-free users of the submodules (optical
# flow, motion masks, COLMAP helpers: `python -m baselines.prepare`) do not pay torch's import.
_LAZY = {
    "Camera": "cameras", "PointCloud": "pointcloud", "SceneInfo": "scene_info", "Triangulation": "triangulation",
    "detect_dataset_type": "loader", "initial_point_cloud": "initial_points", "load_scene": "loader",
    "nerfpp_normalization": "scene_info", "random_point_cloud": "initial_points",
    "triangulate_static_points": "triangulation",
}


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "Camera", "DatasetError", "PointCloud", "SceneInfo", "Triangulation", "detect_dataset_type",
    "initial_point_cloud", "load_scene", "nerfpp_normalization", "random_point_cloud",
    "triangulate_static_points",
]
