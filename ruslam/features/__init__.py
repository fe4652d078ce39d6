"""hloc's feature and match files from any extractor of the project (`python -m ruslam.features`)."""

from ruslam.features.hloc_io import names_to_pair, read_features, read_matches, read_pairs
from ruslam.features.pipeline import extract_features, list_images, make_pairs, match_features

__all__ = ["extract_features", "list_images", "make_pairs", "match_features", "names_to_pair", "read_features",
           "read_matches", "read_pairs"]
