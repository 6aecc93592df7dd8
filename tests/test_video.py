"""Novel-time videos of odd-sized frames keep every rendered pixel (padded, never cropped)."""
from __future__ import annotations

import cv2
import numpy as np
import torch

from baselines.data.cameras import Camera
from baselines.fourdgs.evaluate import pad_to_even, render_video
from tests._model_helpers import make_model


def test_pad_to_even_repeats_the_last_row_and_column():
    frame = np.arange(3 * 5 * 3, dtype=np.uint8).reshape(3, 5, 3)
    padded = pad_to_even(frame)
    assert padded.shape == (4, 6, 3)
    assert np.array_equal(padded[:3, :5], frame)
    assert np.array_equal(padded[3, :5], frame[2]) and np.array_equal(padded[:3, 5], frame[:, 4])
    even = np.zeros((4, 6, 3), np.uint8)
    assert pad_to_even(even) is even


def test_odd_sized_video_is_padded_not_cropped(tmp_path):
    width, height = 25, 15
    K = torch.tensor([[20.0, 0, width / 2], [0, 20.0, height / 2], [0, 0, 1]])
    viewmat = torch.eye(4)
    viewmat[2, 3] = 4.0
    cameras = [Camera(uid=k, image_name=f"{k}", width=width, height=height, K=K, viewmat=viewmat, time=k / 2)
               for k in range(3)]
    path = render_video(make_model(count=30), cameras, "fine", torch.zeros(3), tmp_path / "video.mp4", "cpu")
    capture = cv2.VideoCapture(str(path))
    ok, frame = capture.read()
    capture.release()
    assert ok and frame.shape[:2] == (height + 1, width + 1)  # 25x15 -> 26x16, nothing cropped
