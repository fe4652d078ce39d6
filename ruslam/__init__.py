"""RU-SLAM: distilled underwater features (UWNet) and a compact visual SLAM."""

from ruslam.models.registry import load_extractor

__all__ = ["load_extractor"]
__version__ = "0.1.0"
