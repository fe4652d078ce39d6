"""Local bundle adjustments recorded from real SLAM runs, each solver against gtsam problem by problem.

    nice .venv/bin/python bench/ba_regression.py DATA_ROOT [--cache cache/ba_problems] [--sources ...]
        [--solvers schur] [--rerecord] [--record-only]

DATA_ROOT holds the real dev sequences (`tum_freiburg3_cabinet_keyframes`, `subvo_pool_first110`,
`vamr_desk_handheld`); a source whose folder is missing is skipped. The `grid:` sources are robustness-matrix
variants (conf/dataset/robustness.yaml, rendered into the RUSLAM cache).

Recording: each source runs once through the SLAM (synchronous, the extractor's preset, one torch thread, gtsam as
local-BA solver) with `bundle_adjustment` wrapped, so that every local BA's arguments go to
CACHE/<source>/<n>.npz before gtsam solves them; a source whose folder is already there is not run again
(`--rerecord` runs it anew). Nothing is written to the repository: the cache folder is ignored by git.

Comparison: every recorded problem is solved by gtsam and by each solver of `--solvers`; a problem agrees when the
final cost is within 1e-3 relative of gtsam's and every keyframe pose within 1 mm (map units) and 0.01 deg of
gtsam's. The cost is the second pass's objective (Huber on the whitened reprojection errors, gtsam's loss) over the
observations gtsam keeps as inliers, evaluated at each solution. Printed per source: problems, agreeing problems,
the worst cost ratio, the worst pose differences, inlier decisions that differ, and the solve times.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from ruslam.slam.bundle_adjustment import SOLVERS, bundle_adjustment, robust_cost

# source -> (kind, where, extractor, max frames): kind "folder" reads DATA_ROOT/where, "grid" a robustness variant
SOURCES = {
    "tum_cabinet/xfeat": ("folder", "tum_freiburg3_cabinet_keyframes", "xfeat", None),
    "pool/xfeat": ("folder", "subvo_pool_first110", "xfeat", None),
    "pool/uwnet_xfeat": ("folder", "subvo_pool_first110", "uwnet_xfeat", None),
    "desk/orb": ("folder", "vamr_desk_handheld", "orb", 300),
    "grid_dev_hard/orb": ("grid", "dev:hard", "orb", None),
    "grid_test_turn10/xfeat": ("grid", "test:turn10", "xfeat", None),
}
COST_RTOL, POSE_M, POSE_DEG = 1e-3, 1e-3, 0.01


def load_source(kind: str, where: str, data_root: Path):
    """The sequence of a source, or None when its folder is missing."""
    if kind == "folder":
        from ruslam.data.sequence_folder import read_sequence  # noqa: PLC0415

        path = data_root / where
        return read_sequence(path) if path.is_dir() else None
    from omegaconf import OmegaConf  # noqa: PLC0415

    from ruslam.data.robustness import robustness_sequence  # noqa: PLC0415

    split, name = where.split(":")
    grid = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "dataset" / "robustness.yaml")
    knobs = OmegaConf.to_container(grid.splits[split][name])
    return robustness_sequence(name, progress=False, width=grid.reader.width, height=grid.reader.height, **knobs)


def record(source: str, data_root: Path, folder: Path) -> int | None:
    """Run the SLAM on a source with every local BA's arguments saved to folder/<n>.npz; the number of problems
    (None when the source's data is missing)."""
    import torch  # noqa: PLC0415

    import ruslam.slam.system as system  # noqa: PLC0415
    from ruslam.slam import run  # noqa: PLC0415
    from ruslam.slam.presets import preset  # noqa: PLC0415

    kind, where, name, max_frames = SOURCES[source]
    seq = load_source(kind, where, data_root)
    if seq is None:
        return None
    torch.set_num_threads(1)
    options = {"max_keypoints": 1000} if kind == "grid" and name != "orb" else {}  # the grid's extractor_options
    extractor, cfg = preset(name, **options)
    import dataclasses  # noqa: PLC0415

    cfg = dataclasses.replace(cfg, progress=False, synchronous=True, max_frames=max_frames)
    folder.mkdir(parents=True, exist_ok=True)
    count = [0]

    def recording(poses, fixed, points, obs_pose, obs_point, obs_uv, K, obs_right=None, K_right=None,
                  T_c0_c1=None, iterations=(5, 10), sigma=1.0, **kwargs):
        np.savez_compressed(
            folder / f"{count[0]:04d}.npz", poses=poses, fixed=fixed, points=points, obs_pose=obs_pose,
            obs_point=obs_point, obs_uv=obs_uv, K=K, iterations=np.asarray(iterations), sigma=sigma,
            **({} if obs_right is None else {"obs_right": obs_right}),
            **({} if K_right is None else {"K_right": K_right, "T_c0_c1": T_c0_c1}))
        count[0] += 1
        return bundle_adjustment(poses, fixed, points, obs_pose, obs_point, obs_uv, K, obs_right, K_right, T_c0_c1,
                                 iterations=iterations, sigma=sigma, **kwargs)

    original = system.bundle_adjustment
    system.bundle_adjustment = recording
    try:
        start = time.perf_counter()
        result = run(seq, extractor, cfg)
    finally:
        system.bundle_adjustment = original
    print(f"recorded {source}: {count[0]} local BAs, {result.tracked_ratio:.0%} of {len(result.timings)} frames, "
          f"{time.perf_counter() - start:.0f} s")
    return count[0]


def load_problem(path: Path) -> tuple[tuple, dict]:
    z = np.load(path)
    args = tuple(z[k] for k in ("poses", "fixed", "points", "obs_pose", "obs_point", "obs_uv", "K"))
    kwargs = {"obs_right": z["obs_right"] if "obs_right" in z else None,
              "K_right": z["K_right"] if "K_right" in z else None,
              "T_c0_c1": z["T_c0_c1"] if "T_c0_c1" in z else None,
              "iterations": tuple(int(i) for i in z["iterations"]), "sigma": float(z["sigma"])}
    return args, kwargs


def problem_cost(T, X, args, kwargs, use) -> float:
    """gtsam's robust cost of a solution over the observations in `use`."""
    oi, oj, uv = args[3], args[4], args[5]
    right = np.zeros(len(oi), bool) if kwargs["obs_right"] is None else kwargs["obs_right"].astype(bool)
    o = np.argsort(oi, kind="stable")
    return robust_cost(T, X, (oi[o], oj[o], uv[o], right[o]), use[o], args[6], kwargs["K_right"], kwargs["T_c0_c1"],
                       kwargs["sigma"])


def pose_differences(Ta: np.ndarray, Tb: np.ndarray) -> tuple[float, float]:
    """Largest camera-centre distance and rotation angle (deg) between two sets of T_cw."""
    centre = lambda T: -np.einsum("nji,nj->ni", T[:, :3, :3], T[:, :3, 3])  # noqa: E731
    dR = np.einsum("nji,njk->nik", Ta[:, :3, :3], Tb[:, :3, :3])
    angle = np.degrees(np.arccos(np.clip((np.trace(dR, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(centre(Ta) - centre(Tb), axis=1).max()), float(angle.max())


def compare(files: list[Path], solvers: list[str]) -> dict[str, dict]:
    rows = {s: {"agree": 0, "ratio": [], "dt": [], "dr": [], "inliers": 0, "time": 0.0} for s in solvers}
    rows["gtsam"] = {"time": 0.0}
    for path in files:
        args, kwargs = load_problem(path)
        start = time.perf_counter()
        ref = bundle_adjustment(*args, **kwargs, solver="gtsam")
        rows["gtsam"]["time"] += time.perf_counter() - start
        cost_ref = problem_cost(ref[0], ref[1], args, kwargs, ref[2])
        for solver in solvers:
            start = time.perf_counter()
            out = bundle_adjustment(*args, **kwargs, solver=solver)
            r = rows[solver]
            r["time"] += time.perf_counter() - start
            ratio = problem_cost(out[0], out[1], args, kwargs, ref[2]) / max(cost_ref, 1e-300)
            dt, dr = pose_differences(out[0], ref[0])
            r["ratio"].append(ratio)
            r["dt"].append(dt)
            r["dr"].append(dr)
            r["inliers"] += int(np.sum(out[2] != ref[2]))
            r["agree"] += abs(ratio - 1) <= COST_RTOL and dt <= POSE_M and dr <= POSE_DEG
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("data_root", type=Path, help="folder of the real dev sequences")
    parser.add_argument("--cache", type=Path, default=Path("cache/ba_problems"))
    parser.add_argument("--sources", nargs="+", default=list(SOURCES), choices=list(SOURCES))
    parser.add_argument("--solvers", nargs="+", default=[s for s in SOLVERS if s != "gtsam"],
                        choices=[s for s in SOLVERS if s != "gtsam"])
    parser.add_argument("--rerecord", action="store_true", help="run the SLAM again even when problems are cached")
    parser.add_argument("--record-only", action="store_true")
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    print(f"{'source':24s} {'solver':7s} {'problems':>8s} {'agree':>6s} {'cost ratio min/max':>19s} "
          f"{'max dpos mm':>11s} {'max drot deg':>12s} {'inlier diffs':>12s} {'ms (gtsam ms)':>14s}")
    for source in args.sources:
        folder = args.cache / source.replace("/", "_")
        if args.rerecord or not any(folder.glob("*.npz")):
            for old in folder.glob("*.npz"):
                old.unlink()
            if record(source, args.data_root, folder) is None:
                print(f"skipped {source}: {args.data_root / SOURCES[source][1]} is missing")
                continue
        if args.record_only:
            continue
        files = sorted(folder.glob("*.npz"))
        rows = compare(files, args.solvers)
        g = rows["gtsam"]["time"]
        for solver in args.solvers:
            r = rows[solver]
            print(f"{source:24s} {solver:7s} {len(files):8d} {r['agree']:6d} "
                  f"{min(r['ratio']):9.6f}/{max(r['ratio']):9.6f} {1e3 * max(r['dt']):11.4f} "
                  f"{max(r['dr']):12.5f} {r['inliers']:12d} "
                  f"{1e3 * r['time'] / len(files):6.1f} ({1e3 * g / len(files):5.1f})", flush=True)

if __name__ == "__main__":
    main()
