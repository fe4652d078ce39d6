"""RGB-D folder reader: both layouts, every depth encoding, invalid depth, and bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from ruslam.data.rgbd_folder import RGBDFolder

H, W = 6, 8


def _colour(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)


def _write_rgb(path: Path, rgb: np.ndarray) -> None:
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))


def test_subfolder_layout_with_16bit_pgm_in_millimetres(tmp_path):
    (tmp_path / "color").mkdir(), (tmp_path / "depth").mkdir()
    depth_mm = np.full((H, W), 2500, np.uint16)
    depth_mm[0, 0] = 0  # the sensor's "no measurement"
    for key in ("10", "2"):
        _write_rgb(tmp_path / "color" / f"{key}.png", _colour(int(key)))
        assert cv2.imwrite(str(tmp_path / "depth" / f"{key}.pgm"), depth_mm)
    ds = RGBDFolder(tmp_path, depth_scale=1000.0)
    assert [ds[i]["id"] for i in range(len(ds))] == ["2", "10"]  # natural order
    s = ds[1]
    np.testing.assert_allclose(s["image"], _colour(10) / 255.0, atol=1e-6)  # RGB order kept, scaled to [0, 1]
    assert s["depth"].dtype == np.float32 and s["depth"][1, 1] == pytest.approx(2.5)
    assert np.isnan(s["depth"][0, 0]) and np.isnan(s["depth"]).sum() == 1


def test_tum_depth_scale(tmp_path):
    (tmp_path / "rgb").mkdir(), (tmp_path / "depth").mkdir()
    _write_rgb(tmp_path / "rgb" / "0.png", _colour())
    cv2.imwrite(str(tmp_path / "depth" / "0.png"), np.full((H, W), 5000, np.uint16))
    assert RGBDFolder(tmp_path, depth_scale=5000.0)[0]["depth"][2, 3] == pytest.approx(1.0)


def test_flat_layout_with_csv_and_npy_in_metres_and_invalid_values(tmp_path):
    depth = np.full((H, W), 1.5, np.float32)
    depth[0, :4] = [0.0, -2.0, np.nan, np.inf]
    depth[5, 7] = 9.25
    _write_rgb(tmp_path / "img42.jpg", _colour())
    np.savetxt(tmp_path / "depth42.csv", depth, delimiter=",")
    _write_rgb(tmp_path / "rgb_7.png", _colour(1))
    np.save(tmp_path / "depth_7.npy", depth)
    (tmp_path / "README.md").write_text("not an image")
    ds = RGBDFolder(tmp_path)
    assert [ds[i]["id"] for i in range(2)] == ["7", "42"]
    for i in range(2):
        d = ds[i]["depth"]
        assert d.shape == (H, W) and d[5, 7] == pytest.approx(9.25) and d[3, 3] == pytest.approx(1.5)
        assert np.isnan(d[0, :4]).all() and np.isnan(d).sum() == 4


def test_shared_nyu_samples(shared_data):
    ds = RGBDFolder(shared_data / "rgbd" / "nyu_samples")
    assert len(ds) == 2
    s = ds[0]
    assert s["id"] == "42" and s["image"].shape == (480, 640, 3) and s["depth"].shape == (480, 640)
    # SOURCES.md: hole-filled depth in metres, 1.33-3.61 m for image 42
    assert np.nanmin(s["depth"]) == pytest.approx(1.33) and np.nanmax(s["depth"]) == pytest.approx(3.61)


def test_shared_slambook_frames(shared_data):
    ds = RGBDFolder(shared_data / "rgbd" / "slambook_rgbd_poses", depth_scale=1000.0)
    assert [ds[i]["id"] for i in range(len(ds))] == ["1", "2", "3", "4", "5"]
    d = ds[0]["depth"]
    valid = np.isfinite(d)
    assert 0.3 < valid.mean() < 1.0  # Kinect holes became NaN
    assert 0.5 < np.median(d[valid]) < 5.0  # indoor room, millimetres scaled to metres


def test_empty_folder(tmp_path):
    with pytest.raises(ValueError, match="holds no colour/depth pairs"):
        RGBDFolder(tmp_path)


def test_missing_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        RGBDFolder(tmp_path / "nope")


def test_unpaired_files(tmp_path):
    _write_rgb(tmp_path / "img1.png", _colour())
    _write_rgb(tmp_path / "img2.png", _colour())
    np.save(tmp_path / "depth1.npy", np.ones((H, W), np.float32))
    with pytest.raises(ValueError, match="without a colour/depth partner, e.g. .*img2.png"):
        RGBDFolder(tmp_path)


def test_grayscale_colour_image(tmp_path):
    cv2.imwrite(str(tmp_path / "img1.png"), np.zeros((H, W), np.uint8))
    np.save(tmp_path / "depth1.npy", np.ones((H, W), np.float32))
    with pytest.raises(ValueError, match="img1.png is grayscale"):
        RGBDFolder(tmp_path)[0]


def test_16bit_colour_image(tmp_path):
    cv2.imwrite(str(tmp_path / "img1.png"), np.zeros((H, W, 3), np.uint16))
    np.save(tmp_path / "depth1.npy", np.ones((H, W), np.float32))
    with pytest.raises(ValueError, match="img1.png is uint16 \\(16-bit\\); 8-bit RGB is expected"):
        RGBDFolder(tmp_path)[0]


def test_size_mismatch(tmp_path):
    _write_rgb(tmp_path / "img1.png", _colour())
    np.save(tmp_path / "depth1.npy", np.ones((H + 1, W), np.float32))
    with pytest.raises(ValueError, match="is 7x8 but its colour image is 6x8"):
        RGBDFolder(tmp_path)[0]


def test_all_invalid_depth_names_the_sample(tmp_path):
    _write_rgb(tmp_path / "img1.png", _colour())
    cv2.imwrite(str(tmp_path / "depth1.png"), np.zeros((H, W), np.uint16))
    with pytest.raises(ValueError, match="sample '1'.*no valid pixel"):
        RGBDFolder(tmp_path)[0]


def test_8bit_depth_is_refused(tmp_path):
    _write_rgb(tmp_path / "img1.png", _colour())
    cv2.imwrite(str(tmp_path / "depth1.png"), np.full((H, W), 9, np.uint8))
    with pytest.raises(ValueError, match="8-bit, which cannot hold metric depth"):
        RGBDFolder(tmp_path)[0]


def test_corrupt_csv_depth(tmp_path):
    _write_rgb(tmp_path / "img1.png", _colour())
    (tmp_path / "depth1.csv").write_text("1.0,abc\n")
    with pytest.raises(ValueError, match="depth1.csv cannot be read as a depth map"):
        RGBDFolder(tmp_path)[0]


def test_hydra_config_builds_the_reader(tmp_path):
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    _write_rgb(tmp_path / "img1.png", _colour())
    np.save(tmp_path / "depth1.npy", np.ones((H, W), np.float32))
    cfg = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "data" / "rgbd_folder.yaml")
    ds = instantiate(cfg, root=str(tmp_path))
    assert isinstance(ds, RGBDFolder) and ds.depth_scale == 1000.0 and ds[0]["id"] == "1"


def test_sample_validator_refuses_float_colour_outside_unit_range_and_keeps_the_callers_depth():
    from ruslam.data.rgbd_sample import make_sample

    with pytest.raises(ValueError, match="must lie in \\[0, 1\\], got values in \\[255, 255\\]"):
        make_sample("x", np.full((H, W, 3), 255.0, np.float32), np.ones((H, W), np.float32))
    depth = np.zeros((H, W), np.float32)
    depth[0, 0] = 2.0
    out = make_sample("x", np.zeros((H, W, 3), np.float32), depth)
    assert np.isnan(out["depth"]).sum() == H * W - 1 and depth[1, 1] == 0.0  # input not modified


def test_tum_layout_pairs_by_nearest_timestamp(tmp_path):
    (tmp_path / "rgb").mkdir(), (tmp_path / "depth").mkdir()
    for t_rgb, t_depth, metres in (("100.000", "100.011", 1.0), ("100.033", "100.040", 2.0), ("100.066", None, 0)):
        _write_rgb(tmp_path / "rgb" / f"{t_rgb}.png", _colour())
        if t_depth:
            cv2.imwrite(str(tmp_path / "depth" / f"{t_depth}.png"), np.full((H, W), 5000 * metres, np.uint16))
    cv2.imwrite(str(tmp_path / "depth" / "100.300.png"), np.full((H, W), 5000, np.uint16))  # too far from any rgb
    with pytest.raises(ValueError, match="set max_time_diff"):
        RGBDFolder(tmp_path, depth_scale=5000.0)
    ds = RGBDFolder(tmp_path, depth_scale=5000.0, max_time_diff=0.02)
    assert [ds[i]["id"] for i in range(len(ds))] == ["100.000", "100.033"]  # 100.066 has no depth within 20 ms
    assert ds[0]["depth"][0, 0] == pytest.approx(1.0) and ds[1]["depth"][0, 0] == pytest.approx(2.0)


def test_time_association_needs_timestamp_names(tmp_path):
    _write_rgb(tmp_path / "img_a.png", _colour())
    np.save(tmp_path / "depth_a.npy", np.ones((H, W), np.float32))
    with pytest.raises(ValueError, match="timestamps in seconds"):
        RGBDFolder(tmp_path, max_time_diff=0.02)
