"""Distillation without a teacher cache: views and teacher targets made on the fly on the training device.

`python train.py experiment=fine_cells` (or any training config with an ``online`` block) trains here instead of
through Lightning and the HDF5 cache. Every step takes a batch of clean in-air images with their depth, runs the
frozen teacher on them, and makes each student view on the same device: the pseudo-underwater synthesis (eq. 4,
`ruslam.data.synthesis.degrade`), the photometric jitter and the geometric warp that moves the targets with it
(`ruslam.training.augment`), with the parameters of every view drawn from generators seeded by (seed, step,
image, view). The losses are `DistillationModule`'s. On CUDA the student runs under bf16 autocast (fp16 with a
gradient scaler where bf16 is missing); on the CPU in fp32, so the same config rehearses on either machine.

The learning rate warms up linearly over ``online.warmup_steps``. The run stops at ``online.budget_s`` seconds of
training (or ``online.max_steps``), evaluates the held-out views
(fixed per image, drawn once) before and after, and writes into ``out_dir``: the fp16 weights file
(``export_name``, rewritten every ``online.save_every_s`` seconds so a stopped run still leaves one) and
``online_losses.json`` (held-out losses before and after, steps, images per second, the device).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
from hydra.utils import instantiate
from kornia.geometry.transform import warp_perspective
from omegaconf import DictConfig, OmegaConf

from ruslam.data.synthesis import PseudoUnderwater, degrade
from ruslam.errors import InputError
from ruslam.models.export import export_weights
from ruslam.training.augment import GeometricAugment, PhotometricAugment, seeded_generator, warp_targets_batch
from ruslam.training.datamodule import PreparedSource

DEFAULTS = {"budget_s": 420.0, "max_steps": None, "save_every_s": 60.0, "log_every": 25, "val_batches": None,
            "device": "auto", "precision": "auto", "warmup_steps": 0}


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _autocast_dtype(precision: str, device: torch.device) -> torch.dtype | None:
    """None: fp32. 'auto' is bf16 on a CUDA device that has it (fp16 otherwise), fp32 on the CPU."""
    if precision == "auto":
        if device.type != "cuda":
            return None
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    return {"32": None, "fp32": None, "bf16": torch.bfloat16, "16": torch.float16, "fp16": torch.float16}[precision]


class OnlineViews:
    """Batches of (clean image, depth) -> the `DistillationModule` batch of two degraded, warped views with the
    teacher's targets warped along, all on the images' device."""

    def __init__(self, teacher, synthesis: PseudoUnderwater | None, photometric: PhotometricAugment | None,
                 geometric: GeometricAugment | None, seed: int = 0, pair_views: bool = True):
        self.teacher, self.synthesis, self.photometric, self.geometric = teacher, synthesis, photometric, geometric
        self.seed, self.pair_views = seed, pair_views

    def _photometric(self, rgb: torch.Tensor, gens: list[torch.Generator], noise: torch.Generator) -> torch.Tensor:
        """`PhotometricAugment` on the batch at once: each image's scalars from its own generator, the noise on
        the device."""
        p = self.photometric
        u = torch.stack([torch.rand(5, generator=gen, dtype=torch.float64) for gen in gens]).float().to(rgb.device)
        shape = (-1, 1, 1, 1)
        b = (p.brightness * (2 * u[:, 0] - 1)).view(shape)
        c = torch.exp(p.contrast * (2 * u[:, 1] - 1)).view(shape)
        g = torch.exp(p.gamma * (2 * u[:, 2] - 1)).view(shape)
        mean = rgb.mean(dim=(1, 2, 3), keepdim=True)
        out = ((rgb - mean) * c + mean + b).clamp(0, 1) ** g
        if p.noise_std > 0:
            std = (u[:, 3] * p.noise_std).view(shape)
            out = out + std * torch.randn(rgb.shape, generator=noise, device=rgb.device, dtype=rgb.dtype)
        return out.clamp(0, 1)

    def _view(self, rgb, depth, targets, keys: list[tuple[int, ...]], view: int, noise: torch.Generator):
        gens = [seeded_generator(self.seed, *key, view) for key in keys]
        if self.synthesis is not None:
            drawn = [self.synthesis.draw(g) for g in gens]
            stack = {k: torch.as_tensor(np.array([d[k] for d in drawn]), dtype=rgb.dtype, device=rgb.device)
                     for k in ("beta", "A", "L", "noise_std")}
            rgb = degrade(rgb, depth, stack["beta"], stack["A"], stack["L"], stack["noise_std"],
                          self.synthesis.blur_angle_deg, self.synthesis.blur_length, generator=noise)
        if self.photometric is not None:
            rgb = self._photometric(rgb, gens, noise)
        h, w = rgb.shape[-2:]
        if self.geometric is None:
            homs = torch.eye(3, dtype=torch.float64).expand(len(keys), 3, 3).clone()
            mask = torch.ones(rgb.shape[0], *targets["keypoint_logits"].shape[2:], device=rgb.device)
            return {**targets, "mask": mask, "image": rgb}, homs
        homs = torch.stack([self.geometric.sample(h, w, g) for g in gens])  # [B, 3, 3] float64, CPU
        batch = warp_targets_batch(targets, homs)
        batch["image"] = warp_perspective(rgb, homs.to(rgb), (h, w), mode="bilinear", padding_mode="zeros",
                                          align_corners=True)
        return batch, homs

    @torch.no_grad()
    def __call__(self, rgb: torch.Tensor, depth: torch.Tensor, keys: list[tuple[int, ...]]) -> dict:
        """rgb [B, 3, H, W] in [0, 1], depth [B, H, W] (m), one key (ints) per image seeding its views."""
        targets = {k: v.float() for k, v in self.teacher(rgb).items()}
        noise = torch.Generator(device=rgb.device).manual_seed(hash(tuple(keys)) % (2**62))
        batch, hom_a = self._view(rgb, depth, targets, keys, 0, noise)
        if self.pair_views:
            pair, hom_b = self._view(rgb, depth, targets, keys, 1, noise)
            batch["pair"] = pair
            batch["homography_ab"] = (hom_b @ torch.linalg.inv(hom_a)).float().to(rgb.device)
        return batch


def _stack(source, indices, device) -> tuple[torch.Tensor, torch.Tensor]:
    items = [source[i] for i in indices]
    rgb = torch.from_numpy(np.stack([np.asarray(it["image"], np.float32) for it in items])).permute(0, 3, 1, 2)
    depth = torch.from_numpy(np.stack([np.asarray(it["depth"], np.float32) for it in items]))
    return rgb.to(device).contiguous(), depth.to(device)


def _held_out(module, batches, dtype, device) -> dict[str, float]:
    module.net.eval()
    sums, count = {}, 0
    with torch.no_grad(), torch.autocast(device.type, dtype=dtype or torch.float32, enabled=dtype is not None):
        for batch in batches:
            out = module._losses(batch)
            for k, v in out.items():
                if k not in ("alpha", "beta", "gamma"):
                    sums[k] = sums.get(k, 0.0) + float(v)
            count += 1
    return {k: v / max(count, 1) for k, v in sums.items()}


def train_online(cfg: DictConfig) -> float:
    """Train from the composed training config (its ``online`` block) and return the held-out total loss."""
    from ruslam.training.common import format_report, load_initial_weights  # noqa: PLC0415

    opts = {**DEFAULTS, **OmegaConf.to_container(cfg.online, resolve=True)}
    torch.manual_seed(int(cfg.seed))
    if cfg.get("torch_threads"):
        torch.set_num_threads(int(cfg.torch_threads))
    device = _device(str(opts["device"]))
    dtype = _autocast_dtype(str(opts["precision"]), device)
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    dm = cfg.datamodule
    t0 = time.perf_counter()
    source = PreparedSource(instantiate(cfg.data), dm.get("limit_images"), dm.get("image_size"), preload=True)
    order = torch.randperm(len(source), generator=torch.Generator().manual_seed(int(dm.split_seed))).tolist()
    val_idx, train_idx = sorted(order[: dm.val_size]), order[dm.val_size:]
    teacher = instantiate(cfg.teacher).to(device)
    if hasattr(teacher.global_head, "fitted") and not teacher.global_head.fitted:
        raise InputError("online training needs a fixed VLAD codebook: teacher.global_head.codebook=packaged or a "
                         ".npy path.")
    build = lambda key: None if dm.get(key) is None else instantiate(dm[key])  # noqa: E731
    views = OnlineViews(teacher, build("synthesis"), build("photometric"), build("geometric"), int(cfg.seed),
                        bool(dm.get("pair_views", True)))
    module = instantiate(cfg.model)
    if cfg.get("init_weights"):
        load_initial_weights(module.net, cfg.init_weights)
    module.to(device)
    bs = int(dm.batch_size)
    val_batches = []
    nval = len(val_idx) if opts["val_batches"] is None else min(len(val_idx), bs * int(opts["val_batches"]))
    for start in range(0, nval, bs):  # the held-out views: fixed per image (step -1)
        idx = val_idx[start:start + bs]
        rgb, depth = _stack(source, idx, device)
        val_batches.append(views(rgb, depth, [(-1, i) for i in idx]))
    setup_s = time.perf_counter() - t0
    before = _held_out(module, val_batches, dtype, device)
    optimizer = module.configure_optimizers()
    # Adam's first steps move every weight by ~lr whatever its gradient; a linear warm-up keeps a trained start.
    warmup = max(int(opts["warmup_steps"]), 0)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda i: min(1.0, (i + 1) / warmup) if warmup else 1.0)
    scaler = torch.amp.GradScaler(device.type, enabled=dtype == torch.float16)
    params = [p for p in module.parameters() if p.requires_grad]
    print(f"online training on {device} ({dtype or torch.float32}), {len(train_idx)} train / {len(val_idx)} held-out "
          f"images, setup {setup_s:.1f} s; held-out before: {before.get('total', float('nan')):.4f}", flush=True)
    gen = torch.Generator().manual_seed(int(cfg.seed))
    step, start, last_save, perm, pos = 0, time.perf_counter(), time.perf_counter(), [], 0
    data_s = 0.0
    while True:
        elapsed = time.perf_counter() - start
        if elapsed >= float(opts["budget_s"]) or (opts["max_steps"] is not None and step >= int(opts["max_steps"])):
            break
        if pos + bs > len(perm):
            perm, pos = [train_idx[i] for i in torch.randperm(len(train_idx), generator=gen).tolist()], 0
        idx = perm[pos:pos + bs]
        pos += bs
        td = time.perf_counter()
        rgb, depth = _stack(source, idx, device)
        batch = views(rgb, depth, [(step, i) for i in idx])
        data_s += time.perf_counter() - td
        module.on_train_batch_start(batch, step)  # the network's own train() (frozen parts stay frozen)
        with torch.autocast(device.type, dtype=dtype or torch.float32, enabled=dtype is not None):
            out = module._losses(batch)
        loss = out["total"]
        if not torch.isfinite(loss):
            raise FloatingPointError(f"online training stopped at step {step}: the loss is {float(loss)}.")
        optimizer.zero_grad(set_to_none=True)
        scaler.scale(loss).backward()
        scaler.unscale_(optimizer)
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        scaler.step(optimizer)
        scaler.update()
        schedule.step()
        step += 1
        if step % int(opts["log_every"]) == 0:
            terms = " ".join(f"{k}={out[k].item():.4f}" for k in ("detector", "local", "global", "correspondence",
                                                                 "repeatability") if k in out)
            print(f"step {step} {time.perf_counter() - start:.0f} s loss={loss.item():.4f} {terms}", flush=True)
        if time.perf_counter() - last_save >= float(opts["save_every_s"]):
            export_weights(module.net, out_dir / cfg.get("export_name", "uwnet.pt"))
            last_save = time.perf_counter()
    train_s = time.perf_counter() - start
    after = _held_out(module, val_batches, dtype, device)
    weights = export_weights(module.net, out_dir / cfg.get("export_name", "uwnet.pt"))
    report = {"device": str(device), "autocast": str(dtype), "steps": step, "batch_size": bs,
              "train_seconds": round(train_s, 1), "data_seconds": round(data_s, 1), "setup_seconds": round(setup_s, 1),
              "images_per_second": round(step * bs / max(train_s, 1e-9), 2), "train_images": len(train_idx),
              "held_out_images": nval, "held_out_before": before, "held_out_after": after,
              "weights": weights.name}
    (out_dir / "online_losses.json").write_text(json.dumps(report, indent=2))
    renamed = {f"val/{k if k != 'total' else 'loss'}": v for k, v in before.items()}
    renamed_after = {f"val/{k if k != 'total' else 'loss'}": v for k, v in after.items()}
    print(format_report(renamed, renamed_after, "initial" if cfg.get("init_weights") else "untrained"))
    print(f"{step} steps in {train_s:.0f} s; fp16 weights for load_extractor: {weights}")
    return float(after.get("total", float("nan")))
