"""The SLAM: `run(sequence, extractor, cfg) -> SLAMTrajectory` (synchronous or threaded), see `system.py`."""

from ruslam.slam.system import SLAMConfig, SLAMTrajectory, run, write_tum

__all__ = ["SLAMConfig", "SLAMTrajectory", "run", "write_tum"]
