"""`python evaluate.py task=slam`: paper Tables 3-5 (APE / RPE per sequence x method) and the turbidity sweep.

For every sequence of ``cfg.dataset`` and every extractor of ``cfg.extractors`` the SLAM runs once
(`ruslam.slam.system.run`); the estimate is scored with evo (`ruslam.eval.trajectory`, Sim3 alignment for
monocular, SE3 for stereo, RPE over 0.1 m). A run fails (x) when it tracks too few frames or its aligned
trajectory leaves the ground truth's bounding box by more than a margin (paper: "too short or diverges"), and
'Avg' is the mean over the sequences on which every compared method succeeds. Writes into ``cfg.out_dir``:
``table.md``/``table.csv``, ``runs.md``/``runs.csv`` (runtime, frames/s, keyframes, loops per run),
``trajectories/<sequence>/<method>.txt`` (TUM), ``plots/<sequence>.png`` (top view, ground truth vs each method),
and for the embedded synthetic sequences ``sweep.png`` (APE, RPE and tracked fraction per water type).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from hydra.utils import get_method, instantiate
from omegaconf import DictConfig, OmegaConf

from ruslam.atomic_files import atomic_path, atomic_write
from ruslam.config_checks import SLAM_METRICS as METRICS
from ruslam.data.readers import Trajectory, write_tum_trajectory
from ruslam.errors import InputError, MissingInput
from ruslam.eval.trajectory import evaluate_trajectory
from ruslam.slam import two_view_odometry
from ruslam.slam.presets import EXTRACTOR_OPTIONS, slam_options

log = logging.getLogger(__name__)
FAIL = "×"
TITLES = {"tracked": "tracked fraction", "tracked_after_init": "tracked after initialisation", "maps": "maps",
          "tracked_all_maps": "frames in all maps",
          "ape_path": "APE as % of the path", "fps": "frames/s"}
ERRORS = ("ape", "rpe", "ape_path")  # metrics in metres (lower is better, meaningless for a failed run)
HIGHER_IS_BETTER = ("tracked", "tracked_after_init", "tracked_all_maps", "fps")


@dataclass
class RunResult:
    sequence: str
    method: str
    ok: bool
    reason: str  # why the run failed ("" on success)
    ape: float = math.nan  # m, RMSE after alignment
    rpe: float = math.nan  # m, RMSE over 0.1 m
    tracked: float = 0.0  # fraction of the sequence's frames with a pose
    tracked_after_init: float = 0.0  # fraction of the frames from the first posed one on that have a pose
    maps: int = 0  # maps the SLAM built (1 when it never lost itself for good; 0 when it never initialised)
    tracked_all_maps: float = 0.0  # fraction of the frames with a pose in any map (the reported one or another)
    ape_path: float = math.nan  # APE / length of the ground-truth path over the frames run
    frames: int = 0
    runtime_s: float = 0.0
    fps: float = 0.0
    keyframes: int = 0
    loops: int = 0


# ------------------------------------------------------------------------------------------- failure and Avg


def failure_reason(tracked: float, aligned_xyz: np.ndarray | None, reference_xyz: np.ndarray, rule,
                   ape: float | None = None) -> str:
    """"" when the run counts, else why not: tracked fraction below ``rule.min_tracked``, an aligned position
    farther than ``rule.bound_margin_m`` outside the ground truth's axis-aligned bounding box, or an APE above
    ``rule.max_ape_fraction`` of the ground-truth path length (both divergence: a Sim3 alignment shrinks a lost
    trajectory towards the centre of the box, where only the APE rule sees it)."""
    if tracked < rule.min_tracked:
        return f"tracked {tracked:.0%} of frames < {rule.min_tracked:.0%}"
    if aligned_xyz is None or len(aligned_xyz) == 0:
        return "no pose matched the ground truth"
    get = rule.get if hasattr(rule, "get") else lambda key: getattr(rule, key, None)
    fraction = get("max_ape_fraction")
    if fraction is not None and ape is not None:
        path = float(np.linalg.norm(np.diff(reference_xyz, axis=0), axis=1).sum())
        if ape > fraction * path:
            return f"diverged: APE {ape:.2f} m > {fraction:.0%} of the {path:.2f} m path"
    margin = get("bound_margin_m")
    if margin is not None:
        lo, hi = reference_xyz.min(axis=0) - margin, reference_xyz.max(axis=0) + margin
        outside = np.maximum(lo - aligned_xyz, aligned_xyz - hi).max()
        if outside > 0:
            return f"diverged: {outside:.2f} m beyond the ground-truth box + {margin} m"
    return ""


def average_over_common_successes(results: list[RunResult], sequences: list[str], methods: list[str],
                                  metrics: list[str]) -> tuple[dict, list[str]]:
    """{(method, metric): mean} over the sequences where every method succeeded, and those sequences."""
    by_key = {(r.sequence, r.method): r for r in results}
    common = [s for s in sequences if all(by_key.get((s, m)) is not None and by_key[(s, m)].ok for m in methods)]
    avg = {(m, k): (float(np.mean([getattr(by_key[(s, m)], k) for s in common])) if common else math.nan)
           for m in methods for k in metrics}
    return avg, common


def _cell(value: float, metric: str) -> str:
    if value is None or not np.isfinite(value):
        return FAIL
    if metric in ("tracked", "tracked_after_init", "tracked_all_maps"):
        return f"{100 * value:.0f}%"
    if metric == "ape_path":
        return f"{100 * value:.2f}%"
    if metric == "maps":
        return f"{value:.0f}"
    if metric == "fps":
        return f"{value:.1f}"
    return f"{value:.3f}"


def results_table(results: list[RunResult], sequences: list[str], methods: list[str], metrics: list[str],
                  labels: dict, title: str, row_label: str = "Sequence") -> tuple[str, str]:
    """(markdown, csv) in the paper's layout: one row per sequence + Avg, one column per method (x metric);
    failed runs are x (their tracked fraction is still shown), the best value of a row is bold (lowest error,
    highest tracked fraction)."""
    by_key = {(r.sequence, r.method): r for r in results}
    avg, common = average_over_common_successes(results, sequences, methods, metrics)
    rows = []
    for s in sequences:
        # errors of a failed run are meaningless (x); its tracked fraction etc. are measured and say how it failed
        rows.append((s, {(m, k): (getattr(by_key[(s, m)], k) if (s, m) in by_key
                                  and (by_key[(s, m)].ok or k not in ERRORS) else None)
                         for m in methods for k in metrics}))
    rows.append(("Avg", {key: (v if common else None) for key, v in avg.items()}))
    header = [row_label] + [f"{labels.get(m, m)} {METRICS[k]}" if len(metrics) > 1 else labels.get(m, m)
                            for m in methods for k in metrics]
    md = [f"### {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow([row_label] + [f"{m}_{k}" for m in methods for k in metrics])
    for name, values in rows:
        cells = []
        for k in metrics:
            ok = [v for (m, kk), v in values.items() if kk == k and v is not None and np.isfinite(v)]
            best = (max(ok) if k in HIGHER_IS_BETTER else min(ok)) if len(ok) > 1 and k != "maps" else None
            for m in methods:
                v = values[(m, k)]
                text = _cell(v, k)
                cells.append((m, k, f"**{text}**" if best is not None and v == best else text))
        order = {(m, k): c for m, k, c in cells}
        md.append("| " + " | ".join([name] + [order[(m, k)] for m in methods for k in metrics]) + " |")
        writer.writerow([name] + ["x" if values[(m, k)] is None or not np.isfinite(values[(m, k)])
                                  else f"{values[(m, k)]:.6g}" for m in methods for k in metrics])
    md += ["", f"{FAIL} = failure (too few frames tracked or trajectory diverged). Avg over the sequences where "
               f"every method succeeds: {', '.join(common) if common else 'none'}."]
    return "\n".join(md) + "\n", out.getvalue()


def runs_table(results: list[RunResult], labels: dict) -> tuple[str, str]:
    head = ["sequence", "method", "status", "frames", "tracked", "tracked_after_init", "maps", "tracked_all_maps",
            "runtime_s", "fps", "keyframes", "loops"]
    md = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(head + ["ape", "rpe", "ape_path", "reason"])
    for r in results:
        status = "ok" if r.ok else f"{FAIL} {r.reason}"
        md.append(f"| {r.sequence} | {labels.get(r.method, r.method)} | {status} | {r.frames} | {r.tracked:.0%} | "
                  f"{r.tracked_after_init:.0%} | {r.maps} | {r.tracked_all_maps:.0%} | {r.runtime_s:.1f} | "
                  f"{r.fps:.2f} | {r.keyframes} | "
                  f"{r.loops} |")
        writer.writerow([r.sequence, r.method, "ok" if r.ok else "x", r.frames, f"{r.tracked:.4f}",
                         f"{r.tracked_after_init:.4f}", r.maps, f"{r.tracked_all_maps:.4f}", f"{r.runtime_s:.2f}",
                         f"{r.fps:.3f}", r.keyframes,
                         r.loops, f"{r.ape:.6g}", f"{r.rpe:.6g}", f"{r.ape_path:.6g}", r.reason])
    return "\n".join(md) + "\n", out.getvalue()


# --------------------------------------------------------------------------------------------------- plots


def top_view_axes(xyz: np.ndarray) -> tuple[int, int]:
    """The two world axes along which the ground truth spreads most, in order (x-z for a camera driving on the
    floor of a y-down world, x-y for an aerial survey)."""
    a, b = sorted(np.argsort(-np.ptp(xyz, axis=0))[:2])
    return int(a), int(b)


def plot_top_view(path: Path, title: str, reference_xyz: np.ndarray, estimates: dict[str, np.ndarray]) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    a, b = top_view_axes(reference_xyz)
    fig, ax = plt.subplots(figsize=(6, 5))
    ax.plot(reference_xyz[:, a], reference_xyz[:, b], "k--", lw=1.5, label="ground truth")
    for name, xyz in estimates.items():
        ax.plot(xyz[:, a], xyz[:, b], lw=1.2, label=name)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(title=title, xlabel=f"{'xyz'[a]} [m]", ylabel=f"{'xyz'[b]} [m]")
    ax.legend(fontsize=8)
    _save(fig, path)


def plot_sweep(path: Path, results: list[RunResult], levels: list[str], methods: list[str], labels: dict) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    by_key = {(r.sequence, r.method): r for r in results}
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    x = np.arange(len(levels))
    for m in methods:
        runs = [by_key.get((s, m)) for s in levels]
        for ax, k in zip(axes, ("ape", "rpe", "tracked"), strict=True):
            y = [getattr(r, k) if r is not None and (r.ok or k == "tracked") else np.nan for r in runs]
            line, = ax.plot(x, y, "o-", label=labels.get(m, m))
            failed = [i for i, r in enumerate(runs) if r is not None and not r.ok and k != "tracked"]
            ax.plot(failed, [0] * len(failed), "x", color=line.get_color(), ms=10, mew=2)
    for ax, k in zip(axes, ("ape", "rpe", "tracked"), strict=True):
        ax.set_xticks(x, levels, rotation=30)
        ax.set_ylabel({"ape": "APE RMSE [m]", "rpe": "RPE RMSE [m] (0.1 m)", "tracked": "tracked fraction"}[k])
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("Turbidity sweep on the synthetic seafloor (x on the axis = failed run)")
    _save(fig, path)


def _save(fig, path: Path) -> None:
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------------- run


def open_sequence(dataset: DictConfig, name: str, entry: str):
    """Build one sequence with the dataset's reader; a missing dataset gives one sentence on where to get it."""
    reader = instantiate(dataset.reader)
    root = dataset.get("root", "__embedded__")
    if root == "__embedded__":  # generated sequences: entry is a level name, or a variant's knobs
        return reader(name=name, **entry) if isinstance(entry, dict) else reader(entry)
    path = Path(str(root)) / entry if root else None
    if path is None or not path.exists():
        raise MissingInput(f"Dataset {dataset.get('label') or dataset.name} not found: sequence {name} expected "
                           f"at {path if path else '<dataset.root>/' + entry}. {dataset.download} Then pass "
                           f"dataset.root=<folder>.")
    return reader(path)


