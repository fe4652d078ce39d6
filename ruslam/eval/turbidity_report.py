"""`python evaluate.py task=turbidity`: the turbidity view of Table 2, MMA per class of water.

One procedural Upatches build per class (``task.classes``: Jerlov I-III, 1C-5C, 7C-9C, low light), each made
pseudo-underwater at full strength (eq. 4 with the paper's 10 px motion blur; `conf/dataset/turbidity.yaml`),
with the class's settings merged into the dataset's ``degrade``; every extractor runs on every class exactly
as in `matching_report` (same protocol, same rotation modes). Writes into cfg.out_dir ``table.md`` (MMA at the
headline threshold over all rotations and at the first rotation bin, one column per class), ``table.csv``,
``results.json`` and, per class, the match pictures under ``<class>/matches``.
"""

from __future__ import annotations

import csv
import io
import json
import re
from pathlib import Path

import numpy as np
from hydra.utils import get_method
from omegaconf import DictConfig, OmegaConf

from ruslam.atomic_files import atomic_write
from ruslam.eval.matching_report import (
    bin_name,
    evaluate_dataset,
    resolve_extractors,
    row_labels,
    summarize_by_bin,
    with_task_threads,
)


def slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", name).strip("_")


def class_dataset(dataset_cfg: DictConfig, settings: dict, name: str):
    """The dataset of one class: ``settings`` merged into ``degrade``, built in ``<build_dir>/<class>``."""
    conf = OmegaConf.to_container(dataset_cfg, resolve=True)
    conf.pop("label", None)
    unknown = set(settings) - {"water_types", "low_light", "blur_length", "noise_std", "background_light"}
    if unknown:
        raise ValueError(f"task.classes.{name} has unknown setting(s) {sorted(unknown)}; expected some of "
                         "water_types, low_light, blur_length, noise_std, background_light.")
    conf["degrade"] = {**conf["degrade"], **settings}
    conf["build_dir"] = str(Path(conf["build_dir"]) / slug(name))
    return get_method(conf.pop("_target_"))(**conf)


def run(cfg: DictConfig) -> dict:
    """MMA per class of water for ``cfg.extractors``, with torch at ``task.torch_threads`` during the run."""
    return with_task_threads(cfg, _run)


def _run(cfg: DictConfig) -> dict:
    task, out_dir = cfg.task, Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = list(cfg.extractors)
    classes = OmegaConf.to_container(task.classes, resolve=True)
    if not names or not classes:
        raise ValueError("extractors and task.classes must both be non-empty for task=turbidity.")
    thresholds, headline = tuple(task.thresholds), float(task.headline_threshold)
    bins = [tuple(b) for b in task.rotation_bins]
    labels = row_labels(task, names)
    extractors, skipped = resolve_extractors(names, task)
    datasets = {name: class_dataset(cfg.dataset, settings or {}, name) for name, settings in classes.items()}

    summary = {}  # class -> key -> summary by bin
    for name, dataset in datasets.items():
        print(f"class {name}: {len(dataset)} pairs")
        results, geometry, _, _ = evaluate_dataset(dataset, extractors, task, out_dir / slug(name), bins)
        rotations = [g[0] for g in geometry]
        summary[name] = {k: summarize_by_bin(r, rotations, bins, thresholds, headline) for k, r in results.items()}
        summary[name]["zoom"] = float(np.nanmedian([g[1] for g in geometry]))

    pairs = {name: len(d) for name, d in datasets.items()}
    title = (f"{cfg.dataset.get('label', 'dataset')}: MMA@{headline:g}px per class of water "
             f"({', '.join(f'{n}: {p} pairs' for n, p in pairs.items())}), {task.max_keypoints} keypoints max")
    md = markdown(title, summary, labels, skipped, bins[0])
    atomic_write(out_dir / "table.md", md)
    atomic_write(out_dir / "table.csv", table_csv(summary, labels, bins))
    report = {"dataset": title, "classes": classes, "pairs": pairs, "results": summary, "skipped": skipped}
    atomic_write(out_dir / "results.json", json.dumps(report, indent=1))
    print(md)
    return report


def _keys(summary: dict) -> list[str]:
    first = next(iter(summary.values()))
    return [k for k in first if k != "zoom"]


def markdown(title: str, summary: dict, labels: dict, skipped: dict, first_bin) -> str:
    classes = list(summary)
    low = bin_name(*first_bin)
    lines = [f"### {title}", ""]
    for part, caption in (("overall", "all rotations"), (low, f"rotation {low}")):
        counts = [summary[c][_keys(summary)[0]][part]["pairs"] if _keys(summary) else 0 for c in classes]
        lines += [f"MMA, {caption}:", "", "| Method | " + " | ".join(
            f"{c} (n={n})" for c, n in zip(classes, counts, strict=True)) + " |", "|---|" + "---:|" * len(classes)]
        for key in _keys(summary):
            cells = [summary[c][key][part] for c in classes]
            lines.append(f"| {labels.get(key, key)} | " + " | ".join(
                f"{s['mma']:.2f}" if s.get("pairs") else "-" for s in cells) + " |")
        lines.append("")
    if skipped:
        lines += ["Skipped:"] + [f"- {labels.get(n, n)} (`{n}`): {why}" for n, why in skipped.items()]
    return "\n".join(lines) + "\n"


def table_csv(summary: dict, labels: dict, bins) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(["method", "name", "class", "part", "pairs", "rep", "ms", "mma", "keypoints", "matches"])
    for c, per_key in summary.items():
        for key in _keys(summary):
            for part in ["overall"] + [bin_name(lo, hi) for lo, hi in bins]:
                p = per_key[key][part]
                values = [round(p[k], 3) for k in ("rep", "ms", "mma", "keypoints", "matches")] if p.get("pairs") \
                    else [""] * 5
                writer.writerow([labels.get(key, key), key, c, part, p.get("pairs", 0), *values])
    return buf.getvalue()
