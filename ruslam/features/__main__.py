"""``python -m ruslam.features extract|pairs|match``: hloc's features.h5, pairs.txt and matches.h5.

    python -m ruslam.features extract IMAGES OUT.h5 --extractor uwnet_xfeat [--resize-max 1024] [--every 3]
    python -m ruslam.features pairs IMAGES PAIRS.txt (--exhaustive | --window K | --retrieval K --features F.h5)
    python -m ruslam.features match FEATURES.h5 PAIRS.txt OUT.h5 [--matcher nn|lightglue] [--ratio 0.9]

Bad input (a missing or empty folder, an unreadable image, a pair naming an unknown image) prints one sentence
and exits with status 2; no output file is left half written.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ruslam.cli import run_cli
from ruslam.features.hloc_io import list_feature_names, read_pairs, write_pairs
from ruslam.features.pipeline import extract_features, list_images, make_pairs, match_features


def _extract(args) -> None:
    names = list_images(args.images, args.every)
    from ruslam.models.registry import load_extractor  # noqa: PLC0415

    options = {"max_keypoints": args.max_keypoints} if args.max_keypoints else {}
    stats = extract_features(args.images, args.out, load_extractor(args.extractor, device=args.device, **options),
                             names, resize_max=args.resize_max, half=not args.full_precision)
    print(f"wrote {args.out}: {stats['images']} images, {stats['keypoints']} keypoints, {stats['seconds']:.1f} s")


def _pairs(args) -> None:
    if args.features:
        names = list_feature_names(args.features)
    else:
        names = list_images(args.images, args.every)
    pairs = make_pairs(names, exhaustive=args.exhaustive, window=args.window, retrieval=args.retrieval,
                       features_path=args.features)
    from ruslam.atomic_files import atomic_path  # noqa: PLC0415

    with atomic_path(args.out) as tmp:
        write_pairs(tmp, pairs)
    print(f"wrote {args.out}: {len(pairs)} pairs of {len(names)} images")


def _match(args) -> None:
    stats = match_features(args.features, read_pairs(args.pairs), args.out, matcher=args.matcher, ratio=args.ratio)
    print(f"wrote {args.out}: {stats['pairs']} pairs, {stats['matches']} matches, {stats['seconds']:.1f} s")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m ruslam.features", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    e = sub.add_parser("extract", help="features.h5 of every image in a folder")
    e.add_argument("images", type=Path)
    e.add_argument("out", type=Path)
    e.add_argument("--extractor", default="uwnet_xfeat", help="registry name or UWNet weights file")
    e.add_argument("--resize-max", type=int, default=None, help="shrink images whose longer side exceeds this")
    e.add_argument("--max-keypoints", type=int, default=None)
    e.add_argument("--every", type=int, default=1, help="every N-th image in name order")
    e.add_argument("--device", default="cpu")
    e.add_argument("--full-precision", action="store_true", help="float32 descriptors and scores (default float16)")
    e.set_defaults(fn=_extract)
    p = sub.add_parser("pairs", help="pairs.txt: exhaustive, sequential window and/or retrieval")
    p.add_argument("images", type=Path, help="image folder (names), ignored when --features is given")
    p.add_argument("out", type=Path)
    p.add_argument("--exhaustive", action="store_true")
    p.add_argument("--window", type=int, default=0, help="each image with the next K in name order")
    p.add_argument("--retrieval", type=int, default=0, help="each image with its K nearest by global descriptor")
    p.add_argument("--features", type=Path, default=None, help="features.h5 (names; global descriptors)")
    p.add_argument("--every", type=int, default=1)
    p.set_defaults(fn=_pairs)
    m = sub.add_parser("match", help="matches.h5 of every pair")
    m.add_argument("features", type=Path)
    m.add_argument("pairs", type=Path)
    m.add_argument("out", type=Path)
    m.add_argument("--matcher", default="nn", choices=["nn", "lightglue"])
    m.add_argument("--ratio", type=float, default=None, help="Lowe's ratio test for nn (e.g. 0.9)")
    m.set_defaults(fn=_match)
    args = parser.parse_args(argv)
    run_cli(args.fn, args)


if __name__ == "__main__":
    main()
