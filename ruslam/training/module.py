"""`DistillationModule`: the LightningModule that trains a plain UWNet against cached teacher targets (eq. 8)."""

from __future__ import annotations

from collections.abc import Callable

import pytorch_lightning as pl
import torch

from ruslam.errors import InputError
from ruslam.models.correspondence_loss import CorrespondenceLoss
from ruslam.models.distillation_loss import DistillationLoss
from ruslam.models.reliability_loss import ReliabilityLoss
from ruslam.models.repeatability_loss import RepeatabilityLoss

TARGET_KEYS = ("keypoint_logits", "dense_descriptors", "global_descriptor")


class NonFiniteLossError(InputError, FloatingPointError):
    """Raised when the distillation loss becomes NaN or infinite, so training stops instead of wasting hours.

    An input error for the entry point: the run's settings (learning rate, data) made it diverge, which the user
    fixes; the sentence names the epoch and step."""


class DistillationModule(pl.LightningModule):
    def __init__(self, net: torch.nn.Module, optimizer: Callable, loss: DistillationLoss | None = None,
                 channels_last: bool = True, correspondence: CorrespondenceLoss | None = None,
                 correspondence_weight: float = 1.0, reliability: ReliabilityLoss | None = None,
                 reliability_weight: float = 0.0, trainable: list[str] | None = None,
                 repeatability: RepeatabilityLoss | None = None, repeatability_weight: float = 0.0,
                 fine_teacher: str | None = None, fine_teacher_scale: int = 2):
        super().__init__()
        self.net = net  # UWNet or XFeatStudent: same outputs, a ``config`` dict for export
        self.loss = loss if loss is not None else DistillationLoss()
        # Used when the batch holds two views (datamodule.pair_views=true): total = eq. 8 + weight * InfoNCE.
        self.correspondence = correspondence
        self.correspondence_weight = correspondence_weight
        # Used with the correspondence loss when the net outputs a reliability map (XFeat student) and the weight > 0.
        self.reliability = reliability if reliability is not None else ReliabilityLoss()
        self.reliability_weight = reliability_weight
        # The two views' keypoint heat made to agree under the homography (needs pair views and a weight > 0).
        self.repeatability = repeatability if repeatability is not None else RepeatabilityLoss()
        self.repeatability_weight = repeatability_weight
        self.optimizer_factory = optimizer
        # A finer-cell student's keypoint targets from a UWNet weights file run on the view upsampled by
        # `fine_teacher_scale` (its 8x8 cells are then 8/scale-pixel cells of the view; docs/finer_cells.md). Kept
        # out of the module's parameters and checkpoints, frozen, always in eval mode.
        self._fine_teacher = []
        self.fine_teacher_scale = int(fine_teacher_scale)
        if fine_teacher:
            from ruslam.models.export import load_uwnet  # noqa: PLC0415

            self._fine_teacher.append(load_uwnet(fine_teacher).eval().requires_grad_(False))
        # Parameter-name prefixes of the net to train (e.g. ["xfeat.heatmap_head."]); the rest of the net and the
        # loss weights are frozen, so no gradient flows through them. None trains everything.
        self.trainable = None if trainable is None else tuple(trainable)
        if self.trainable is not None:
            names = [k for k, _ in self.net.named_parameters()]
            if not self.trainable or any(not any(n.startswith(t) for n in names) for t in self.trainable):
                raise InputError(f"model.trainable={list(self.trainable)} must name prefixes of the network's "
                                 f"parameters (e.g. {names[0]!r}).")
            for k, p in self.named_parameters():
                p.requires_grad_(k.startswith("net.") and k[len("net."):].startswith(self.trainable))
        # NHWC lets oneDNN run the convolutions' backward faster on CPU (measured ~1.3x on a training step here).
        self.memory_format = torch.channels_last if channels_last else torch.contiguous_format
        self.net.to(memory_format=self.memory_format)

    def _losses(self, batch: dict) -> dict[str, torch.Tensor]:
        self._check_targets(batch)
        pair = batch.get("pair")
        if pair is None:
            if self._fine_teacher:
                batch = {**batch, "keypoint_logits": self._fine_targets(batch["image"])}
            pred = self.net(batch["image"].contiguous(memory_format=self.memory_format))
            return self.loss(pred, batch, batch.get("mask"))
        # Both views in one forward pass; eq. 8 on both, the correspondence loss between them.
        both = {k: torch.cat([batch[k], pair[k]]) for k in ("image", "mask", *TARGET_KEYS)}
        if self._fine_teacher:
            both["keypoint_logits"] = self._fine_targets(both["image"])
        pred = self.net(both["image"].contiguous(memory_format=self.memory_format))
        out = self.loss(pred, both, both["mask"])
        if self.correspondence is not None:
            desc_a, desc_b = pred["dense_descriptors"].chunk(2)
            samples = self.correspondence.sample(desc_a, desc_b, batch["homography_ab"], batch["mask"])
            corr = self.correspondence.loss(desc_a, samples)
            out["correspondence"] = corr
            out["total"] = out["total"] + self.correspondence_weight * corr
            if self.reliability_weight > 0 and "reliability" in pred:
                rel = self.reliability(pred["reliability"].chunk(2)[0], samples)
                out["reliability"] = rel
                out["total"] = out["total"] + self.reliability_weight * rel
        if self.repeatability_weight > 0:
            logits_a, logits_b = pred["keypoint_logits"].chunk(2)
            rep = self.repeatability(logits_a, logits_b, batch["homography_ab"], batch["mask"])
            out["repeatability"] = rep
            out["total"] = out["total"] + self.repeatability_weight * rep
        return out

    @torch.no_grad()
    def _fine_targets(self, image: torch.Tensor) -> torch.Tensor:
        from ruslam.models.uwnet_xfeat_student import CELL, upsampled_cells  # noqa: PLC0415

        teacher = self._fine_teacher[0].to(image.device).eval()
        s = self.fine_teacher_scale
        up = torch.nn.functional.interpolate(image.float(), scale_factor=s, mode="bilinear", align_corners=False)
        return upsampled_cells(teacher(up.clamp(0, 1))["keypoint_logits"].float(), CELL // s)

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.net(image)

    def _check_targets(self, batch: dict) -> None:
        want = self.net.config["descriptor_dim"]
        got = batch["dense_descriptors"].shape[1]
        if got != want:
            raise InputError(f"The teacher targets have {got}-d local descriptors but the student is built with "
                             f"descriptor_dim={want}; set model.net.descriptor_dim={got}.")

    def on_train_epoch_start(self) -> None:
        datamodule = getattr(self.trainer, "datamodule", None)
        if hasattr(datamodule, "set_epoch"):  # new water, noise and warps every epoch, still seeded
            datamodule.set_epoch(self.current_epoch)

    def on_train_batch_start(self, batch: dict, batch_idx: int) -> None:
        # Lightning (>= 2.2) neither calls .train() at the start of fit nor after validation: it sets each
        # submodule's `training` flag back one by one, which bypasses a network's own train() (the XFeat student
        # keeps its teacher's batch norms in eval mode there). Calling it here makes every step run in the mode
        # the network defines.
        self.net.train()
        if self.trainable is not None:  # frozen parts keep their batch-norm statistics too
            for name, m in self.net.named_modules():
                if isinstance(m, torch.nn.modules.batchnorm._BatchNorm) and not f"{name}.".startswith(self.trainable):
                    m.eval()

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        out = self._losses(batch)
        if not torch.isfinite(out["total"]):
            terms = ", ".join(f"{k}={out[k].item():.4g}" for k in ("global", "local", "detector"))
            raise NonFiniteLossError(
                f"Training stopped at epoch {self.current_epoch}, step {self.global_step}: the distillation loss is "
                f"{out['total'].item()} ({terms}); lower the learning rate or check the data and teacher cache.")
        bs = batch["image"].shape[0]
        self.log("train/loss", out["total"], prog_bar=True, batch_size=bs)
        for key in ("global", "local", "detector", "alpha", "beta", "gamma", "correspondence", "reliability",
                    "repeatability"):
            if key in out:
                self.log(f"train/{key}", out[key], batch_size=bs)
        return out["total"]

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        out = self._losses(batch)
        bs = batch["image"].shape[0]
        for key in ("global", "local", "detector", "correspondence", "reliability", "repeatability"):
            if key in out:
                self.log(f"val/{key}", out[key], batch_size=bs, sync_dist=True)
        self.log("val/loss", out["total"], prog_bar=True, batch_size=bs, sync_dist=True)

    def configure_optimizers(self):
        return self.optimizer_factory(params=[p for p in self.parameters() if p.requires_grad])

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        # Lets `export` rebuild the network from a Lightning checkpoint without the Hydra config.
        checkpoint["uwnet_config"] = dict(self.net.config)
