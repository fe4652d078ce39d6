"""Monocular scale drift on a robustness-matrix variant, against the rendered ground truth.

    nice .venv/bin/python bench/scale_drift.py lowtex_s4 --split dev --extractors orb xfeat
    nice .venv/bin/python bench/scale_drift.py lowtex_s4 --extractors xfeat --frames 40 --map-depth

Runs the SLAM with the evaluation's options for each extractor (the library's presets, `dataset.extractor_options`;
extra `--set slam.<key>=<value>` overrides), loop closing off, so the scale is what tracking and local mapping keep
on their own. Prints the estimated / true distance between frames ten apart along the trajectory (the estimate's
scale; monocular, so only its change matters) and the ratio of the last window to the first.

`--map-depth` also prints, per frame, the scale of the frame's step (est / true) next to the scale of the depths of
the map points it tracked (estimated depth / depth of the rendered scene at the keypoint, median): in a healthy
run the two agree; a step scale below the depth scale is tracking that shortens the motion against its own map.
Next to them, the share of those matches more than 3 px from where the true pose projects their point (its median
true position over all the frames that tracked it): on repetitive texture, a corner matched to a look-alike.
`--start N` runs the sequence from frame N (single runs on the tiled pool change with the first frame).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ruslam.data.robustness import MAX_INCIDENCE_DEG, SurveyConfig, survey_poses, survey_seafloor  # noqa: E402
from ruslam.data.synthetic_sequence import pixel_rays, render, texture_pyramid  # noqa: E402
from ruslam.data.tiled_pool import make_pool, render_pool  # noqa: E402
from ruslam.eval.slam_report import open_sequence, slam_config_for, slam_extractors  # noqa: E402
from ruslam.slam import tracking  # noqa: E402
from ruslam.slam.map import inverse_pose, transform  # noqa: E402
from ruslam.slam.system import run  # noqa: E402


def window_scales(frames: np.ndarray, centres: np.ndarray, truth: np.ndarray, window: int = 10) -> list[tuple]:
    """(first frame, est / true distance) over consecutive windows of `window` posed frames."""
    out = []
    for k in range(0, len(frames) - window, window):
        true = np.linalg.norm(truth[frames[k + window]] - truth[frames[k]])
        out.append((int(frames[k]), float(np.linalg.norm(centres[k + window] - centres[k]) / max(true, 1e-12))))
    return out


class MapDepthProbe:
    """Wraps `Tracker._track_local_map`: after each frame, its step scale and the depth scale of its tracked points."""

    def __init__(self, survey: SurveyConfig, start: int = 0):
        poses = survey_poses(survey)
        self.poses = poses[start:]  # indexed like the frames run
        rays = pixel_rays(survey.camera())
        if survey.scene == "pool":
            pool = make_pool(poses[:, :2, 3], survey.tile_m, survey.seed)
            self.render = lambda i: render_pool(pool, rays, self.poses[i])[1]
        else:
            floor = survey_seafloor(survey, poses)
            levels = texture_pyramid(floor.texture)
            self.render = lambda i: render(floor, rays, self.poses[i], texture_levels=levels,
                                           max_incidence_deg=MAX_INCIDENCE_DEG)[1]
        self.K = survey.camera().K
        self.last = None
        self.rows = []
        self.matches = []  # per frame: (map point ids, keypoints, their true positions in the world)

    def wrap(self, track_local_map):
        def probed(tracker, frame):
            ok = track_local_map(tracker, frame)
            self.measure(frame, tracker.store)
            return ok
        return probed

    def measure(self, frame, store) -> None:
        used = np.nonzero((frame.points >= 0) & ~frame.outliers)[0]
        if not len(used):
            return
        kp = frame.keypoints[used]
        z_est = transform(frame.T_cw, store.position[frame.points[used]])[:, 2]
        h, w = frame.image_size[1], frame.image_size[0]
        rng = self.render(frame.index)
        r = rng[np.clip(np.round(kp[:, 1]).astype(int), 0, h - 1), np.clip(np.round(kp[:, 0]).astype(int), 0, w - 1)]
        rays = np.column_stack([(kp - self.K[:2, 2]) / np.diag(self.K)[:2], np.ones(len(kp))])
        z_true = r / np.linalg.norm(rays, axis=1)
        self.matches.append((frame.points[used], kp, transform(self.poses[frame.index], rays / np.linalg.norm(
            rays, axis=1, keepdims=True) * r[:, None])))
        centre = inverse_pose(frame.T_cw)[:3, 3]
        step = np.nan
        if self.last is not None:
            i0, c0 = self.last
            step = np.linalg.norm(centre - c0) / np.linalg.norm(self.poses[frame.index, :3, 3] - self.poses[i0, :3, 3])
        self.rows.append((frame.index, step, float(np.median(z_est / z_true)), len(used)))
        self.last = (frame.index, centre)

    def wrong_shares(self, px: float = 3.0) -> list[float]:
        """Per measured frame, the share of its matches more than `px` from the true projection of their point."""
        seen: dict[int, list] = {}
        for ids, _, xyz in self.matches:
            for j, x in zip(ids, xyz, strict=True):
                seen.setdefault(int(j), []).append(x)
        where = {j: np.median(xs, axis=0) for j, xs in seen.items()}
        shares = []
        for (i, *_), (ids, kp, _) in zip(self.rows, self.matches, strict=True):
            X = transform(inverse_pose(self.poses[i]), np.array([where[int(j)] for j in ids]))
            uv = X[:, :2] / X[:, 2:] * np.diag(self.K)[:2] + self.K[:2, 2]
            shares.append(float(np.mean(np.linalg.norm(uv - kp, axis=1) > px)))
        return shares


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("variant")
    ap.add_argument("--split", default="dev")
    ap.add_argument("--extractors", nargs="+", default=["orb", "xfeat"])
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--map-depth", action="store_true")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--set", nargs="*", default=[], help="slam.<key>=<value> overrides")
    args = ap.parse_args()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        cfg = compose("evaluate", overrides=["task=slam", "dataset=robustness", f"dataset.split={args.split}"])
    entry = OmegaConf.to_container(cfg.dataset.sequences, resolve=True)[args.variant]
    sequence = open_sequence(cfg.dataset, args.variant, entry)
    sequence = sequence.subset(range(args.start, len(sequence))) if args.start else sequence
    survey = SurveyConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in entry.items()})
    truth = survey_poses(survey)[args.start:, :3, 3]
    for name in args.extractors:
        slam = OmegaConf.merge(slam_config_for(cfg, name), OmegaConf.from_dotlist(
            ["loop.enabled=false", "progress=false", f"max_frames={args.frames or 'null'}"]
            + [s.removeprefix("slam.") for s in args.set]))
        probe = MapDepthProbe(survey, args.start) if args.map_depth else None
        original = tracking.Tracker._track_local_map
        if probe is not None:
            tracking.Tracker._track_local_map = probe.wrap(original)
        try:
            extractor = slam_extractors([name], cfg)[0][name]
            traj = run(sequence, extractor, instantiate(slam))
        finally:
            tracking.Tracker._track_local_map = original
        scales = window_scales(traj.frame_indices, traj.poses[:, :3, 3], truth)
        drift = scales[-1][1] / scales[0][1] if scales else float("nan")
        print(f"{args.variant} {name}: {len(traj)}/{traj.num_frames} frames posed, {traj.num_keyframes} keyframes, "
              f"scale last/first window {drift:.3f}")
        print("  scale per 10 frames: " + " ".join(f"{i + args.start}:{s:.3f}" for i, s in scales))
        if probe is not None:
            for (i, step, depth, n), wrong in zip(probe.rows, probe.wrong_shares(), strict=True):
                print(f"  frame {i + args.start:4d}: step scale {step:.3f}  map-depth scale {depth:.3f}  ({n} inliers, "
                      f"{wrong:.0%} off their point)")


if __name__ == "__main__":
    main()
