"""The SLAM: `run(sequence, extractor, cfg) -> SLAMTrajectory` (synchronous or threaded), see `system.py`;
`preset(name)` gives an extractor and the SLAM settings it runs with (`presets.py`)."""

from ruslam.slam.presets import preset
from ruslam.slam.system import SLAMConfig, SLAMTrajectory, run, write_tum

__all__ = ["SLAMConfig", "SLAMTrajectory", "preset", "run", "write_tum"]
