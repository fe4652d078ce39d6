"""APE / RPE of an estimated trajectory against ground truth, through evo's Python API (paper 4.3).

Association (`evo.core.sync`), Umeyama alignment (`PoseTrajectory3D.align`, Sim3 with ``correct_scale`` for
monocular, SE3 for stereo) and the metrics (`evo.core.metrics`) are evo's own, so numbers are comparable with
`evo_ape` / `evo_rpe` runs on the same files. RPE pairs are 0.1 m apart along the ground truth, as in the paper.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
from evo.core import filters, metrics, sync
from evo.core.trajectory import PoseTrajectory3D

from ruslam.data.readers import Trajectory

ALIGNMENTS = ("sim3", "se3", "none")


@dataclass
class TrajectoryErrors:
    ape_rmse: float  # metres, after alignment
    rpe_rmse: float  # metres, translation part over ~rpe_delta of travelled ground truth (NaN if too short)
    scale: float  # scale of the alignment (1 for se3/none)
    matched: int  # poses associated with ground truth
    aligned: PoseTrajectory3D  # the estimate after alignment (for plots)
    reference: PoseTrajectory3D  # the associated ground truth


def to_evo(trajectory: Trajectory, name: str = "") -> PoseTrajectory3D:
    return PoseTrajectory3D(poses_se3=list(trajectory.poses), timestamps=trajectory.timestamps, meta={"name": name})


def evaluate_trajectory(estimate: Trajectory, reference: Trajectory, alignment: str = "sim3",
                        rpe_delta: float = 0.1, max_time_diff: float = 0.02) -> TrajectoryErrors:
    """RMSE of APE and RPE (translation parts) of ``estimate`` against ``reference`` after ``alignment``."""
    if alignment not in ALIGNMENTS:
        raise ValueError(f"alignment must be one of {ALIGNMENTS}, got {alignment!r}.")
    if len(estimate) < 3:
        raise ValueError(f"An estimated trajectory needs at least 3 poses to be evaluated, got {len(estimate)}.")
    if not np.all(np.isfinite(estimate.poses)):
        raise ValueError("The estimated trajectory contains NaN or infinite poses.")
    try:
        ref, est = sync.associate_trajectories(to_evo(reference, "reference"), to_evo(estimate, "estimate"),
                                               max_diff=max_time_diff)
    except sync.SyncException:
        raise ValueError(f"No estimated pose lies within {max_time_diff} s of a ground-truth timestamp "
                         f"(estimate {estimate.timestamps[0]:.3f}-{estimate.timestamps[-1]:.3f} s, ground truth "
                         f"{reference.timestamps[0]:.3f}-{reference.timestamps[-1]:.3f} s).") from None
    if ref.num_poses < 3:
        raise ValueError(f"Only {ref.num_poses} estimated poses match ground-truth timestamps; need at least 3.")
    aligned = copy.deepcopy(est)
    scale = 1.0
    if alignment != "none":
        _, _, scale = aligned.align(ref, correct_scale=alignment == "sim3")
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, aligned))
    rpe_rmse = float("nan")
    rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=rpe_delta, delta_unit=metrics.Unit.meters,
                      all_pairs=False, pairs_from_reference=True)
    try:
        rpe.process_data((ref, aligned))
        rpe_rmse = float(rpe.get_statistic(metrics.StatisticsType.rmse))
    except (metrics.MetricsException, filters.FilterException):  # a path shorter than one delta: RPE is n/a
        pass
    return TrajectoryErrors(ape_rmse=float(ape.get_statistic(metrics.StatisticsType.rmse)), rpe_rmse=rpe_rmse,
                            scale=float(scale), matched=ref.num_poses, aligned=aligned, reference=ref)
