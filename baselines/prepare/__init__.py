"""From a video (or a folder of frames) to a dataset the readers load: `python -m baselines.prepare`.

    python -m baselines.prepare clip.mp4 -o data/custom/clip [--fps F] [--max-frames N] [--size W]
                                                             [--masks auto|none|FOLDER]
    python train.py -s data/custom/clip

Modules, one stage each: `frames` (OpenCV extraction, resize, subsampling), `parallax` (does the
camera move? why did SfM fail?), `masks` (motion masks without cameras, or the user's),
`sfm` (pycolmap: SIFT, sequential matching, incremental mapping, one shared camera), `dataset`
(COLMAP layout + times.json + motion_masks/), `report` (prepare_report.json, summary), `cache`
(stage reuse), `pipeline` (the order), `evaluate` (pose error against known cameras).
"""
from .errors import PrepareError
from .pipeline import PrepareOptions, prepare

__all__ = ["PrepareError", "PrepareOptions", "prepare"]
