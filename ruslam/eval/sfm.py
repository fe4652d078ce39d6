"""`python evaluate.py task=sfm`: a COLMAP reconstruction per extractor with pycolmap, from hloc's files.

Per extractor, into ``<out_dir>/<extractor>/``: ``features.h5``, ``pairs.txt`` and ``matches.h5`` (hloc's files,
`ruslam.features`), ``database.db``, and the largest model in ``sparse/`` (COLMAP binary) and ``sparse_txt/``
(text). Keypoints get +0.5 on import (COLMAP's origin is the top-left corner of the top-left pixel, ours and
hloc's its centre), matches (per extractor: ``task.matcher``, ``task.ratio``) are geometrically verified
(`pycolmap.verify_matches`), then incremental mapping.
In ``out_dir``: ``table.md`` and ``results.json`` with, per extractor, ``images``, ``registered``, ``points``,
``track_length``, ``reproj_error`` (px), ``seconds`` (extraction + matching + verification + mapping) and, when the
folder has a ``groundtruth.txt`` (TUM, T_world_camera; image stems are timestamps in ns or s), the camera position
error after a Sim3 alignment (``position_rmse`` and ``position_median``, in ground-truth units).

Camera: with ``calibration.yaml`` in the folder (the image-folder sequences' file: pinhole or fisheye, OpenCV
pixel-centre convention) its intrinsics are used, fixed (0.5 added to the principal point for COLMAP); otherwise
one shared SIMPLE_RADIAL camera that COLMAP initialises from the image size and refines.

Default folder (``dataset.root=null``): the rendered underwater multi-view set (`ruslam.data.multiview`).
"""

from __future__ import annotations

import json
import re
import shutil
import time
from pathlib import Path

import numpy as np
import yaml
from omegaconf import DictConfig, OmegaConf

from ruslam.atomic_files import atomic_write
from ruslam.errors import InputError, MissingInput

# ------------------------------------------------------------------------------------------- config check (light)


def check(cfg: DictConfig) -> None:
    """Before anything heavy: the extractors are known, the folder exists and holds images."""
    from ruslam.config_checks import check_extractors  # noqa: PLC0415
    from ruslam.features.pipeline import list_images  # noqa: PLC0415

    check_extractors(cfg)
    task = cfg.task
    if task.get("max_keypoints") is not None and int(task.max_keypoints) < 1:
        raise InputError(f"task.max_keypoints must be >= 1 (null: no cap); got {task.max_keypoints}.")
    if task.get("resize_max") is not None and int(task.resize_max) < 16:
        raise InputError(f"task.resize_max must be >= 16 pixels (null: images as they are); got {task.resize_max}.")
    root = cfg.dataset.get("root")
    if root is not None:
        list_images(Path(str(root)).expanduser(), _every(cfg.dataset))
    matcher = task.get("matcher")
    given = _plain(matcher) if OmegaConf.is_config(matcher) or isinstance(matcher, dict) else {None: matcher}
    for key, value in given.items():
        if value not in ("nn", "lightglue", None):
            where = "task.matcher" if key is None else f"task.matcher.{key}"
            raise InputError(f"{where} must be 'nn' or 'lightglue', got {value!r}.")


def per_extractor(setting, name: str, fallback=None):
    """A task setting given once for every extractor, or per name as {default: ..., <name>: ...}."""
    if not OmegaConf.is_config(setting) and not isinstance(setting, dict):
        return fallback if setting is None else setting
    setting = _plain(setting)
    return setting.get(name, setting.get("default", fallback))


def _every(dataset: DictConfig) -> int:
    every = dataset.get("every")
    return 1 if every is None else int(every)  # 0 is refused by list_images, not read as 1


# ------------------------------------------------------------------------------------------------------ camera


