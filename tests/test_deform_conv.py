"""The fast deformable-convolution path must equal torchvision's operator (values and gradients)."""

import pytest
import torch
from torchvision.ops import deform_conv2d

from ruslam.models.deform_conv import DeformableConv, deform_conv2d_fast


@pytest.mark.parametrize(("stride", "padding", "dilation"), [(1, 1, 1), (2, 1, 1), (1, 2, 2), (1, 0, 1)])
def test_fast_path_equals_torchvision(stride, padding, dilation):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 5, 11, 13, generator=g, dtype=torch.float64)
    w = torch.randn(7, 5, 3, 3, generator=g, dtype=torch.float64)
    b = torch.randn(7, generator=g, dtype=torch.float64)
    ho = (11 + 2 * padding - dilation * 2 - 1) // stride + 1
    wo = (13 + 2 * padding - dilation * 2 - 1) // stride + 1
    # Large offsets so that many taps fall between pixels and some fall outside the image.
    off = 3.0 * torch.randn(2, 18, ho, wo, generator=g, dtype=torch.float64)
    ref = deform_conv2d(x, off, w, b, stride=(stride, stride), padding=(padding, padding),
                        dilation=(dilation, dilation))
    out = deform_conv2d_fast(x, off, w, b, stride=stride, padding=padding, dilation=dilation)
    assert out.shape == ref.shape
    torch.testing.assert_close(out, ref, rtol=1e-9, atol=1e-9)


def test_fast_path_gradients_equal_torchvision():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(1, 4, 9, 10, generator=g, dtype=torch.float64, requires_grad=True)
    w = torch.randn(6, 4, 3, 3, generator=g, dtype=torch.float64, requires_grad=True)
    # Offsets away from integers: bilinear interpolation is not differentiable exactly at grid points.
    off = (torch.randn(1, 18, 9, 10, generator=g, dtype=torch.float64) * 2).round() + 0.3
    off.requires_grad_(True)
    grads = []
    for fn in (deform_conv2d, deform_conv2d_fast):
        out = fn(x, off, w, None, padding=(1, 1)) if fn is deform_conv2d else fn(x, off, w, None, padding=1)
        grads.append(torch.autograd.grad(out.pow(2).sum(), (x, w, off)))
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-7)


def test_zero_initialized_offsets_make_a_plain_convolution():
    layer = DeformableConv(3, 4)
    x = torch.randn(1, 3, 8, 8)
    plain = torch.nn.functional.conv2d(x, layer.conv.weight, layer.conv.bias, padding=1)
    torch.testing.assert_close(layer(x), plain, rtol=1e-5, atol=1e-5)
    layer.fast = False
    torch.testing.assert_close(layer(x), plain, rtol=1e-5, atol=1e-5)


def test_module_fast_and_reference_agree_with_learned_offsets():
    torch.manual_seed(0)
    layer = DeformableConv(6, 8)
    torch.nn.init.normal_(layer.offset.weight, std=0.5)
    x = torch.randn(2, 6, 12, 16)
    fast = layer(x)
    layer.fast = False
    torch.testing.assert_close(fast, layer(x), rtol=1e-4, atol=1e-4)


def test_wrong_offset_channels_is_one_clear_error():
    with pytest.raises(ValueError, match="offset has 8 channels, expected 18"):
        deform_conv2d_fast(torch.zeros(1, 2, 5, 5), torch.zeros(1, 8, 5, 5), torch.zeros(3, 2, 3, 3), padding=1)
