"""The training data agree with the synthesis (invalid depth is infinitely far) and the teacher cache is built on
the trainer's accelerator."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from ruslam.data.synthesis import PseudoUnderwater
from ruslam.training import datamodule as dm


class _Targets:
    def read(self, image_id):
        return {"keypoint_logits": np.zeros((65, 4, 6), np.float32)}


def _sample(rgb_where_invalid: float) -> list[dict]:
    image = np.full((32, 48, 3), 0.5, np.float32)
    depth = np.full((32, 48), 2.0, np.float32)
    depth[:, 30:] = np.nan  # no depth: open water behind the scene
    image[:, 30:] = rgb_where_invalid
    return [{"id": "a", "image": image, "depth": depth}]


def test_invalid_depth_shows_pure_background_light_in_training_samples():
    """At infinite range the direct term vanishes, so what the in-air image holds there must not matter; the
    old code put those pixels at the image's largest depth (2 m here), where the scene is still visible."""
    synthesis = PseudoUnderwater(seed=0, water_types=["1C"])
    outputs = [dm.DistillationDataset(_sample(v), [0], _Targets(), synthesis)[0]["image"] for v in (0.0, 1.0)]
    assert torch.allclose(outputs[0], outputs[1], atol=1e-6)


def test_teacher_cache_is_built_on_the_trainers_device(monkeypatch, tmp_path):
    module = dm.DistillationDataModule(source={"_target_": "x"}, teacher={"_target_": "y"}, cache_root=str(tmp_path))
    assert module._cache_device() == {}  # no trainer: build_cache's defaults
    module.trainer = SimpleNamespace(strategy=SimpleNamespace(root_device=torch.device("cuda", 1)))
    assert module._cache_device() == {"accelerator": "gpu", "devices": [1]}
    module.trainer = SimpleNamespace(strategy=SimpleNamespace(root_device=torch.device("cpu")))
    calls = []
    monkeypatch.setattr(dm, "instantiate", lambda conf: object())
    monkeypatch.setattr(module, "_source", lambda: "source")
    monkeypatch.setattr("ruslam.data.teacher_cache.build_cache", lambda *a, **kw: calls.append(kw))
    module.prepare_data()
    assert calls and calls[0]["accelerator"] == "cpu" and calls[0]["devices"] == 1
