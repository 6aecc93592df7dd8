"""Dataset readers (nvidia, dnerf, hypernerf, colmap) producing cameras in our convention.

    scene = load_scene("data/nvidia/Balloon1", images="images_2", eval=True)
    points, source = initial_point_cloud(scene)   # "dataset" | "triangulated" | "random"

Every camera is world->camera with OpenCV axes and pixel centres at +0.5 (see `geometry.py`).
Every bad input raises `DatasetError` (a `ValueError`) naming the file, before the long work.
"""
from .cameras import Camera
from .errors import DatasetError
from .initial_points import initial_point_cloud, random_point_cloud
from .loader import detect_dataset_type, load_scene
from .pointcloud import PointCloud
from .scene_info import SceneInfo, nerfpp_normalization
from .triangulation import Triangulation, triangulate_static_points

__all__ = [
    "Camera", "DatasetError", "PointCloud", "SceneInfo", "Triangulation", "detect_dataset_type",
    "initial_point_cloud", "load_scene", "nerfpp_normalization", "random_point_cloud",
    "triangulate_static_points",
]
