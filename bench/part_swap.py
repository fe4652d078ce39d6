"""Which part separates UWNet/XFeat from ALIKED: one extractor's keypoints with the other's descriptors.

    .venv/bin/python bench/part_swap.py task=matching \
        'extractors=[xfeat,aliked,aliked_kp_xfeat_desc,xfeat_kp_aliked_desc,uwnet_xfeat,aliked_kp_uwnet_desc]'

Any `evaluate.py task=matching` override works (dataset, rotation_tta...). `aliked_kp_xfeat_desc`: ALIKED-n16rot's
keypoints with XFeat's dense descriptors sampled at them (the project's convention); `xfeat_kp_aliked_desc`: XFeat's
keypoints with ALIKED's SDDH descriptors computed at them; `aliked_kp_uwnet_desc`: ALIKED's keypoints with the shipped
UWNet's dense descriptors sampled at them. Result (BENCHMARKS.md, `bench/part_swap.py`): the keypoints carry the
difference.
"""

from __future__ import annotations

import hydra
import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import DictConfig

from ruslam.cli import run_cli
from ruslam.evaluate import evaluate
from ruslam.models import registry
from ruslam.models.extractor import Extractor, sample_descriptors, to_float_rgb
from ruslam.models.pretrained.aliked_disk import ALIKED
from ruslam.models.pretrained.xfeat import STRIDE, XFeat, pad_to_multiple
from ruslam.models.uwnet_extractor import UWNetExtractor


class _Swap(Extractor):
    default_conf = {"device": "cpu"}
    uses_device = True

    def __init__(self, **conf):
        super().__init__(**conf)
        self.aliked, self.xfeat = ALIKED(), XFeat(vlad_codebook=None)


class ALIKEDKeypointsXFeatDescriptors(_Swap):
    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> dict[str, np.ndarray]:
        out = self.aliked.extract(image)
        x = pad_to_multiple(torch.from_numpy(to_float_rgb(image)).permute(2, 0, 1)[None], STRIDE)
        _, dense, _ = self.xfeat.teacher.run(x)
        out["descriptors"] = sample_descriptors(dense, torch.from_numpy(out["keypoints"])[None], STRIDE)[0].numpy()
        return out


class XFeatKeypointsALIKEDDescriptors(_Swap):
    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> dict[str, np.ndarray]:
        out = self.xfeat.extract(image)
        rgb = to_float_rgb(image)
        h, w = rgb.shape[:2]
        net = self.aliked.net
        feature_map, _ = net.extract_dense_map(torch.from_numpy(rgb).permute(2, 0, 1)[None])
        normalized = 2.0 * torch.from_numpy(out["keypoints"]) / torch.tensor([w - 1, h - 1]) - 1  # ALIKED's own
        out["descriptors"] = F.normalize(net.desc_head(feature_map, [normalized])[0][0], dim=-1).numpy()
        return out


class ALIKEDKeypointsUWNetDescriptors(Extractor):
    default_conf = {"device": "cpu"}
    uses_device = True

    def __init__(self, **conf):
        super().__init__(**conf)
        self.aliked, self.uwnet = ALIKED(), UWNetExtractor()

    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> dict[str, np.ndarray]:
        out = self.aliked.extract(image)
        net_out, (h, w), (nh, nw) = self.uwnet.run(image)  # at UWNet's working size
        xy = (torch.from_numpy(out["keypoints"]) + 0.5) * torch.tensor([nw / w, nh / h]) - 0.5  # UWNet's pixels
        out["descriptors"] = sample_descriptors(net_out["dense_descriptors"], xy[None], STRIDE)[0].numpy()
        return out


registry.register("aliked_kp_xfeat_desc", f"{__name__}:ALIKEDKeypointsXFeatDescriptors")
registry.register("xfeat_kp_aliked_desc", f"{__name__}:XFeatKeypointsALIKEDDescriptors")
registry.register("aliked_kp_uwnet_desc", f"{__name__}:ALIKEDKeypointsUWNetDescriptors")


@hydra.main(version_base="1.3", config_path="../conf", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    run_cli(evaluate, cfg)


if __name__ == "__main__":
    main()
