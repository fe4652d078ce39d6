"""`load_extractor(name_or_path)`: the one door to every extractor of the project."""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import TYPE_CHECKING

from ruslam.errors import InputError, MissingWeights

if TYPE_CHECKING:  # the registry itself stays light: a config check reads EXTRACTORS without importing torch
    from ruslam.models.extractor import Extractor

# name -> "module:Class"; imported lazily so that e.g. ORB does not import torch models.
EXTRACTORS = {
    "orb": "ruslam.models.classical:ORB",
    "sift": "ruslam.models.classical:SIFT",
    "uwnet_xfeat": "ruslam.models.uwnet_extractor:UWNetExtractor",
    "uwnet_xfeat_s4": "ruslam.models.uwnet_extractor:UWNetFineCellExtractor",
    "uwnet_mobilenet": "ruslam.models.uwnet_extractor:UWNetMobileNetExtractor",
    "xfeat": "ruslam.models.pretrained.xfeat:XFeat",
    "superpoint": "ruslam.models.pretrained.superpoint:SuperPoint",
    "aliked": "ruslam.models.pretrained.aliked_disk:ALIKED",  # ALIKED-n16rot
    "aliked-n16": "ruslam.models.pretrained.aliked_disk:ALIKEDN16",
    "aliked-t16": "ruslam.models.pretrained.aliked_disk:ALIKEDT16",
    "aliked-n32": "ruslam.models.pretrained.aliked_disk:ALIKEDN32",
    "disk": "ruslam.models.pretrained.aliked_disk:DISK",
}


def register(name: str, target: str) -> None:
    EXTRACTORS[name] = target


def load_extractor(name_or_path: str | Path, device: str = "cpu", **conf) -> Extractor:
    """Build an extractor by registry name (``orb``, ``sift``, ``xfeat``, ``uwnet_xfeat``...) or weights path."""
    key = str(name_or_path)
    if key in EXTRACTORS:
        module, cls = EXTRACTORS[key].split(":")
        klass = getattr(importlib.import_module(module), cls)
        if getattr(klass, "uses_device", False):
            conf["device"] = device
        return klass(**conf)
    path = Path(key)
    if path.suffix in (".pt", ".pth", ".ckpt"):
        if not path.is_file():
            raise MissingWeights(f"Extractor weights file {path} does not exist.")
        from ruslam.models.uwnet_extractor import UWNetExtractor  # noqa: PLC0415 (optional heavy import)

        return UWNetExtractor.from_file(path, device=device, **conf)
    raise InputError(f"Unknown extractor {key!r}; expected a weights file or one of {sorted(EXTRACTORS)}.")
