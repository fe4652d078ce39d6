"""Eq. 4 (`degrade`) and the seeded per-image `PseudoUnderwater`."""

import pickle

import numpy as np
import pytest
import torch
from kornia.filters import motion_blur

from ruslam.data.synthesis import PseudoUnderwater, attenuate_eq1, correlate, degrade, motion_kernel
from ruslam.data.water import beta_rgb


def _batch(b=2, h=24, w=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(b, 3, h, w, generator=g)
    depth = 0.5 + 4 * torch.rand(b, h, w, generator=g)
    beta = torch.tensor(np.stack([beta_rgb("III"), beta_rgb("7C")][:b]), dtype=torch.float32)
    A = torch.tensor([[0.1, 0.6, 0.7], [0.3, 0.7, 0.4]][:b])
    return rgb, depth, beta, A


def _eq1_by_hand(rgb, depth, beta, A):
    """M = N t + A (1 - t) with N = A R (eq. 3), written out in numpy."""
    R, d, bt, a = (x.double().numpy() for x in (rgb, depth, beta, A))
    t = np.exp(-bt[:, :, None, None] * d[:, None])
    N = a[:, :, None, None] * R
    return N * t + a[:, :, None, None] * (1 - t)


def test_eq4_without_blur_noise_and_low_light_is_eq1():
    rgb, depth, beta, A = _batch()
    out = degrade(rgb, depth, beta, A, torch.ones(2), torch.zeros(2), 20.0, 0.0)
    np.testing.assert_allclose(out.numpy(), _eq1_by_hand(rgb, depth, beta, A), atol=1e-6)


def test_low_light_scales_the_whole_illumination():
    rgb, depth, beta, A = _batch()
    full = degrade(rgb, depth, beta, A, torch.ones(2), torch.zeros(2), 20.0, 0.0)
    dim = degrade(rgb, depth, beta, A, torch.tensor([0.5, 0.25]), torch.zeros(2), 20.0, 0.0)
    np.testing.assert_allclose(dim.numpy(), full.numpy() * np.array([0.5, 0.25])[:, None, None, None], atol=1e-6)


def test_deep_pixels_converge_to_background_light():
    rgb, depth, beta, A = _batch()
    out = degrade(rgb, torch.full_like(depth, 500.0), beta, A, torch.full((2,), 0.8), torch.zeros(2), 20.0, 10.0)
    np.testing.assert_allclose(out.numpy(), (0.8 * A)[:, :, None, None].expand_as(out).numpy(), atol=1e-5)


def test_correlate_equals_kornia_motion_blur():
    x = torch.rand(2, 3, 30, 40)
    for angle, length in ((20.0, 10.0), (-65.0, 7.0), (90.0, 4.0)):
        k = motion_kernel(angle, length)
        assert k.shape[-1] == 2 * int(length // 2) + 1 and abs(float(k.sum()) - 1) < 1e-6
        np.testing.assert_allclose(correlate(x, k).numpy(), motion_blur(x, k.shape[-1], angle, 0.0).numpy(),
                                   atol=1e-6)
    assert motion_kernel(20.0, 0.5) is None and motion_kernel(20.0, 1.0) is None


def test_per_image_blur_angles():
    rgb, depth, beta, A = _batch()
    both = degrade(rgb, depth, beta, A, torch.ones(2), torch.zeros(2), torch.tensor([20.0, 70.0]), 6.0)
    for i, angle in enumerate((20.0, 70.0)):
        one = degrade(rgb[i:i + 1], depth[i:i + 1], beta[i:i + 1], A[i:i + 1], torch.ones(1), torch.zeros(1),
                      angle, 6.0)
        np.testing.assert_allclose(both[i].numpy(), one[0].numpy(), atol=1e-6)


def test_blur_acts_on_the_direct_term_only():
    rgb, depth, beta, A = _batch()
    sharp = degrade(rgb, depth, beta, A, torch.ones(2), torch.zeros(2), 20.0, 0.0)
    blurred = degrade(rgb, depth, beta, A, torch.ones(2), torch.zeros(2), 20.0, 10.0)
    t = torch.exp(-beta[:, :, None, None] * depth[:, None])
    direct = A[:, :, None, None] * rgb * t
    expected = motion_blur(direct, 11, 20.0, 0.0) + A[:, :, None, None] * (1 - t)
    np.testing.assert_allclose(blurred.numpy(), expected.clamp(0, 1).numpy(), atol=1e-5)
    assert (blurred - sharp).abs().max() > 0.01
    black = torch.zeros_like(rgb)  # no direct light: the blur has nothing to act on
    np.testing.assert_allclose(degrade(black, depth, beta, A, torch.ones(2), torch.zeros(2), 20.0, 10.0).numpy(),
                               degrade(black, depth, beta, A, torch.ones(2), torch.zeros(2), 20.0, 0.0).numpy(),
                               atol=1e-6)


def test_invalid_depth_is_pure_background_light():
    rgb, depth, beta, A = _batch()
    depth[0, :4] = float("nan")
    depth[0, 4, :5] = 0.0
    depth[0, 5, :5] = -1.0
    depth[0, 6, :5] = float("inf")
    out = degrade(rgb, depth, beta, A, torch.ones(2), torch.zeros(2), 20.0, 0.0)
    assert torch.isfinite(out).all()
    for rows, cols in ((slice(0, 4), slice(None)), (slice(4, 7), slice(0, 5))):
        np.testing.assert_allclose(out[0, :, rows, cols].numpy(),
                                   A[0, :, None, None].expand(3, *out[0, 0, rows, cols].shape).numpy(), atol=1e-6)
    all_nan = degrade(rgb, torch.full_like(depth, float("nan")), torch.zeros(2, 3), A, torch.ones(2),
                      torch.zeros(2), 20.0, 10.0)  # also beta = 0: no 0 * inf
    np.testing.assert_allclose(all_nan.numpy(), A[:, :, None, None].expand_as(all_nan).numpy(), atol=1e-6)


def test_noise_has_the_requested_std():
    rgb = torch.full((1, 3, 200, 200), 0.5)
    depth = torch.ones(1, 200, 200)
    args = (torch.zeros(1, 3), torch.full((1, 3), 0.5), torch.ones(1))
    clean = degrade(rgb, depth, *args, torch.zeros(1), 20.0, 0.0)
    noisy = degrade(rgb, depth, *args, torch.tensor([0.03]), 20.0, 0.0, generator=torch.Generator().manual_seed(1))
    diff = (noisy - clean).flatten()
    assert abs(float(diff.std()) - 0.03) < 0.001 and abs(float(diff.mean())) < 0.001


def test_bad_shapes_are_one_sentence():
    rgb, depth, beta, A = _batch()
    with pytest.raises(ValueError, match=r"depth must be \[B,H,W\]"):
        degrade(rgb, depth[:, :-1], beta, A, torch.ones(2), torch.zeros(2))
    with pytest.raises(ValueError, match="beta must have shape"):
        degrade(rgb, depth, beta[:1], A, torch.ones(2), torch.zeros(2))


def test_attenuate_eq1_keeps_in_air_colours_at_zero_depth():
    rgb, depth, beta, A = _batch()
    np.testing.assert_allclose(attenuate_eq1(rgb, torch.full_like(depth, 1e-6), beta, A).numpy(), rgb.numpy(),
                               atol=1e-5)
    far = attenuate_eq1(rgb, torch.full_like(depth, 1e4), beta, A)
    np.testing.assert_allclose(far.numpy(), A[:, :, None, None].expand_as(far).numpy(), atol=1e-6)


def test_same_seed_and_index_give_the_same_image_in_any_batch():
    rgb, depth, _, _ = _batch(b=3)
    pu = PseudoUnderwater(seed=7)
    batch = pu(rgb, depth, [4, 9, 2])
    alone = PseudoUnderwater(seed=7)(rgb[1:2], depth[1:2], [9])
    assert torch.equal(batch[1], alone[0])
    other_mates = pu(torch.stack([rgb[0], rgb[1]]), torch.stack([depth[0], depth[1]]), [11, 9])
    assert torch.equal(other_mates[1], batch[1])
    assert not torch.equal(PseudoUnderwater(seed=8)(rgb[1:2], depth[1:2], [9])[0], batch[1])
    assert not torch.equal(pu(rgb[1:2], depth[1:2], [10])[0], batch[1])


def test_pickled_instance_reproduces_images_in_dataloader_workers():
    rgb, depth, _, _ = _batch(b=4)
    pu = PseudoUnderwater(seed=3)
    expected = pu(rgb, depth, [0, 1, 2, 3])
    assert torch.equal(pickle.loads(pickle.dumps(pu))(rgb, depth, [0, 1, 2, 3]), expected)

    class Items(torch.utils.data.Dataset):
        def __len__(self):
            return 4

        def __getitem__(self, i):
            return pu(rgb[i:i + 1], depth[i:i + 1], [i])[0]

    loader = torch.utils.data.DataLoader(Items(), batch_size=2, num_workers=2)
    assert torch.equal(torch.cat(list(loader)), expected)


def test_parameters_come_from_the_configured_ranges():
    pool = np.array([[0.1, 0.5, 0.6], [0.2, 0.6, 0.3]])
    pu = PseudoUnderwater(water_types=["II", "9C"], background_light=pool, noise_std=(0.01, 0.02),
                          low_light=(0.5, 0.6), seed=0)
    drawn = [pu.params(i) for i in range(60)]
    assert {d["water_type"] for d in drawn} == {"II", "9C"}
    assert all(any(np.array_equal(d["A"], a) for a in pool) for d in drawn)
    assert all(0.5 <= d["L"] <= 0.6 and 0.01 <= d["noise_std"] <= 0.02 for d in drawn)
    fixed = pu.for_water_type("5C")
    assert {fixed.params(i)["water_type"] for i in range(20)} == {"5C"}
    np.testing.assert_allclose(fixed.params(3)["beta"], beta_rgb("5C"))


def test_pseudo_underwater_bad_input():
    with pytest.raises(ValueError, match="Unknown Jerlov water type"):
        PseudoUnderwater(water_types=["I", "X"])
    with pytest.raises(ValueError, match=r"\[K,3\] array in \[0,1\]"):
        PseudoUnderwater(background_light=[[0.1, 2.0, 0.3]])
    rgb, depth, _, _ = _batch()
    with pytest.raises(ValueError, match="Got 1 indices for a batch of 2"):
        PseudoUnderwater()(rgb, depth, [0])


def test_streak_of_l_pixels_covers_the_nearest_odd_tap_count():
    from ruslam.data.synthesis import motion_kernel

    sizes = {length: motion_kernel(20.0, length).shape[-1] for length in (2, 3, 4, 5, 7, 10)}
    assert sizes == {2: 3, 3: 3, 4: 5, 5: 5, 7: 7, 10: 11}