def evaluate_run(sequence, estimate, method: str, alignment: str, rule, rpe_delta: float) -> tuple[RunResult, dict]:
    """Score one SLAM output (anything with timestamps, poses, num_frames, timings, num_keyframes, loops)."""
    runtime = float(np.sum(estimate.timings))
    frames = int(estimate.num_frames)
    posed = len(estimate.timestamps)
    tracked = posed / max(frames, 1)
    first = int(np.searchsorted(sequence.timestamps, np.min(estimate.timestamps) - 1e-6)) if posed else frames
    base = dict(sequence=sequence.name, method=method, tracked=tracked, frames=frames, runtime_s=runtime,
                tracked_after_init=posed / max(frames - first, 1) if posed else 0.0,
                maps=int(getattr(estimate, "num_maps", 1 if posed else 0)),
                tracked_all_maps=sum(getattr(estimate, "map_frames", None) or [posed]) / max(frames, 1),
                fps=frames / runtime if runtime > 0 else 0.0, keyframes=int(getattr(estimate, "num_keyframes", 0)),
                loops=len(getattr(estimate, "loops", [])))
    gt = sequence.groundtruth
    errors, reason = None, ""
    if gt is None:
        reason = "the sequence has no ground truth"
    elif len(estimate.timestamps) >= 3:
        try:
            errors = evaluate_trajectory(Trajectory(estimate.timestamps, estimate.poses), gt, alignment, rpe_delta)
        except ValueError as err:
            reason = str(err)
    if not reason:
        aligned = errors.aligned.positions_xyz if errors else None
        run_xyz = _positions_over(gt, sequence.timestamps[:frames])  # the frames run (slam.max_frames)
        reason = failure_reason(tracked, aligned, run_xyz if len(run_xyz) > 1 else gt.positions, rule,
                                errors.ape_rmse if errors else None)
    if reason:
        return RunResult(ok=False, reason=reason, **base), {}
    path = _path_length(gt, sequence.timestamps[:frames])
    return (RunResult(ok=True, reason="", ape=errors.ape_rmse, rpe=errors.rpe_rmse,
                      ape_path=errors.ape_rmse / path if path > 0 else math.nan, **base),
            {"aligned": errors.aligned.positions_xyz, "reference": errors.reference.positions_xyz})


