"""The transposed convolution by phases against torch's own (the reference)."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from genre_backend.nets.phase_conv import PhaseConvTranspose3d, _ByPhases, phase_kernel, pixel_shuffle_3d
from genre_backend.nets.refiner import VoxelRefiner

LAYOUTS = [torch.contiguous_format, torch.channels_last_3d]


def _pair(cin: int, cout: int, bias: bool, seed: int = 0) -> tuple[PhaseConvTranspose3d, nn.ConvTranspose3d]:
    torch.manual_seed(seed)
    phase = PhaseConvTranspose3d(cin, cout, bias=bias)
    with torch.no_grad():  # weights of the size a trained layer has, and a bias that is not zero
        phase.weight.normal_(0, 0.3)
        if bias:
            phase.bias.normal_(0, 1)
    ref = nn.ConvTranspose3d(cin, cout, 4, 2, 1, bias=bias)
    ref.load_state_dict(phase.state_dict())
    return phase, ref


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize(("cin", "cout", "bias", "shape"), [
    (8, 1, True, (2, 8, 6, 6, 6)),
    (3, 2, False, (1, 3, 3, 5, 4)),  # not cubic, odd sizes
    (2, 5, True, (3, 2, 1, 2, 7)),  # a side of one voxel
])
def test_forward_and_gradients_match_torchs_transposed_convolution(layout, cin, cout, bias, shape):
    phase, ref = _pair(cin, cout, bias)
    phase.to(memory_format=layout)
    ref.to(memory_format=layout)
    torch.manual_seed(1)
    x = torch.randn(shape).contiguous(memory_format=layout).requires_grad_()
    out, expected = phase(x), ref(x)
    assert out.shape == expected.shape == (shape[0], cout, 2 * shape[2], 2 * shape[3], 2 * shape[4])
    torch.testing.assert_close(out, expected, atol=2e-6, rtol=1e-5)
    assert out.is_contiguous(memory_format=layout)
    grad = torch.randn_like(expected)
    params = [x, phase.weight] + ([phase.bias] if bias else [])
    ref_params = [x, ref.weight] + ([ref.bias] if bias else [])
    for got, want in zip(torch.autograd.grad(out, params, grad), torch.autograd.grad(expected, ref_params, grad)):
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)


def test_the_forward_by_phases_is_consistent_with_its_backward_in_double_precision():
    torch.manual_seed(2)
    weight = torch.randn(2, 3, 4, 4, 4, dtype=torch.float64, requires_grad=True)
    bias = torch.randn(3, dtype=torch.float64, requires_grad=True)
    x = torch.randn(1, 2, 3, 2, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(_ByPhases.apply, (x, weight, bias))
    torch.testing.assert_close(_ByPhases.apply(x, weight, bias), F.conv_transpose3d(x, weight, bias, stride=2, padding=1))


def test_every_tap_of_the_transposed_kernel_lands_once_in_the_phase_kernel():
    """Each of the 4 taps per axis is read by exactly one (phase, tap) pair: k = r + 3 − 2t."""
    weight = torch.arange(1, 2 * 3 * 64 + 1, dtype=torch.float32).reshape(2, 3, 4, 4, 4)
    kernel = phase_kernel(weight)
    assert kernel.shape == (3 * 8, 2, 3, 3, 3)
    values = kernel[kernel != 0]
    assert values.numel() == weight.numel()
    torch.testing.assert_close(values.sort().values, weight.flatten().sort().values)
    # phase (rz, ry, rx) = (0, 1, 1) of output channel 2 at taps (t) = (0, 1, 2) reads k = (3, 2, 0)
    assert kernel[2 * 8 + 0 * 4 + 1 * 2 + 1, 1, 0, 1, 2] == weight[1, 2, 3, 2, 0]
    # and phase 0 never reads its last tap (k = −1)
    assert (kernel[0::8, :, 2] == 0).all()


def test_pixel_shuffle_puts_each_phase_channel_at_its_offset():
    x = torch.arange(2 * 16 * 2 * 1 * 3, dtype=torch.float32).reshape(2, 16, 2, 1, 3)
    out = pixel_shuffle_3d(x)
    assert out.shape == (2, 2, 4, 2, 6)
    for c in range(2):
        for rz in range(2):
            for ry in range(2):
                for rx in range(2):
                    torch.testing.assert_close(out[:, c, rz::2, ry::2, rx::2], x[:, c * 8 + rz * 4 + ry * 2 + rx])


def test_under_autocast_and_in_half_precision_it_is_torchs_layer():
    phase, ref = _pair(4, 1, True)
    x = torch.randn(1, 4, 3, 3, 3)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert torch.equal(phase(x), ref(x))
    assert torch.equal(phase.bfloat16()(x.bfloat16()), ref.bfloat16()(x.bfloat16()))


def test_it_keeps_the_parameters_of_torchs_layer():
    phase, ref = _pair(8, 1, True)
    assert {k: v.shape for k, v in phase.state_dict().items()} == {k: v.shape for k, v in ref.state_dict().items()}
    assert isinstance(phase, nn.ConvTranspose3d)
    x = torch.randn(1, 8, 2, 2, 2)
    assert torch.equal(phase(x, output_size=[5, 5, 5]), ref(x, output_size=[5, 5, 5]))  # torch's own, output padding 1


def test_the_refiner_by_phases_matches_it_with_torchs_last_layer():
    torch.manual_seed(3)
    refiner = VoxelRefiner(16, 4, 16).eval()
    with torch.no_grad():
        refiner.out.weight.normal_(0, 0.3)
    plain = VoxelRefiner(16, 4, 16).eval()
    plain.out = nn.ConvTranspose3d(4, 1, 4, 2, 1)
    plain.load_state_dict(refiner.state_dict())
    x = (torch.rand(2, 2, 16, 16, 16) > 0.8).float()
    with torch.no_grad():
        torch.testing.assert_close(refiner(x), plain(x), atol=1e-5, rtol=1e-5)
