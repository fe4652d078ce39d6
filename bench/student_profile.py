"""Where the XFeat student's extraction time goes, stage by stage, against XFeat's own stages.

    nice .venv/bin/python bench/student_profile.py [--reps 15] [--threads 2] [--weights PATH]

Every stage runs round-robin on the same 480x640 image (machine load hits them alike); medians are reported with
their share of XFeat's full extract measured in the same run. The student's stages are the ones of
`XFeatStudent.forward` (backbone shared with XFeat, the added residual blocks, NetVLAD) and the sparse decoding of
`UWNetExtractor`; XFeat's are those of `ruslam.models.pretrained.xfeat.XFeat.extract`. The target is UWNet extract
<= 1.3x XFeat extract (bench/extractor.py); this script says which block to make cheaper.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
from extractor import H, W, round_robin, test_image  # noqa: E402  (the same image and timing loop)

from ruslam import load_extractor  # noqa: E402
from ruslam.models.deform_conv import deform_conv2d_fast  # noqa: E402
from ruslam.models.extractor import decode_sparse  # noqa: E402
from ruslam.models.uwnet_extractor import SHIPPED_WEIGHTS, UWNetExtractor  # noqa: E402
from ruslam.models.uwnet_xfeat_student import CELL, XFeatStudent, _pad  # noqa: E402


def candidates(feats: torch.Tensor, hidden: torch.Tensor) -> dict:
    """Cheaper placements of the same blocks (random weights: the cost, not the accuracy)."""
    gen = torch.Generator().manual_seed(0)

    def dcn(cin: int, cout: int):
        w = torch.randn(cout, cin, 3, 3, generator=gen) * 0.05
        off_w = torch.randn(18, cin, 3, 3, generator=gen) * 0.01
        return lambda x: deform_conv2d_fast(x, F.conv2d(x, off_w, padding=1), w, padding=1)

    reduce_w, expand_w = torch.randn(16, 64, 1, 1, generator=gen), torch.randn(64, 16, 1, 1, generator=gen)
    d16a, d16b, d32, d64 = dcn(16, 16), dcn(16, 16), dcn(32, 32), dcn(64, 64)
    reduce32_w, expand32_w = torch.randn(32, 64, 1, 1, generator=gen), torch.randn(64, 32, 1, 1, generator=gen)

    def bottleneck16():  # 1x1 64->16, DCN 16->16, ReLU, DCN 16->16, 1x1 16->64 (zero at step 0)
        y = F.relu(d16a(F.conv2d(feats, reduce_w)))
        return F.conv2d(d16b(y), expand_w)

    def bottleneck32_one():  # 1x1 64->32, one DCN 32->32, 1x1 32->64 (zero at step 0)
        return F.conv2d(F.relu(d32(F.conv2d(feats, reduce32_w))), expand32_w)

    from ruslam.models.attention import PositionAttention  # noqa: PLC0415

    pam8 = PositionAttention(64, key_stride=8).eval()
    return {
        "candidate: one DCN 64->64 (instead of two)": lambda: d64(feats),
        "candidate: bottleneck 64->16, two DCN 16->16, 16->64": bottleneck16,
        "candidate: bottleneck 64->32, one DCN 32->32, 32->64": bottleneck32_one,
        "candidate: position attention, key stride 8": lambda: pam8(hidden),
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--reps", type=int, default=15)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--weights", default=str(SHIPPED_WEIGHTS), help="XFeat student weights (default: shipped);"
                        " the per-block rows use every block of the architecture at step 0")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    image = test_image()
    uwnet = UWNetExtractor.from_file(args.weights)
    if getattr(uwnet.net, "architecture", None) != "xfeat_student":
        raise SystemExit(f"--weights {args.weights}: not an XFeat student file.")
    s = XFeatStudent().eval()  # every block, whatever the file keeps (a block's cost does not depend on weights)
    full = UWNetExtractor.from_file(args.weights)
    full.net = s
    xfeat = load_extractor("xfeat")
    x = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255
    m = s.xfeat

    torch.set_grad_enabled(False)
    g = m.norm(_pad(x).mean(dim=1, keepdim=True))
    x1 = m.block1(g)
    x2 = m.block2(x1 + m.skip1(g))
    x3 = m.block3(x2)
    x4, x5 = m.block4(x3), None
    x5 = m.block5(x4)
    size = x3.shape[-2:]
    feats = m.block_fusion(x3 + F.interpolate(x4, size, mode="bilinear") + F.interpolate(x5, size, mode="bilinear"))
    dcn1, dcn2 = s.deform[0], s.deform[3]
    offset1 = dcn1.offset(feats)
    hidden = m.keypoint_head[:3](m._unfold2d(g, ws=CELL))
    out = s(x)
    desc, logits = out["dense_descriptors"], out["keypoint_logits"]
    hx, dx, rx = xfeat.teacher.run(x)

    def backbone():
        g = m.norm(_pad(x).mean(dim=1, keepdim=True))
        x1 = m.block1(g)
        x3 = m.block3(m.block2(x1 + m.skip1(g)))
        x4 = m.block4(x3)
        x5 = m.block5(x4)
        m.block_fusion(x3 + F.interpolate(x4, size, mode="bilinear") + F.interpolate(x5, size, mode="bilinear"))

    stages = {
        "XFeat extract (total)": lambda: xfeat.extract(image),
        "UWNet extract (total, --weights file)": lambda: uwnet.extract(image),
        "UWNet extract (total, every block: attention, two DCNs)": lambda: full.extract(image),
        "shared: XFeat backbone + fusion (1/8, 64 ch)": backbone,
        "shared: keypoint head on 8x8 cells": lambda: m.keypoint_head(m._unfold2d(g, ws=CELL)),
        "XFeat only: reliability head": lambda: m.heatmap_head(feats),
        "XFeat only: decode (thr 0.05, reliability)": lambda: decode_sparse(hx, dx, (H, W), xfeat.conf, 8, rx),
        "XFeat only: hard VLAD": lambda: xfeat.vlad(x, {"dense_descriptors": dx}),
        "student: DCN 1 offsets (3x3 conv 64->18)": lambda: dcn1.offset(feats),
        "student: DCN 1 (offsets + sampling + matmul, 64->64)": lambda: dcn1(feats),
        "student: DCN 2 (offsets + sampling + matmul)": lambda: dcn2(feats),
        "student: 3x3 conv 64->64 (plain, reference)": lambda: F.conv2d(feats, dcn1.conv.weight, padding=1),
        "student: keypoint context 1x1": lambda: s.kp_context(feats),
        "student: position attention": lambda: s.attention.position(hidden),
        "student: channel attention": lambda: s.attention.channel(hidden),
        "student: NetVLAD + power": lambda: s.netvlad(desc.contiguous()),
        "student: decode (thr 0.005)": lambda: decode_sparse(logits, desc, (H, W), uwnet.conf, 8),
    }
    del offset1
    stages.update(candidates(feats, hidden))
    ms = round_robin(stages, args.reps)
    xf = ms["XFeat extract (total)"]
    print(f"# bench/student_profile.py  {H}x{W}, {args.threads} threads, median of {args.reps}, weights {args.weights}")
    print("| stage | median ms | x XFeat extract |\n|---|---:|---:|")
    for k, v in ms.items():
        print(f"| {k} | {v:.1f} | {v / xf:.2f} |")
    n_x = len(decode_sparse(hx, dx, (H, W), xfeat.conf, 8, rx)[0])
    n_s = len(decode_sparse(logits, desc, (H, W), uwnet.conf, 8)[0])
    print(f"\nkeypoints: XFeat {n_x}, UWNet {n_s}")


if __name__ == "__main__":
    main()
