"""Jerlov beta per camera channel: names, physics of the channel ordering, and the band weighting."""

import numpy as np
import pytest

from ruslam.data import water
from ruslam.data.water import WATER_TYPES, beta_rgb, camera_response


def test_the_ten_jerlov_types():
    assert WATER_TYPES == ("I", "IA", "IB", "II", "III", "1C", "3C", "5C", "7C", "9C")


def test_clear_ocean_loses_red_first_and_turbid_coast_loses_blue_first():
    for name in ("I", "IA", "IB", "II"):
        r, g, b = beta_rgb(name)
        assert r > g > b > 0, name  # pure-water absorption dominates: red goes first
    r, g, b = beta_rgb("9C")
    assert b > g and b > r  # yellow substance and particles absorb blue most


def test_attenuation_grows_from_clear_to_turbid_in_every_channel():
    betas = np.stack([beta_rgb(n) for n in ("I", "IA", "IB", "II", "III")])
    assert np.all(np.diff(betas, axis=0) > 0)
    coastal = np.stack([beta_rgb(n) for n in ("1C", "3C", "5C", "7C", "9C")])
    assert np.all(np.diff(coastal, axis=0) > 0)


def test_channel_weights_are_camera_like_bands():
    wl, weights = camera_response()
    assert wl[0] == 400 and wl[-1] == 700 and np.all(weights >= 0)
    peaks = wl[np.argmax(weights, axis=0)]
    assert 580 <= peaks[0] <= 630 and 520 <= peaks[1] <= 570 and 430 <= peaks[2] <= 470


def test_beta_is_a_weighted_mean_of_kd(monkeypatch):
    """A flat Kd gives that value in every channel; a step Kd puts red above blue."""
    wl, _ = camera_response()
    monkeypatch.setattr(water, "kd_spectrum", lambda name: np.full(wl.shape, 0.37))
    np.testing.assert_allclose(water.beta_rgb("I"), 0.37, rtol=1e-12)
    monkeypatch.setattr(water, "kd_spectrum", lambda name: (wl > 580).astype(float))
    r, g, b = water.beta_rgb("I")
    assert r > 0.8 and b < 0.05 and 0 < g < r


def test_beta_lies_within_the_kd_of_its_band():
    import jerlov

    for name in WATER_TYPES:
        kd = jerlov.water(name, source="jerlov1976").kd(np.arange(400.0, 701.0))
        assert np.all(beta_rgb(name) >= kd.min()) and np.all(beta_rgb(name) <= kd.max())


def test_unknown_water_type_lists_the_valid_names():
    with pytest.raises(ValueError, match="Unknown Jerlov water type 'IV'.*I, IA, IB, II, III, 1C, 3C, 5C, 7C, 9C"):
        beta_rgb("IV")
