"""UCIQE / UIQM components against values worked out by hand, and their monotone properties."""

import math

import cv2
import numpy as np
import pytest

from ruslam.eval.quality import alpha_trimmed_mean_var, eme, quality, uciqe, uicm, uiconm, uiqm_terms, uism


def _rgb(r, g, b):
    return np.stack(np.broadcast_arrays(r, g, b), axis=-1).astype(np.uint8)


def test_uicm_by_hand():
    # K = 10 pixels; R = 0,10,...,80,200; G = B = 0 -> RG = R, YB = R/2.
    r = np.array([0, 10, 20, 30, 40, 50, 60, 70, 80, 200]).reshape(2, 5)
    image = _rgb(r, 0, 0)
    # alpha 0.1: drop ceil(1) smallest and floor(1) largest -> mean of 10..80 = 45 (untrimmed would be 48).
    # variance about 45 over all ten: 2025+1225+625+225+25+25+225+625+1225+24025 = 30250 -> 3025.
    mu_rg, var_rg = 45.0, 3025.0
    mu_yb, var_yb = 22.5, 3025.0 / 4
    assert alpha_trimmed_mean_var(r) == pytest.approx((mu_rg, var_rg))
    expected = -0.0268 * math.sqrt(mu_rg**2 + mu_yb**2) + 0.1586 * math.sqrt(var_rg + var_yb)  # = 8.404262
    assert expected == pytest.approx(8.404262, abs=1e-6)
    assert uicm(image) == pytest.approx(expected, rel=1e-12)


def test_uicm_has_no_uint8_wraparound():
    # R < G: RG = -100 in every pixel; uint8 arithmetic would wrap it to 156.
    image = _rgb(np.full((4, 5), 50), 150, 100)  # YB = 100 - 100 = 0
    assert uicm(image) == pytest.approx(-0.0268 * 100.0)


def test_uism_by_hand_with_the_blue_weight_0114():
    # One 8x8 block; every row identical. Sobel x with replicated border on a ramp of step s:
    # 4*s at the two border columns, 8*s inside; Sobel y = 0.
    x = np.arange(8)
    r = np.tile(10 + 10 * x, (8, 1))  # edge*R: col0 40*10=400 ... col6 80*70=5600, col7 40*80=3200
    g = np.full((8, 8), 100)  # flat: Sobel 0 -> block minimum 0 -> contributes 0
    b = np.tile(50 + 10 * x, (8, 1))  # edge*B: col0 40*50=2000, col1 80*60=4800, col6 80*110=8800, col7 40*120=4800
    eme_r, eme_b = 2 * math.log(5600 / 400), 2 * math.log(8800 / 2000)
    assert uism(_rgb(r, g, b)) == pytest.approx(0.299 * eme_r + 0.114 * eme_b, rel=1e-12)


def test_eme_averages_over_all_blocks():
    two = np.concatenate([np.tile(1.0 + np.arange(8), (8, 1)), np.zeros((8, 8))], axis=1)  # 8x16: 2 blocks
    assert eme(two) == pytest.approx(2 * math.log(8 / 1) / 2)
    assert eme(np.concatenate([two, np.ones((3, 16))], axis=0)) == pytest.approx(eme(two))  # partial rows cropped


def test_uiconm_by_hand_plip():
    gamma = k = 1026.0

    def h(lo, hi):
        num = k * (hi - lo) / (k - lo)  # PLIP difference
        den = hi + lo - hi * lo / gamma  # PLIP sum
        r = num / den
        return -r * math.log(r)

    one = np.full((8, 8), 100)
    one[:, 4:] = 150
    h1 = h(100, 150)  # r = 55.3996 / 235.3801 = 0.23536 -> h = 0.34048
    assert h1 == pytest.approx(0.34048, abs=1e-5)
    assert uiconm(_rgb(one, one, one)) == pytest.approx(h1, rel=1e-9)
    two = np.concatenate([one, np.where(one == 150, 200, 100)], axis=1)
    h2 = h(100, 200)
    expected = gamma * (1 - math.sqrt((1 - h1 / gamma) * (1 - h2 / gamma)))  # (1/2) (x) (h1 (+) h2)
    assert uiconm(_rgb(two, two, two)) == pytest.approx(expected, rel=1e-9)