def _positions_over(groundtruth, stamps: np.ndarray) -> np.ndarray:
    """Ground-truth positions between the first and the last of ``stamps`` (the frames that were run)."""
    if len(stamps) == 0:
        return np.zeros((0, 3))
    inside = (groundtruth.timestamps >= stamps[0] - 1e-6) & (groundtruth.timestamps <= stamps[-1] + 1e-6)
    return groundtruth.positions[inside]


def _path_length(groundtruth, stamps: np.ndarray) -> float:
    """Length of the ground-truth path over the frames that were run."""
    xyz = _positions_over(groundtruth, stamps)
    return float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum()) if len(xyz) > 1 else 0.0


def dataset_sequences(dataset: DictConfig) -> dict:
    """{name: entry} of the dataset: its ``sequences`` (a dict, or a list of names), or, when null, every
    sequence its ``discover`` function finds under ``root`` (a generic folder of sequences)."""
    if dataset.get("sequences") is None:
        if not dataset.get("root"):
            raise ValueError(f"Dataset {dataset.name} needs dataset.root=<folder of sequences>.")
        if not dataset.get("discover"):
            raise ValueError(f"Dataset {dataset.name} lists no sequences and has no discover function.")
        return get_method(dataset.discover)(dataset.root)
    sequences = OmegaConf.to_container(dataset.sequences, resolve=True)
    return sequences if isinstance(sequences, dict) else {str(s): str(s) for s in sequences}


