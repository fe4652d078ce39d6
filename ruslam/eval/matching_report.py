"""`python evaluate.py task=matching`: paper Table 2 (Rep., M.S., MMA) for several extractors on one dataset.

Writes into cfg.out_dir: ``table.md`` and ``table.csv`` (overall and per rotation bin), ``mma_vs_threshold.png``,
``matches/<extractor>_<pair>.png`` (correct matches green, wrong red) and ``results.json``.

Extractor names resolve as: a key of ``task.weights`` -> that weights file (skipped with a note when it is null
or missing); a registered name (`ruslam.models.registry`) -> `load_extractor` (skipped with a note when it cannot
be built here, e.g. SuperPoint without weights); a ``.pt/.pth/.ckpt`` path -> UWNet weights. Anything else is an
error before any work starts.
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from hydra.utils import get_method
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from ruslam.atomic_files import atomic_write
from ruslam.errors import MissingWeights
from ruslam.eval.match_plots import draw_matches, plot_mma, write_png
from ruslam.eval.matching import PairResult, cap_keypoints, evaluate_pair, rotation_bin, summarize
from ruslam.models.registry import EXTRACTORS, load_extractor
from ruslam.models.rotation_tta import ROTATIONS, best_rotation, extract_rotations, pool

WEIGHT_SUFFIXES = (".pt", ".pth", ".ckpt")
ROTATION_MODES = {"none": "", "c4": " + C4 TTA", "c4best": " + C4 best rotation"}  # mode -> row label suffix


def resolve_extractors(names, task: DictConfig, extra_options=None) -> tuple[dict, dict]:
    """Validate every name first (unknown -> one clear error), then build: ({name: extractor}, {name: skip note}).

    `extra_options` ({name: {key: value}}, e.g. a dataset's own) update `task.extractor_options` per name."""
    weights = dict(task.get("weights") or {})
    options = OmegaConf.to_container(OmegaConf.create(task.get("extractor_options") or {}), resolve=True)
    extra = OmegaConf.to_container(OmegaConf.create(extra_options or {}), resolve=True)
    options = {name: {**options.get(name, {}), **extra.get(name, {})} for name in {*options, *extra}}
    for name in names:
        if name not in weights and name not in EXTRACTORS and Path(str(name)).suffix not in WEIGHT_SUFFIXES:
            raise ValueError(
                f"Unknown extractor {name!r} in extractors; expected one of "
                f"{sorted(set(EXTRACTORS) | set(weights))} or a {'/'.join(WEIGHT_SUFFIXES)} weights file."
            )
    built, skipped = {}, {}
    for name in names:
        conf = dict(options.get(name, {}))
        if name in weights:
            path = weights[name]
            if not path or not Path(path).is_file():
                skipped[name] = f"no weights file configured (task.weights.{name}={path})"
                continue
            built[name] = load_extractor(path, device=task.device, **conf)
        elif name in EXTRACTORS:
            try:
                built[name] = load_extractor(name, device=task.device, **conf)
            except MissingWeights as exc:  # absent weights only: an extractor that crashes is a bug, not a note
                skipped[name] = f"unavailable: {exc}"
        else:
            built[name] = load_extractor(name, device=task.device, **conf)  # an explicit weights path must exist
    return built, skipped


def rotation_modes(task: DictConfig) -> list[str]:
    """``task.rotation_tta``: none, c4, c4best, or a list of them (one table row per extractor and mode)."""
    value = task.get("rotation_tta") or "none"
    modes = [value] if isinstance(value, str) else list(value)
    if not modes or any(m not in ROTATION_MODES for m in modes) or len(set(modes)) != len(modes):
        raise ValueError(f"task.rotation_tta must be one of {list(ROTATION_MODES)} or a list of them, got {value!r}.")
    return modes


def mode_key(name: str, mode: str) -> str:
    return name if mode == "none" else f"{name}+{mode}"


def row_labels(task: DictConfig, names) -> dict:
    """Table labels of every extractor and rotation mode (``task.labels``, '+ C4 TTA' etc. for the augmented rows)."""
    labels = dict(task.get("labels") or {})
    labels.update({mode_key(n, m): f"{labels.get(n, n)}{ROTATION_MODES[m]}" for n in names
                   for m in rotation_modes(task) if m != "none"})
    return labels


def bin_name(lo, hi) -> str:
    return f"{lo:g}-{hi:g}°"


def evaluate_dataset(dataset, extractors: dict, task: DictConfig, out_dir: Path, bins) -> tuple:
    """Run every extractor on every pair (one progress bar over pairs).

    Returns ({key: [PairResult]}, [(rotation, zoom) of each pair], {key: [seconds per image 2]}, [pictures]),
    one key per extractor and rotation mode (`mode_key`); the first pair met in each rotation bin (at most
    ``task.num_pictures`` pairs) gets a match picture per key. With C4 test-time augmentation, image 1 (shared by
    the pairs of a sequence) is also extracted at 90/180/270°, each rotation capped to ``task.max_keypoints``;
    ``c4`` matches image 2 against the four pooled, ``c4best`` against the one `best_rotation` picks.
    """
    modes = rotation_modes(task)
    keys = [(name, mode, mode_key(name, mode)) for name in extractors for mode in modes]
    results = {key: [] for _, _, key in keys}
    rotations, timings = [], {key: [] for _, _, key in keys}
    reference = {}  # name -> (sequence, features of image 1): image 1 is shared by the pairs of a sequence
    pictured_bins, pictures = set(), []
    (out_dir / "matches").mkdir(parents=True, exist_ok=True)
    for i in tqdm(range(len(dataset)), desc="matching pairs", unit="pair"):
        pair = dataset[i]
        rotations.append((pair["rotation_deg"], pair.get("zoom", float("nan"))))
        b = rotation_bin(pair["rotation_deg"], bins)
        picture = len(pictured_bins) < task.num_pictures and b not in pictured_bins
        for name, extractor in extractors.items():
            if reference.get(name, (None,))[0] != pair["sequence"]:
                rotated = any(m != "none" for m in modes)
                parts = extract_rotations(extractor, pair["image1"], ROTATIONS if rotated else (0,))
                parts = [cap_keypoints(p, task.max_keypoints) for p in parts]
                reference[name] = (pair["sequence"], {"none": parts[0], "c4": pool(parts), "parts": parts})
            start = time.perf_counter()
            features2 = extractor.extract(pair["image2"])
            seconds = time.perf_counter() - start
            for mode in modes:
                key = mode_key(name, mode)
                timings[key].append(seconds)
                features1 = reference[name][1].get(mode)
                if mode == "c4best":
                    parts = reference[name][1]["parts"]
                    features1 = parts[best_rotation(parts, features2, getattr(extractor, "binary", False))]
                results[key].append(_evaluate(features1, features2, pair, extractor, task, key, out_dir, picture,
                                              pictures))
        if picture:
            pictured_bins.add(b)
    return results, rotations, timings, pictures


def _evaluate(features1, features2, pair, extractor, task, key, out_dir, picture, pictures) -> PairResult:
    """One pair's metrics (image 1 already capped), its match picture when asked, arrays dropped from the result."""
    res = evaluate_pair(
        features1, features2, pair["H"], pair["image1"].shape[:2], pair["image2"].shape[:2],
        binary=getattr(extractor, "binary", False), max_keypoints=task.max_keypoints, eps=task.eps,
        thresholds=tuple(task.thresholds), max_keypoints1=0,
    )
    if picture:
        canvas = draw_matches(pair["image1"], pair["image2"], res.keypoints1, res.keypoints2, res.matches,
                              res.match_errors <= task.eps)
        stem = Path(str(key)).name  # an extractor given as a weights path: named after the file
        path = out_dir / "matches" / f"{stem}_{pair['name'].replace('/', '_')}.png"
        write_png(path, canvas)
        pictures.append(str(path.relative_to(out_dir)))
    empty = np.zeros((0, 2))
    return replace(res, keypoints1=empty, keypoints2=empty, matches=empty, match_errors=empty)


def summarize_by_bin(results: list[PairResult], rotations: list[float], bins, thresholds, headline) -> dict:
    out = {"overall": summarize(results, thresholds, headline)}
    for k, (lo, hi) in enumerate(bins):
        subset = [r for r, a in zip(results, rotations, strict=True) if rotation_bin(a, bins) == k]
        out[bin_name(lo, hi)] = summarize(subset, thresholds, headline)
    return out


def markdown_table(title: str, summary: dict, labels: dict, skipped: dict, bins, headline) -> str:
    bin_names = [bin_name(lo, hi) for lo, hi in bins]
    first = next(iter(summary.values()), None)
    counts = [first[b]["pairs"] if first else 0 for b in bin_names]
    head = ["Method", "%Rep.", "%M.S.", f"%MMA@{headline:g}px"]
    head += [f"%MMA {b} (n={n})" for b, n in zip(bin_names, counts, strict=True)] + ["kpts", "matches"]
    lines = [f"### {title}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    fmt = lambda s, key: f"{s[key]:.2f}" if s.get("pairs") else "-"  # noqa: E731
    for name, s in summary.items():
        o = s["overall"]
        row = [labels.get(name, name), fmt(o, "rep"), fmt(o, "ms"), fmt(o, "mma")]
        row += [fmt(s[b], "mma") for b in bin_names] + [f"{o['keypoints']:.0f}", f"{o['matches']:.0f}"]
        lines.append("| " + " | ".join(row) + " |")
    if skipped:
        lines += ["", "Skipped:"] + [f"- {labels.get(n, n)} (`{n}`): {why}" for n, why in skipped.items()]
    return "\n".join(lines) + "\n"


def csv_table(summary: dict, labels: dict, skipped: dict, bins, thresholds) -> str:
    parts = ["overall"] + [bin_name(lo, hi) for lo, hi in bins]
    header = ["method", "name", "part", "pairs", "rep", "ms", "mma", "keypoints", "matches"]
    header += [f"mma@{t:g}" for t in thresholds] + ["note"]
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(header)
    for name, s in summary.items():
        for part in parts:
            p = s[part]
            if not p.get("pairs"):
                writer.writerow([labels.get(name, name), name, part, 0] + [""] * (len(header) - 5))
                continue
            values = [round(p[k], 3) for k in ("rep", "ms", "mma", "keypoints", "matches")]
            writer.writerow([labels.get(name, name), name, part, p["pairs"], *values,
                             *[round(v, 3) for v in p["mma_curve"]], ""])
    for name, why in skipped.items():
        writer.writerow([labels.get(name, name), name, "overall", 0] + [""] * (len(header) - 5) + [why])
    return buf.getvalue()


def with_task_threads(cfg: DictConfig, fn) -> dict:
    """``fn(cfg)`` with torch at ``task.torch_threads`` threads (when set), the previous count restored after."""
    threads = torch.get_num_threads()
    if cfg.task.get("torch_threads"):
        torch.set_num_threads(int(cfg.task.torch_threads))
    try:
        return fn(cfg)
    finally:
        torch.set_num_threads(threads)


def run(cfg: DictConfig) -> dict:
    """Table 2 on ``cfg.dataset`` for ``cfg.extractors``; torch runs with ``task.torch_threads`` during the run."""
    return with_task_threads(cfg, _run)


def _run(cfg: DictConfig) -> dict:
    task, out_dir = cfg.task, Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = list(cfg.extractors)
    if not names:
        raise ValueError("extractors is empty; name at least one extractor, e.g. extractors=[sift,orb].")
    thresholds, headline = tuple(task.thresholds), float(task.headline_threshold)
    if headline not in thresholds:
        raise ValueError(f"task.headline_threshold={headline:g} must be one of task.thresholds {list(thresholds)}.")
    bins = [tuple(b) for b in task.rotation_bins]
    labels = row_labels(task, names)
    extractors, skipped = resolve_extractors(names, task)

    dataset_cfg = OmegaConf.to_container(cfg.dataset, resolve=True)
    title = dataset_cfg.pop("label", "dataset")
    # called directly (not hydra.utils.instantiate) so that a bad-input error reaches the user as its own sentence;
    # nested configs (the builder's `degrade`) are instantiated by the builder, which records them.
    dataset = get_method(dataset_cfg.pop("_target_"))(**dataset_cfg)
    if len(dataset) == 0:
        raise ValueError(f"Dataset {title} holds no image pair.")
    if extractors:
        results, geometry, timings, pictures = evaluate_dataset(dataset, extractors, task, out_dir, bins)
    else:  # every extractor was skipped: still write the table with the notes
        results, geometry, timings, pictures = {}, [], {}, []
    rotations, zooms = [g[0] for g in geometry], [g[1] for g in geometry]

    summary = {n: summarize_by_bin(r, rotations, bins, thresholds, headline) for n, r in results.items()}
    for name in summary:
        summary[name]["seconds_per_image"] = float(np.mean(timings[name]))
    zoom = f", median zoom {np.nanmedian(zooms):.2f}x" if np.isfinite(zooms).any() else ""
    title = (f"{title}: {len(dataset)} pairs{zoom}, {task.max_keypoints} keypoints max, Rep./M.S. at "
             f"{task.eps:g} px, MMA at {headline:g} px")
    atomic_write(out_dir / "table.md", markdown_table(title, summary, labels, skipped, bins, headline))
    atomic_write(out_dir / "table.csv", csv_table(summary, labels, skipped, bins, thresholds))
    curves = {labels.get(n, n): s["overall"]["mma_curve"] for n, s in summary.items() if s["overall"].get("pairs")}
    plot_mma(curves, thresholds, out_dir / "mma_vs_threshold.png", title.split(":")[0])
    report = {"dataset": title, "pairs": len(dataset), "rotations_deg": rotations, "zooms": zooms, "results": summary,
              "skipped": skipped, "pictures": pictures,
              "files": ["table.md", "table.csv", "mma_vs_threshold.png", "results.json"]}
    atomic_write(out_dir / "results.json", json.dumps(report, indent=1))
    print((out_dir / "table.md").read_text())
    return report
