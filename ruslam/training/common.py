"""What the Lightning trainer (`ruslam.train`) and the online trainer (`ruslam.training.online`) share: the weights
a fine-tuning run starts from, and the report of held-out losses before and after training."""

from __future__ import annotations

from pathlib import Path

import torch

from ruslam.errors import InputError
from ruslam.models.export import load_uwnet

REPORTED = (("val/detector", "detector (L3, soft CE)"), ("val/local", "local descriptors (L2)"),
            ("val/global", "global descriptor (L1)"), ("val/correspondence", "correspondence (InfoNCE)"),
            ("val/reliability", "reliability (BCE)"), ("val/repeatability", "repeatability (1 - correlation)"),
            ("val/loss", "total"))

# Blocks a fine-tuning run may add to the weights it starts from: zero-initialised, so the start is unchanged.
GROWABLE = {"keypoint_neighbourhood": "kp_neighbours.", "keypoint_cell": "kp_fine_"}


def load_initial_weights(net: torch.nn.Module, path: str | Path) -> None:
    """Fine-tuning: start from trained weights (exported .pt or Lightning .ckpt); unlike ckpt_path, the optimizer,
    learning rate and epoch count start afresh from the config."""
    source = load_uwnet(path)
    differ = [k for k in net.config if source.config.get(k) != net.config[k]]
    added = [k for k in differ if k in GROWABLE and net.config[k]]  # the rebuilt source has every key: False there
    if set(differ) - set(added):
        k = next(k for k in differ if k not in added)
        raise InputError(f"init_weights={path} holds a UWNet with {k}={source.config.get(k)!r}, but the configured "
                         f"model has {k}={net.config[k]!r}; use weights of the same architecture.")
    missing, unexpected = net.load_state_dict(source.state_dict(), strict=False)
    grown = tuple(GROWABLE[k] for k in added)
    if unexpected or any(not k.startswith(grown) for k in missing):  # only the added blocks may be new
        raise InputError(f"init_weights={path} does not fit the configured model (missing {missing[:3]}, "
                         f"unexpected {unexpected[:3]}).")


def format_report(before: dict, after: dict, start: str = "untrained") -> str:
    lines = [f"{'held-out loss':<28}{start:>12}{'trained':>12}"]
    for key, label in REPORTED:
        if key in before and key in after:
            lines.append(f"{label:<28}{before[key]:>12.4f}{after[key]:>12.4f}")
    return "\n".join(lines)
