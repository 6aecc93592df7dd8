"""`python -m baselines.prepare VIDEO_OR_FRAME_FOLDER -o data/custom/NAME [options]`.

Every failure the user can act on prints ONE line (`error: ...; try: ...`) and exits with code 2;
`FOURDGS_TRACEBACK=1` shows the traceback instead.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Sequence

# FFmpeg's and OpenCV's own console messages (e.g. "moov atom not found" for a broken .mp4) would
# break the one-line error; our messages say what failed. Set before OpenCV opens a video.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")

from .errors import PrepareError
from .pipeline import FRAME_BUDGET, PrepareOptions, prepare, summary_lines
from .sfm import CAMERA_MODELS, SfmOptions


class _Parser(argparse.ArgumentParser):
    """Argument errors become PrepareError (one line, exit 2)."""

    def error(self, message: str):
        raise PrepareError(message)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="python -m baselines.prepare",
                     description="Video or frame folder -> COLMAP-layout dataset with cameras (pycolmap), "
                                 "times and motion masks, ready for train.py.")
    parser.add_argument("source", type=Path, help="a video file (any format OpenCV reads) or a folder of JPG/PNG frames")
    parser.add_argument("-o", "--output", type=Path, required=True, help="dataset folder to write, e.g. data/custom/NAME")
    parser.add_argument("--fps", type=float, help="keep at most this many frames per second (videos)")
    parser.add_argument("--max-frames", type=int, default=FRAME_BUDGET,
                        help=f"keep at most this many frames, evenly spread (default {FRAME_BUDGET}: "
                             "a few minutes of SfM on 2 cores)")
    parser.add_argument("--size", type=int, default=640, help="frame width in pixels (never upscaled; default 640)")
    parser.add_argument("--masks", default="auto",
                        help="auto (estimate motion masks from the frames), posed (auto, then re-estimated after "
                             "SfM with the registered cameras: more recall, less precision on DAVIS), background "
                             "(auto for SfM, then background subtraction along the homographies of neighbouring "
                             "frames), none, or a folder of masks (non-zero = moving)")
    parser.add_argument("--camera-model", default="SIMPLE_PINHOLE", choices=CAMERA_MODELS,
                        help="COLMAP camera model shared by all frames (distortion is ignored by the readers)")
    parser.add_argument("--overlap", type=int, default=10, help="sequential matching: frames matched ahead (at least 1; default 10)")
    parser.add_argument("--threads", type=int, default=1, help="threads for pycolmap (default 1; -1: every core, COLMAP's convention)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of RANSAC and the mapper (0 to 2**31 - 1)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--no-fixed-centre", dest="fixed_centre", action="store_false",
                        help="refuse a camera that does not move or only turns (by default such a tripod shot is "
                             "written with every frame at one centre, rotations from homographies, depth unknown)")
    return parser


def run(argv: Sequence[str] | None = None) -> dict:
    """Parse, prepare, print the summary; raises PrepareError."""
    args = build_parser().parse_args(argv)
    options = PrepareOptions(source=args.source, output=args.output, fps=args.fps, max_frames=args.max_frames,
                             width=args.size, masks=args.masks, progress=not args.quiet,
                             fixed_centre=args.fixed_centre,
                             sfm=SfmOptions(camera_model=args.camera_model, overlap=args.overlap,
                                            threads=args.threads, seed=args.seed))
    report = prepare(options)
    print("\n".join(summary_lines(report)))
    return report


def main(argv: Sequence[str] | None = None) -> int:
    try:
        run(argv)
    except PrepareError as err:
        if os.environ.get("FOURDGS_TRACEBACK") == "1":
            raise
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
