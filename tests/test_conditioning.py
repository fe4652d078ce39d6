"""Underwater image conditioning (CLAHE) and where the SLAM applies it: before extraction, on every camera."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
from slam_fakes import FakeSequence

from ruslam.slam import SLAMConfig, run
from ruslam.slam.conditioning import ImageConditioning


def _veiled(shape=(120, 160)) -> np.ndarray:
    """A texture seen through a bright veil: 15 grey levels of contrast around 150."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.standard_normal(shape), (0, 0), 2.0)
    return np.clip(150 + 15 * texture / texture.std(), 0, 255).astype(np.uint8)


def test_clahe_restores_contrast_and_none_is_the_identity():
    grey = _veiled()
    assert ImageConditioning()(grey) is grey
    out = ImageConditioning("clahe", clip_limit=3.0)(grey)
    assert out.shape == grey.shape and out.dtype == np.uint8 and out.std() > 2 * grey.std()
    correlation = np.corrcoef(out.ravel().astype(float), grey.ravel().astype(float))[0, 1]
    assert correlation > 0.8  # the same picture, stretched


def test_clahe_on_colour_changes_lightness_and_keeps_the_colour():
    rgb = np.stack([_veiled() // 3, _veiled(), _veiled() // 2], axis=-1)  # green water cast
    out = ImageConditioning("clahe")(rgb)
    lab_in, lab_out = (cv2.cvtColor(x, cv2.COLOR_RGB2LAB).astype(float) for x in (rgb, out))
    assert lab_out[..., 0].std() > 1.5 * lab_in[..., 0].std()
    assert np.abs(lab_out[..., 1:].mean((0, 1)) - lab_in[..., 1:].mean((0, 1))).max() < 6  # a and b barely move
    floats = ImageConditioning("clahe")(rgb.astype(np.float32) / 255)
    assert floats.dtype == np.uint8 and np.abs(floats.astype(int) - out).max() <= 1


def test_auto_stretches_only_flat_frames():
    flat = (_veiled().astype(float) - 150) / 15 * 3 + 150  # std ~3 grey levels: below the 6.0 default
    flat = flat.astype(np.uint8)
    textured = _veiled()  # std ~15
    auto = ImageConditioning("auto")
    assert auto(textured) is textured
    assert auto(flat).std() > 2 * flat.std()
    assert np.array_equal(auto(flat), ImageConditioning("clahe")(flat))


def test_blur_before_clahe_keeps_the_texture_and_not_the_sensor_noise():
    """A flat texture (std 4) under sensor noise (std 2.5): CLAHE stretches both; a 1 px blur first keeps the
    stretched frame closer to the stretched noise-free one."""
    clean = ((_veiled().astype(float) - 150) / 15 * 4 + 150)
    noisy = np.clip(clean + np.random.default_rng(1).normal(0, 2.5, clean.shape), 0, 255).astype(np.uint8)
    reference = ImageConditioning("clahe")(clean.astype(np.uint8)).astype(float)

    def similarity(blur):
        out = ImageConditioning("clahe", blur_sigma=blur)(noisy).astype(float)
        return np.corrcoef(out.ravel(), reference.ravel())[0, 1]

    assert similarity(1.0) > similarity(0.0) + 0.1


def test_bad_options_are_refused():
    with pytest.raises(ValueError, match="none.*clahe"):
        ImageConditioning("retinex")
    with pytest.raises(ValueError, match="clip_limit"):
        ImageConditioning("clahe", clip_limit=0)
    with pytest.raises(ValueError, match="blur_sigma"):
        ImageConditioning("clahe", blur_sigma=-1)


class RecordingExtractor:
    """Returns 10 keypoints whatever the image, and remembers the contrast of what it was given."""

    binary = False

    def __init__(self):
        self.stds = []

    def extract(self, image):
        self.stds.append(float(image.std()))
        return {"keypoints": np.zeros((10, 2), np.float32), "scores": np.ones(10, np.float32),
                "descriptors": np.zeros((10, 8), np.float32)}


class VeiledSequence(FakeSequence):
    def load(self, i):
        return [_veiled((480, 640))]


@pytest.mark.parametrize("method", ["none", "clahe"])
def test_the_slam_conditions_each_frame_before_extraction_and_says_why_it_skips(method, caplog):
    seq = VeiledSequence(num_frames=3, landmarks=10)
    extractor = RecordingExtractor()
    with caplog.at_level(logging.WARNING):
        result = run(seq, extractor, SLAMConfig(progress=False, conditioning=ImageConditioning(method)))
    raw = _veiled((480, 640)).std()
    assert len(result) == 0 and len(extractor.stds) == 3
    assert (min(extractor.stds) > 2 * raw) if method == "clahe" else np.allclose(extractor.stds, raw)
    assert "Frame 1 skipped: 10 keypoints found, the minimum is 50" in caplog.text