def colmap_camera(root: Path) -> tuple[str, str, bool]:
    """(COLMAP model, comma-separated params or "" for COLMAP's guess, whether the intrinsics are known)."""
    path = root / "calibration.yaml"
    if not path.is_file():
        return "SIMPLE_RADIAL", "", False
    try:
        calib = yaml.safe_load(path.read_text())
        fx, fy, cx, cy = (float(v) for v in calib["intrinsics"])
        dist = [float(v) for v in (calib.get("distortion") or [])]
        model = str(calib.get("model", "pinhole"))
    except (KeyError, TypeError, ValueError, yaml.YAMLError):
        raise InputError(f"{path} must hold model, intrinsics: [fx, fy, cx, cy] and distortion: [...].") from None
    cx, cy = cx + 0.5, cy + 0.5  # pixel centre at 0 -> COLMAP's corner origin
    if model == "fisheye":
        return "OPENCV_FISHEYE", ",".join(map(repr, [fx, fy, cx, cy, *(dist + [0.0] * 4)[:4]])), True
    if not any(dist):
        return "PINHOLE", ",".join(map(repr, [fx, fy, cx, cy])), True
    if len(dist) > 4 and any(dist[4:]):
        return "FULL_OPENCV", ",".join(map(repr, [fx, fy, cx, cy, *(dist + [0.0] * 8)[:8]])), True
    return "OPENCV", ",".join(map(repr, [fx, fy, cx, cy, *(dist + [0.0] * 4)[:4]])), True


# ------------------------------------------------------------------------------------------------ reconstruction


