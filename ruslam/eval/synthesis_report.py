"""`python evaluate.py task=synthesis`: paper Table 1, how real the pseudo-underwater images look.

Methods, all scored at the dataset's height x width (UIQM depends on image size):
- in-air: the RGB-D source images themselves;
- ours: eq. 4 (`PseudoUnderwater`: random Jerlov type, A drawn from the pool, motion PSF, noise, low light);
- UWCNN-style baseline: eq. 1 with the same image's Jerlov beta and one global A (the pool mean), no PSF/noise;
- real: a folder of real underwater images (``dataset.reference``), centre-cropped to the aspect and resized.

Every image is quantized to 8 bits before scoring, as a saved image or a photograph is: the EME of UISM takes
ln(max/min) of Sobel maps, and float images give near-zero minima (1e-6 rather than 0 or >= 1) on flat areas
that would dominate it.

The pool A* comes from ``dataset.background_light`` (eqs. 5-7 on N images, P regions each), else from the
reference folder, else the embedded `default_pool`. Realism = distance of a method's mean metrics to the real
images' means: per metric |mean - real mean|, and one figure, the RMS over UCIQE, UICM, UISM and UIConM of that
difference divided by the real images' std (UIQM is left out because it is a sum of the other three).

Writes ``table.md``, ``table.csv`` and ``grid.png`` (in-air | ours at three water types | baseline | real) into
cfg.out_dir (each written to a temporary name, then renamed) and returns the numbers.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import cv2
import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from ruslam.atomic_files import atomic_write
from ruslam.data.background_light import background_light_pool, list_images, read_rgb
from ruslam.data.synthesis import attenuate_eq1
from ruslam.data.water import check_water_type
from ruslam.errors import InputError
from ruslam.eval.quality import quality

METRICS = ("uciqe", "uiqm", "uicm", "uism", "uiconm")
REALISM_METRICS = ("uciqe", "uicm", "uism", "uiconm")
HEADERS = {"uciqe": "UCIQE", "uiqm": "UIQM", "uicm": "UICM", "uism": "UISM", "uiconm": "UIConM"}
PAPER_HEIGHT = 480


def fit(image: np.ndarray, height: int, width: int, interpolation=cv2.INTER_AREA) -> np.ndarray:
    """Centre-crop ``image`` to the aspect height:width, then resize to exactly height x width."""
    h, w = image.shape[:2]
    if (h, w) == (height, width):
        return image
    if h * width > w * height:
        ch = max(1, round(w * height / width))
        image = image[(h - ch) // 2:(h - ch) // 2 + ch]
    else:
        cw = max(1, round(h * width / height))
        image = image[:, (w - cw) // 2:(w - cw) // 2 + cw]
    return cv2.resize(image, (width, height), interpolation=interpolation)


def select_indices(n_source: int, num_images: int, seed: int) -> list[int]:
    """All indices if the source is no larger than the split, else a seeded random subset (sorted)."""
    if num_images < 1:
        raise InputError(f"dataset.num_images must be >= 1; got {num_images}.")
    if n_source <= num_images:
        return list(range(n_source))
    return sorted(np.random.default_rng(seed).choice(n_source, size=num_images, replace=False).tolist())


def summarize(rows: list[dict]) -> dict:
    values = {m: np.array([r[m] for r in rows]) for m in METRICS}
    return {"n": len(rows), "mean": {m: float(v.mean()) for m, v in values.items()},
            "std": {m: float(v.std()) for m, v in values.items()}}


def realism(summary: dict, real: dict) -> dict:
    """Per-metric |mean - real mean| and the std-normalised RMS distance over `REALISM_METRICS`."""
    diff = {m: abs(summary["mean"][m] - real["mean"][m]) for m in METRICS}
    z = [diff[m] / max(real["std"][m], 1e-12) for m in REALISM_METRICS]
    return {"abs_diff": diff, "distance": float(np.sqrt(np.mean(np.square(z))))}


def markdown_table(results: dict, labels: dict) -> str:
    has_real = "real" in results
    head = ["Method", *(HEADERS[m] for m in METRICS)] + (["Distance to real"] if has_real else [])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, res in results.items():
        cells = [f"{res['mean'][m]:.3f} ± {res['std'][m]:.3f}" for m in METRICS]
        if has_real:
            cells.append("—" if name == "real" else f"{res['realism']['distance']:.3f}")
        lines.append(f"| {labels[name]} (n={res['n']}) | " + " | ".join(cells) + " |")
    if has_real:
        lines += ["", "|mean − real mean| per metric (smaller = closer to real):", "",
                  "| Method | " + " | ".join(HEADERS[m] for m in METRICS) + " |", "|" + "---|" * (len(METRICS) + 1)]
        for name, res in results.items():
            if name != "real":
                lines.append(f"| {labels[name]} | "
                             + " | ".join(f"{res['realism']['abs_diff'][m]:.3f}" for m in METRICS) + " |")
    return "\n".join(lines) + "\n"


def csv_table(results: dict, labels: dict) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(["method", "n", *METRICS, *(f"{m}_std" for m in METRICS), "distance_to_real",
                     *(f"{m}_abs_diff_to_real" for m in METRICS)])
    for name, res in results.items():
        real = res.get("realism")
        writer.writerow([labels[name], res["n"], *(f"{res['mean'][m]:.6f}" for m in METRICS),
                         *(f"{res['std'][m]:.6f}" for m in METRICS),
                         f"{real['distance']:.6f}" if real else "",
                         *((f"{real['abs_diff'][m]:.6f}" for m in METRICS) if real else [""] * len(METRICS))])
    return buf.getvalue()


def grid_png(rows: list[list[np.ndarray]], titles: list[str]) -> bytes:
    """PNG bytes of a labelled grid; rows of equally sized float RGB images in [0,1] (None = blank)."""
    h, w = next(im for row in rows for im in row if im is not None).shape[:2]
    bar, pad = 22, 4
    canvas = np.full((bar + len(rows) * (h + pad), len(titles) * (w + pad), 3), 255, np.uint8)
    for c, title in enumerate(titles):
        cv2.putText(canvas, title, (c * (w + pad) + 3, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1,
                    cv2.LINE_AA)
    for r, row in enumerate(rows):
        for c, im in enumerate(row):
            if im is not None:
                y, x = bar + r * (h + pad), c * (w + pad)
                canvas[y:y + h, x:x + w] = np.clip(np.round(im * 255), 0, 255).astype(np.uint8)
    ok, png = cv2.imencode(".png", canvas[..., ::-1])
    if not ok:
        raise RuntimeError("OpenCV could not encode the grid as PNG.")
    return png.tobytes()


def load_reference(folder: str | Path, height: int, width: int) -> list[np.ndarray]:
    paths = list_images(folder)
    if not paths:
        raise InputError(f"Reference folder {folder} holds no images (expected real underwater RGB images).")
    return [fit(read_rgb(p).astype(np.float32), height, width) for p in paths]


def to_uint8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.round(image * 255.0), 0, 255).astype(np.uint8)


def _tensor(rgb: np.ndarray, depth: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None], torch.from_numpy(depth)[None]


def _image(x: torch.Tensor) -> np.ndarray:
    return x[0].permute(1, 2, 0).numpy()


def run(cfg: DictConfig) -> dict:
    threads = torch.get_num_threads()
    torch.set_num_threads(int(cfg.task.get("torch_threads", 1)))
    try:
        return _run(cfg)
    finally:
        torch.set_num_threads(threads)


def _run(cfg: DictConfig) -> dict:
    task, data = cfg.task, cfg.dataset
    height, width = int(data.height), int(data.width)
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    grid_types = [check_water_type(str(w)) for w in task.grid_water_types]
    reference = data.get("reference")
    light_folder = data.get("background_light") or reference
    pool = background_light_pool(light_folder, **OmegaConf.to_container(task.background_light), seed=int(cfg.seed))
    synth_conf = OmegaConf.to_container(task.synthesis, resolve=True)
    synth_conf["blur_length"] = float(synth_conf.get("blur_length", 10.0)) * height / PAPER_HEIGHT
    ours = instantiate(synth_conf, background_light=pool, seed=int(cfg.seed))
    fixed = {w: ours.for_water_type(w) for w in grid_types}
    global_A = torch.as_tensor(pool.mean(0), dtype=torch.float32)[None]
    real_images = load_reference(reference, height, width) if reference else []  # fail early on a bad folder

    source = instantiate(data.source)
    indices = select_indices(len(source), int(data.num_images), int(cfg.seed))
    scores = {"in_air": [], "ours": [], "baseline": []}
    grid_rows = []
    with torch.inference_mode():
        for i in tqdm(indices, desc="synthesis quality", unit="img"):
            sample = source[i]
            rgb = fit(np.asarray(sample["image"], np.float32), height, width)
            depth = fit(np.asarray(sample["depth"], np.float32), height, width, cv2.INTER_NEAREST)
            rgb_t, depth_t = _tensor(rgb, depth)
            uw = ours(rgb_t, depth_t, [i])
            beta = torch.as_tensor(ours.params(i)["beta"], dtype=torch.float32)[None]
            base = attenuate_eq1(rgb_t, depth_t, beta, global_A)
            for name, im in (("in_air", rgb), ("ours", _image(uw)), ("baseline", _image(base))):
                scores[name].append(quality(to_uint8(im)))
            if len(grid_rows) < int(task.grid_rows):
                row = [rgb, *(_image(f(rgb_t, depth_t, [i])) for f in fixed.values()), _image(base)]
                grid_rows.append(row + ([real_images[len(grid_rows) % len(real_images)]] if real_images else []))
        for im in tqdm(real_images, desc="real reference quality", unit="img"):
            scores.setdefault("real", []).append(quality(to_uint8(im)))

    results = {name: summarize(rows) for name, rows in scores.items()}
    if "real" in results:
        for name in ("in_air", "ours", "baseline"):
            results[name]["realism"] = realism(results[name], results["real"])
    labels = {"in_air": "In-air", "ours": "Ours (eq. 4)", "baseline": "UWCNN-style (eq. 1)",
              "real": f"Real ({Path(str(reference)).name})" if reference else "Real"}
    header = (f"# Synthesis quality (Table 1 layout)\n\n{len(indices)} images of {data.get('label', 'source')} at "
              f"{height}x{width}; background light: {light_folder or 'embedded default pool'} ({len(pool)} "
              f"entries); PSF {ours.blur_angle_deg:g} deg / {ours.blur_length:g} px; mean ± std over images.\n\n")
    atomic_write(out_dir / "table.md", (header + markdown_table(results, labels)).encode())
    atomic_write(out_dir / "table.csv", csv_table(results, labels).encode())
    titles = ["in-air", *(f"ours {w}" for w in grid_types), "UWCNN-style"] + (["real"] if real_images else [])
    atomic_write(out_dir / "grid.png", grid_png(grid_rows, titles))
    return {"results": results, "labels": labels, "out_dir": str(out_dir)}
