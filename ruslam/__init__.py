"""RU-SLAM: distilled underwater features (UWNet) and a compact visual SLAM.

`load_extractor` is imported on first use, so that the entry points can check a config before torch loads.
"""

__all__ = ["load_extractor"]
__version__ = "0.1.0"


def __getattr__(name: str):
    if name == "load_extractor":
        from ruslam.models.registry import load_extractor

        return load_extractor
    raise AttributeError(f"module 'ruslam' has no attribute {name!r}")