def reconstruct(image_dir: Path, names: list[str], features_path: Path, pairs_path: Path, matches_path: Path,
                out_dir: Path, camera: tuple[str, str, bool] | None = None, min_num_matches: int = 15,
                seed: int = 0, verbose: bool = False):
    """hloc's files -> COLMAP database -> verified matches -> incremental mapping. Returns the largest model
    (`pycolmap.Reconstruction`, or None when nothing registers) and the number of models."""
    import pycolmap  # noqa: PLC0415

    from ruslam.features.hloc_io import read_features, read_matches, read_pairs  # noqa: PLC0415

    model, params, known = camera or colmap_camera(image_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    db_path = out_dir / "database.db"
    db_path.unlink(missing_ok=True)
    pycolmap.Database.open(str(db_path)).close()
    options = pycolmap.ImageReaderOptions()
    options.camera_model = model
    if params:
        options.camera_params = params
    pycolmap.import_images(str(db_path), str(image_dir), pycolmap.CameraMode.SINGLE, image_names=names,
                           options=options)
    db = pycolmap.Database.open(str(db_path))
    ids = {image.name: image.image_id for image in db.read_all_images()}
    for name in names:
        db.write_keypoints(ids[name], read_features(features_path, name)["keypoints"].astype(np.float32) + 0.5)
    seen = set()
    for a, b in read_pairs(pairs_path):
        key = tuple(sorted((ids[a], ids[b])))
        if key in seen:
            continue
        seen.add(key)
        matches, _ = read_matches(matches_path, a, b)
        db.write_matches(ids[a], ids[b], matches.astype(np.uint32))
    db.close()
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.max_num_trials = 20000
    verify.ransac.min_inlier_ratio = 0.1
    verify.ransac.random_seed = int(seed)
    pycolmap.verify_matches(str(db_path), str(pairs_path), verify)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.min_num_matches = int(min_num_matches)
    opts.random_seed = int(seed)
    if known:
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
    maps_dir = out_dir / "models"
    shutil.rmtree(maps_dir, ignore_errors=True)
    maps_dir.mkdir()
    models = pycolmap.incremental_mapping(str(db_path), str(image_dir), str(maps_dir), opts)
    shutil.rmtree(maps_dir, ignore_errors=True)
    if not models:
        return None, 0
    best = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    for sub, write in (("sparse", best.write_binary), ("sparse_txt", best.write_text)):
        folder = out_dir / sub
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir()
        write(str(folder))
    return best, len(models)


# ---------------------------------------------------------------------------------------------- ground truth


def _stem_seconds(name: str) -> float | None:
    stem = Path(name).stem
    if not re.fullmatch(r"\d+(\.\d+)?", stem):
        return None
    t = float(stem)
    return t * 1e-9 if t > 1e12 else t


def read_groundtruth_positions(root: Path, names: list[str]) -> dict[str, np.ndarray]:
    """Camera positions of the named images from ``root/groundtruth.txt`` (TUM), matched by timestamp (1 ms)."""
    path = root / "groundtruth.txt"
    if not path.is_file():
        return {}
    rows = []
    for line in path.read_text().splitlines():
        parts = line.replace(",", " ").split()
        if not parts or line.lstrip().startswith("#"):
            continue
        try:
            rows.append([float(p) for p in parts[:8]])
        except ValueError:
            continue
    if not rows:
        return {}
    table = np.array(rows)
    order = np.argsort(table[:, 0])
    stamps, positions = table[order, 0], table[order, 1:4]
    out = {}
    for name in names:
        t = _stem_seconds(name)
        if t is None:
            continue
        i = int(np.clip(np.searchsorted(stamps, t), 1, len(stamps) - 1))
        j = i - 1 if abs(stamps[i - 1] - t) <= abs(stamps[i] - t) else i
        if abs(stamps[j] - t) <= 1e-3:
            out[name] = positions[j]
    return out


def sim3_align(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Umeyama: the similarity s R x + t that best maps src [N, 3] onto dst, applied to src."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U @ Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = (a**2).sum() / len(src)
    s = np.trace(np.diag(S) @ D) / max(var, 1e-18)
    return s * a @ R.T + mu_d


def position_errors(recon, gt: dict[str, np.ndarray]) -> np.ndarray | None:
    """Per registered image with ground truth: the position error after Sim3 alignment (None: < 3 images)."""
    est, ref = [], []
    for image in recon.images.values():
        if image.has_pose and image.name in gt:
            est.append(image.projection_center())
            ref.append(gt[image.name])
    if len(est) < 3:
        return None
    est, ref = np.array(est), np.array(ref)
    return np.linalg.norm(sim3_align(est, ref) - ref, axis=1)


# ------------------------------------------------------------------------------------------------------- report


def summarize(recon, n_models: int, num_images: int, seconds: float, gt: dict) -> dict:
    if recon is None:
        return {"images": num_images, "registered": 0, "points": 0, "track_length": 0.0, "reproj_error": None,
                "seconds": round(seconds, 1), "models": 0}
    row = {"images": num_images, "registered": int(recon.num_reg_images()), "points": int(recon.num_points3D()),
           "track_length": round(float(recon.compute_mean_track_length()), 2),
           "reproj_error": round(float(recon.compute_mean_reprojection_error()), 3),
           "seconds": round(seconds, 1), "models": int(n_models)}
    errors = position_errors(recon, gt) if gt else None
    if errors is not None:
        row["position_rmse"] = float(f"{np.sqrt(np.mean(errors**2)):.4g}")
        row["position_median"] = float(f"{np.median(errors):.4g}")
    return row


def table_markdown(results: dict, labels: dict, title: str) -> str:
    has_gt = any("position_rmse" in r for r in results.values())
    head = ["extractor", "registered / images", "3-D points", "track length", "reproj. error (px)", "seconds"]
    if has_gt:
        head += ["position RMSE", "position median"]
    lines = [f"# {title}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in results.items():
        if "skipped" in r:
            lines.append(f"| {labels.get(name, name)} | skipped: {r['skipped']} |")
            continue
        err = "-" if r["reproj_error"] is None else f"{r['reproj_error']:.2f}"
        cells = [labels.get(name, name), f"{r['registered']} / {r['images']}", str(r["points"]),
                 f"{r['track_length']:.2f}", err, f"{r['seconds']:.0f}"]
        if has_gt:
            cells += [f"{r.get('position_rmse', '-')}", f"{r.get('position_median', '-')}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _plain(value) -> dict:
    """A config mapping (or None) as a plain dict."""
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else dict(value or {})


def run_extractor(name: str, image_dir: Path, names: list[str], pairs: list, out: Path, task: DictConfig,
                  gt: dict, progress: bool = True) -> dict:
    from ruslam.features.hloc_io import write_pairs  # noqa: PLC0415
    from ruslam.features.pipeline import extract_features, match_features  # noqa: PLC0415
    from ruslam.models.registry import load_extractor  # noqa: PLC0415

    options = dict(_plain(task.get("extractor_options")).get(name) or {})
    if task.get("max_keypoints"):
        options.setdefault("max_keypoints", int(task.max_keypoints))
    extractor = load_extractor(name, device=task.device, **options)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    features = out / "features.h5"
    extract_features(image_dir, features, extractor, names, resize_max=task.get("resize_max"), progress=progress)
    pairs_path = out / "pairs.txt"
    write_pairs(pairs_path, pairs)
    matches = out / "matches.h5"
    match_features(features, pairs, matches, matcher=per_extractor(task.get("matcher"), name, "nn"),
                   ratio=per_extractor(task.get("ratio"), name), progress=progress)
    recon, n_models = reconstruct(image_dir, names, features, pairs_path, matches, out,
                                  min_num_matches=int(task.min_num_matches), seed=int(task.seed))
    return summarize(recon, n_models, len(names), time.perf_counter() - start, gt)


def run(cfg: DictConfig) -> dict:
    import torch  # noqa: PLC0415

    from ruslam.features.pipeline import list_images, make_pairs  # noqa: PLC0415

    task, dataset = cfg.task, cfg.dataset
    if dataset.get("root") is None:
        from ruslam.data.multiview import MultiViewConfig, render_multiview  # noqa: PLC0415

        render = _plain(dataset.get("render"))
        render = {k: tuple(v) if isinstance(v, list) else v for k, v in render.items()}
        image_dir = render_multiview(MultiViewConfig(**render), progress=True)
        title = dataset.get("label") or f"Rendered underwater multi-view set ({image_dir.name})"
    else:
        image_dir = Path(str(dataset.root)).expanduser()
        if not image_dir.is_dir():
            raise MissingInput(f"dataset.root={dataset.root}: no such folder.")
        title = dataset.get("label") or image_dir.name
    every = _every(dataset)
    names = list_images(image_dir, every)
    if every > 1:
        title += f", every {every}rd image" if every == 3 else f", every {every}th image"
    exhaustive = len(names) <= int(task.pairs.exhaustive_up_to)
    pairs = make_pairs(names, exhaustive=exhaustive, window=0 if exhaustive else int(task.pairs.window))
    gt = read_groundtruth_positions(image_dir, names)
    labels = _plain(task.get("labels"))
    out_dir = Path(cfg.out_dir)
    threads = torch.get_num_threads()
    if task.get("torch_threads"):
        torch.set_num_threads(int(task.torch_threads))
    results = {}
    try:
        for name in [str(n) for n in cfg.extractors]:
            print(f"[sfm] {name}: {len(names)} images, {len(pairs)} pairs", flush=True)
            results[name] = run_extractor(name, image_dir, names, pairs, out_dir / Path(name).stem, task, gt)
            print(f"[sfm] {name}: {json.dumps(results[name])}", flush=True)
    finally:
        torch.set_num_threads(threads)
    summary = {"dataset": str(image_dir), "every": every, "pairs": len(pairs),
               "pairing": "exhaustive" if exhaustive else f"sequential window {int(task.pairs.window)}",
               "camera": colmap_camera(image_dir)[0], "results": results}
    atomic_write(out_dir / "results.json", json.dumps(summary, indent=2) + "\n")
    table = table_markdown(results, labels, title)
    atomic_write(out_dir / "table.md", table)
    print(table)
    return summary
