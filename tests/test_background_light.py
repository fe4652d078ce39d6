"""Background light A (eqs. 5-7): region maths, pool estimation from a folder, bad input, embedded default."""

import cv2
import numpy as np
import pytest

from ruslam.data.background_light import (
    ambient_rgb,
    background_light_pool,
    default_pool,
    estimate_pool,
    region_light,
    regions_background_light,
)


def _write(folder, n, rng, size=(24, 32)):
    folder.mkdir(exist_ok=True)
    for i in range(n):
        img = rng.integers(0, 256, (*size, 3), dtype=np.uint8)
        cv2.imwrite(str(folder / f"{i:02d}.png"), img)
    return folder


def test_region_light_by_hand():
    region = np.zeros((8, 8, 3))
    region[2, 3] = [0.2, 0.1, 0.5]
    region[5, 1] = [0.1, 0.6, 0.3]  # V = (0.2, 0.6, 0.5) per channel max (eq. 5)
    L, eta = region_light(region)
    assert L == pytest.approx(0.6)  # eq. 7
    np.testing.assert_allclose(eta, [1 / 3, 1.0, 5 / 6])  # eq. 6
    np.testing.assert_allclose(L * eta, [0.2, 0.6, 0.5])


def test_every_entry_is_the_channel_max_of_some_8x8_window():
    rng = np.random.default_rng(1)
    image = rng.random((16, 20, 3))
    A = regions_background_light(image, 8, np.random.default_rng(0))
    windows = np.array([image[y:y + 8, x:x + 8].reshape(-1, 3).max(0) for y in range(9) for x in range(13)])
    for a in A:
        assert np.min(np.abs(windows - a).max(1)) < 1e-12


def test_estimate_pool_shape_seed_and_values(tmp_path):
    folder = _write(tmp_path / "uw", 12, np.random.default_rng(0))
    pool = estimate_pool(folder, num_images=10, regions_per_image=8, seed=3)
    assert pool.shape == (80, 3) and np.all((pool >= 0) & (pool <= 1))
    np.testing.assert_array_equal(pool, estimate_pool(folder, num_images=10, regions_per_image=8, seed=3))
    assert not np.array_equal(pool, estimate_pool(folder, num_images=10, regions_per_image=8, seed=4))
    assert estimate_pool(folder, num_images=2, regions_per_image=3).shape == (6, 3)


def test_16_bit_images_are_scaled_to_unit_range(tmp_path):
    folder = tmp_path / "uw16"
    folder.mkdir()
    img = np.zeros((8, 8, 3), np.uint16)
    img[..., 0], img[..., 1], img[..., 2] = 65535, 32768, 6554  # BGR on disk: B=1.0, G~0.5, R~0.1
    cv2.imwrite(str(folder / "a.png"), img)
    pool = estimate_pool(folder, num_images=1, regions_per_image=2)
    np.testing.assert_allclose(pool, [[6554 / 65535, 32768 / 65535, 1.0]] * 2)


def test_fewer_images_than_n_is_one_sentence(tmp_path):
    folder = _write(tmp_path / "uw", 3, np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"holds 3 images .*needs N = 10"):
        estimate_pool(folder, num_images=10)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        estimate_pool(tmp_path / "nowhere")


def test_unreadable_and_grayscale_images_are_named(tmp_path):
    folder = tmp_path / "bad"
    folder.mkdir()
    (folder / "broken.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(ValueError, match="broken.jpg"):
        estimate_pool(folder, num_images=1)
    (folder / "broken.jpg").unlink()
    cv2.imwrite(str(folder / "gray.png"), np.full((16, 16), 128, np.uint8))
    with pytest.raises(ValueError, match="gray.png is a grayscale image"):
        estimate_pool(folder, num_images=1)


def test_default_pool_is_jerlov_ambient_light():
    pool = default_pool()
    assert pool.shape == (30, 3)  # ten types x three depths
    np.testing.assert_allclose(pool.max(1), 0.7)  # L
    r, g, b = pool[2]  # Jerlov I at 10 m: blue water
    assert b > g > r
    r, g, b = pool[-1]  # Jerlov 9C at 10 m: yellow-green, blue absorbed
    assert r > b and g > b
    assert ambient_rgb("I", 10.0)[0] < ambient_rgb("I", 2.0)[0]  # red fades with depth
    np.testing.assert_allclose(ambient_rgb("III", 0.0), 1.0)  # white-balanced at the surface
    np.testing.assert_array_equal(background_light_pool(None), pool)


def test_real_euvp_pool_is_blue_green(shared_data):
    pool = estimate_pool(shared_data / "underwater_euvp", num_images=10, regions_per_image=8)
    assert pool.shape == (80, 3)
    median = np.median(pool, axis=0)
    assert median[1] > median[0] and median[2] > median[0]  # red is absorbed first in real water