def test_uciqe_by_hand():
    bw = np.zeros((10, 10, 3), np.uint8)
    bw[:5] = 255  # L = 0 and 100, chroma 0: only the luminance contrast term, p99 - p1 = 1
    assert uciqe(bw) == pytest.approx(0.2745, abs=1e-3)
    # Pure sRGB red: linear (1,0,0) -> XYZ = (0.4124, 0.2126, 0.0193); D65 white (0.9505, 1, 1.089).
    X, Y, Z = 0.4124 / 0.9505, 0.2126, 0.0193 / 1.089
    L = 116 * Y ** (1 / 3) - 16  # 53.24
    a = 500 * (X ** (1 / 3) - Y ** (1 / 3))  # 80.1
    b = 200 * (Y ** (1 / 3) - Z ** (1 / 3))  # 67.2
    sat = math.hypot(a, b) / L  # uniform image: no chroma spread, no contrast, only saturation
    red = np.zeros((10, 10, 3), np.uint8)
    red[..., 0] = 255
    assert uciqe(red) == pytest.approx(0.2576 * sat, rel=2e-3)


def _texture(seed=0, size=(96, 128)):
    rng = np.random.default_rng(seed)
    base = cv2.resize(rng.random((12, 16, 3)).astype(np.float32), size[::-1], interpolation=cv2.INTER_CUBIC)
    return np.clip(0.2 + 0.6 * base + 0.05 * rng.random((*size, 3)), 0, 1)


def _u8(x):
    return np.clip(np.round(x * 255), 0, 255).astype(np.uint8)


def test_uicm_falls_when_chroma_is_removed():
    image = _texture()
    grey = np.repeat(image.mean(-1, keepdims=True), 3, -1)
    half = grey + 0.5 * (image - grey)
    assert uicm(_u8(image)) > uicm(_u8(half)) > uicm(_u8(grey))


def test_uism_falls_with_blur():
    rng = np.random.default_rng(1)
    tiles = cv2.resize(rng.random((12, 16, 3)), (128, 96), interpolation=cv2.INTER_NEAREST)  # sharp edges
    image = _u8(0.1 + 0.8 * tiles + 0.03 * rng.random((96, 128, 3)))
    mild, strong = (cv2.GaussianBlur(image, (0, 0), s) for s in (1.0, 3.0))
    assert uism(image) > uism(mild) > uism(strong)


def test_uiconm_falls_when_contrast_is_compressed():
    image = _texture(2)
    compressed = 0.5 + 0.4 * (image - 0.5)
    assert uiconm(_u8(image)) > uiconm(_u8(compressed)) > 0


def test_uiqm_combines_its_terms_and_quality_has_every_figure():
    image = _u8(_texture(3))
    t = uiqm_terms(image)
    assert t["uiqm"] == pytest.approx(0.0282 * t["uicm"] + 0.2953 * t["uism"] + 3.5753 * t["uiconm"])
    q = quality(image)
    assert set(q) == {"uciqe", "uiqm", "uicm", "uism", "uiconm"}
    assert quality(image.astype(np.float32) / 255)["uiqm"] == pytest.approx(q["uiqm"], rel=1e-5)


def test_bad_images_are_one_sentence():
    with pytest.raises(ValueError, match=r"RGB image \[H,W,3\]"):
        quality(np.zeros((8, 8)))
    with pytest.raises(ValueError, match="uint8 or float"):
        quality(np.zeros((8, 8, 3), np.int32))
    with pytest.raises(ValueError, match="smaller than one 8x8 block"):
        uism(np.zeros((4, 30, 3), np.uint8))
