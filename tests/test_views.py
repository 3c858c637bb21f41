"""`train --augment auto`: one fixed camera or views that vary, told from the frames themselves."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fcnpose_tf.data.views import FIXED_CAMERA_MAX_VARIATION, choose_augment, view_variation
from fcnpose_tf.errors import UserError


def _texture(rng: np.random.Generator, size=(240, 320)) -> np.ndarray:
    """A room-like background: smooth random shapes and light."""
    small = rng.uniform(0, 255, (6, 8, 3)).astype(np.float32)
    return cv2.resize(small, size[::-1], interpolation=cv2.INTER_CUBIC).clip(0, 255).astype(np.uint8)


def _frames(tmp_path, fixed: bool, n=30, seed=0) -> list:
    rng = np.random.default_rng(seed)
    background = _texture(rng)
    paths = []
    for i in range(n):
        img = (background if fixed else _texture(rng)).astype(np.float32)
        img = img * rng.uniform(0.6, 1.4) + rng.uniform(-30, 30)          # exposure and light change
        x, y = rng.integers(40, 280), rng.integers(40, 200)                # the arm moves in every frame
        cv2.rectangle(img, (int(x) - 30, int(y) - 60), (int(x) + 30, int(y) + 60), (230, 230, 230), -1)
        img += rng.normal(0, 6, img.shape)                                 # sensor noise
        path = tmp_path / f"f{i:03d}.png"
        cv2.imwrite(str(path), img.clip(0, 255).astype(np.uint8))
        paths.append(path)
    return paths


def test_one_fixed_camera_chooses_the_paper_copies(tmp_path):
    variation = view_variation(_frames(tmp_path, fixed=True))
    assert variation <= FIXED_CAMERA_MAX_VARIATION / 2
    assert choose_augment(variation) == "paper"


def test_views_that_vary_choose_online_augmentation(tmp_path):
    variation = view_variation(_frames(tmp_path, fixed=False))
    assert variation > FIXED_CAMERA_MAX_VARIATION * 1.3
    assert choose_augment(variation) == "online"


def test_a_sample_of_frames_is_read_and_one_frame_is_fixed(tmp_path):
    paths = _frames(tmp_path, fixed=True, n=12)
    assert view_variation(paths[:1]) == 0.0
    assert view_variation(paths, sample=5) != view_variation(paths, sample=12)  # only the sample is read
    paths[0].write_bytes(b"not an image")
    with pytest.raises(UserError, match=r"f000.png: cannot be read as an image"):
        view_variation(paths)
