"""Shared test fixtures: the optional real-sample folder, a composed-config helper, and the global-descriptor check."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
# Optional real samples (EUVP images, NYU frames, TUM keyframes): $RUSLAM_SAMPLES, else shared/data beside the clone.
SHARED_DATA = Path(os.environ.get("RUSLAM_SAMPLES", ROOT.parent / "shared" / "data"))


@pytest.fixture
def shared_data() -> Path:
    """The optional folder of real samples; tests using it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"{SHARED_DATA} is absent (optional real samples; set RUSLAM_SAMPLES)")
    return SHARED_DATA


def compose(config_name: str, overrides: list[str]):
    """Compose a Hydra config from conf/ as the entry points do (no run directory)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return hydra_compose(config_name=config_name, overrides=overrides, return_hydra_config=False)


def assert_same_global_descriptor(got, want) -> None:
    """Global descriptors [B, D] compared as retrieval scores them: unit vectors with a cosine near 1. A NetVLAD
    cluster that got almost no mass is intra-normalised from a residual near its epsilon, so its entries are float
    noise that differs between runtimes and CPUs (up to 2e-4 seen): an element-wise bound would fail there."""
    got, want = np.atleast_2d(np.asarray(got)), np.atleast_2d(np.asarray(want))
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-4)
    assert np.all(np.sum(got * want, axis=1) > 1 - 1e-4)
