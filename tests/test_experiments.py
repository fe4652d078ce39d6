"""`experiment=uwnet_xfeat` builds and trains the shipped UWNet's architecture: the weights file it writes carries
the shipped file's config, key for key."""

from pathlib import Path

import torch
from conftest import ROOT, compose
from hydra.utils import instantiate

from ruslam.models.export import export_weights
from ruslam.train import train

SHIPPED = ROOT / "ruslam" / "weights" / "uwnet_xfeat.pt"
TINY = ["data.num_images=6", "data.height=64", "data.width=96", "datamodule.image_size=null",
        "datamodule.limit_images=null", "datamodule.val_size=2", "datamodule.batch_size=2",
        "datamodule.num_workers=0", "teacher.global_head.fit_images=4", "trainer.enable_progress_bar=false",
        "~callbacks.progress_bar", "+trainer.fast_dev_run=true"]


def _shipped_config() -> dict:
    return torch.load(SHIPPED, map_location="cpu", weights_only=True)["config"]


def test_shipped_experiment_builds_the_shipped_architecture(tmp_path):
    cfg = compose("train", ["experiment=uwnet_xfeat", f"out_dir={tmp_path}"])
    assert cfg.teacher.local.model == "aliked-n16rot"
    net = instantiate(cfg.model.net)
    assert net.config == _shipped_config()
    written = torch.load(export_weights(net, tmp_path / "uwnet.pt"), map_location="cpu", weights_only=True)
    assert written["config"] == _shipped_config()
    # the network it builds loads the shipped weights strictly
    shipped_state = torch.load(SHIPPED, map_location="cpu", weights_only=True)["state_dict"]
    net.load_state_dict({k: v.float() for k, v in shipped_state.items()}, strict=True)


def test_shipped_experiment_trains_and_writes_the_shipped_config(tmp_path: Path):
    cache = tmp_path / "cache"
    cfg = compose("train", ["experiment=uwnet_xfeat", f"out_dir={tmp_path}", f"datamodule.cache_root={cache}", *TINY])
    loss = train(cfg)
    assert loss == loss  # finite
    written = torch.load(tmp_path / "uwnet.pt", map_location="cpu", weights_only=True)
    assert written["config"] == _shipped_config()