def dataset_label(dataset: DictConfig, opened: dict) -> str:
    """The table title: the dataset's label, or for a generic folder its name, size and sensor."""
    if dataset.get("label"):
        return str(dataset.label)
    stereo = [s.stereo for s in opened.values()]
    sensor = "stereo" if all(stereo) else "monocular" if not any(stereo) else "mono and stereo"
    every = int(dataset.get("every") or 1)
    rate = f", 1 frame in {every}" if every > 1 else ""
    return f"{Path(str(dataset.root)).name}, {len(opened)} sequence(s) ({sensor}{rate})"


def slam_config_for(cfg, method: str):
    """The SLAM settings a method runs with: `slam`, then the library's preset for it (`ruslam.slam.presets`), then
    `task.slam_options.<method>`."""
    return OmegaConf.merge(cfg.slam, slam_options(method), (cfg.task.get("slam_options") or {}).get(method) or {})


def slam_extractors(names, cfg) -> tuple[dict, dict]:
    """`resolve_extractors` with the library's extractor presets, then `task.extractor_options`, then the dataset's."""
    from ruslam.eval.matching_report import resolve_extractors  # noqa: PLC0415 (shared name -> extractor rules)

    task = OmegaConf.merge({"extractor_options": EXTRACTOR_OPTIONS}, cfg.task)
    return resolve_extractors(list(names), task, cfg.dataset.get("extractor_options"))


def run(cfg: DictConfig, slam_run=None) -> dict:
    """Every sequence x extractor, the tables, plots and (embedded sequences) the turbidity sweep."""
    task, dataset = cfg.task, cfg.dataset
    out_dir = Path(cfg.out_dir)
    slam_run = slam_run or get_method(task.slam_runner)
    labels = dict(task.get("labels") or {})
    sequences = dataset_sequences(dataset)
    select = dataset.get("select")
    if select:  # dataset.select=[MH01,MH03]: a subset, in the given order
        unknown = [str(s) for s in select if str(s) not in sequences]
        if unknown:
            raise InputError(f"dataset.select names unknown sequence(s) {unknown}; expected some of {list(sequences)}.")
        sequences = {str(s): sequences[str(s)] for s in select}
    opened = {name: open_sequence(dataset, name, entry) for name, entry in sequences.items()}  # fail early
    extractors, skipped = slam_extractors(cfg.extractors, cfg)
    # the chained two-view odometry baseline, with the extractors named in task.two_view_vo
    vo_extractors, vo_skipped = slam_extractors([str(n) for n in task.get("two_view_vo") or []], cfg)
    skipped.update(vo_skipped)
    runners = {m: (e, slam_run, m) for m, e in extractors.items()}
    runners.update({f"vo_{m}": (e, two_view_odometry.run, m)
                    for m, e in vo_extractors.items()})
    for m in vo_extractors:
        labels.setdefault(f"vo_{m}", f"Two-view VO ({labels.get(m, m)})")
    methods = list(runners)
    rule = OmegaConf.merge(task.failure, dataset.get("failure") or {})  # a dataset may rescale the bound
    label = dataset_label(dataset, opened)
    results, curves = [], {}
    for name, seq in opened.items():
        seq.name = name
        for method, (extractor, runner, settings) in runners.items():
            slam_cfg = slam_config_for(cfg, settings)
            try:
                estimate = runner(seq, extractor, slam_cfg)
            except RuntimeError as exc:  # a failed solve (gtsam raises RuntimeError) or mapping thread: an x cell;
                # programming errors (TypeError, KeyError, ValueError...) propagate rather than hide as a failed run
                log.exception("SLAM crashed on %s with %s", name, method)
                results.append(RunResult(name, method, False, f"crashed: {type(exc).__name__}: {exc}"))
                continue
            if len(estimate.timestamps):
                write_tum_trajectory(_mkdir(out_dir / "trajectories" / name) / f"{method}.txt",
                                     Trajectory(estimate.timestamps, estimate.poses))
            else:
                print(f"[slam] {name} / {method}: no frame got a pose, so no trajectory file is written.")
            alignment = dataset.alignment if dataset.alignment != "auto" else ("se3" if seq.stereo else "sim3")
            result, curve = evaluate_run(seq, estimate, method, alignment, rule, task.rpe_delta)
            results.append(result)
            curves.setdefault(name, {})[method] = curve
            print(f"[slam] {name} / {method}: " + (f"APE {result.ape:.3f} m ({result.ape_path:.2%} of the path), "
                  f"RPE {result.rpe:.3f} m" if result.ok else f"{FAIL} {result.reason}") +
                  f", tracked {result.tracked:.0%} ({result.tracked_after_init:.0%} after initialisation), "
                  f"{result.maps} map(s), {result.loops} loop(s), {result.fps:.1f} frames/s", flush=True)
        ref = opened[name].groundtruth
        if ref is not None:
            plot_top_view(out_dir / "plots" / f"{name}.png", f"{label}: {name}", ref.positions,
                          {labels.get(m, m): c["aligned"] for m, c in curves.get(name, {}).items() if c})
    metrics = list(dataset.metrics)
    errors = [METRICS[k] for k in metrics if k in ("ape", "rpe")]
    others = [TITLES[k] for k in metrics if k not in ("ape", "rpe")]
    title = f"{label}: RMSE of {' and '.join(errors)} (m)" + "".join(f", {t}" for t in others)
    md, table_csv = results_table(results, list(sequences), methods, metrics, labels, title,
                                  row_label=dataset.get("row_label", "Sequence"))
    if skipped:
        md += "\nSkipped:\n" + "".join(f"- {labels.get(n, n)} (`{n}`): {why}\n" for n, why in skipped.items())
    atomic_write(out_dir / "table.md", md)
    atomic_write(out_dir / "table.csv", table_csv)
    runs_md, runs_csv = runs_table(results, labels)
    atomic_write(out_dir / "runs.md", runs_md)
    atomic_write(out_dir / "runs.csv", runs_csv)
    if dataset.get("sweep", False) and methods:
        plot_sweep(out_dir / "sweep.png", results, list(sequences), methods, labels)
    summary = {"results": [asdict(r) for r in results], "skipped": skipped, "table": md}
    atomic_write(out_dir / "results.json", json.dumps(summary, indent=2, default=float))
    print(md)
    return summary


def _mkdir(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    return path
