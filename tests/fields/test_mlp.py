"""MLPField: the encoding by hand, shapes, time dependence and gradients."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from dyngs.errors import ConfigError
from dyngs.fields import MLPField, MLPFieldConfig
from dyngs.fields.mlp import positional_encoding
from dyngs.types import SceneBox

BOX = SceneBox((-3.0, 0.0, 1.0), (1.0, 2.0, 9.0))


def _inputs(n: int, seed: int, dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    g = torch.Generator().manual_seed(seed)
    lower, size = torch.tensor(BOX.lower, dtype=dtype), torch.tensor(BOX.size, dtype=dtype)
    xyz = lower + torch.rand(n, 3, generator=g, dtype=dtype) * size
    return xyz, torch.rand(n, 1, generator=g, dtype=dtype)


def test_positional_encoding_by_hand() -> None:
    x = torch.tensor([[0.25, -0.5]], dtype=torch.float64)
    got = positional_encoding(x, 2)
    s, c = math.sin, math.cos
    pi = math.pi
    expected = [
        0.25, -0.5,  # the raw input
        s(pi / 4), s(pi / 2), s(-pi / 2), s(-pi),  # sin, coordinate-major
        c(pi / 4), c(pi / 2), c(-pi / 2), c(-pi),  # cos
    ]  # fmt: skip
    assert torch.allclose(got, torch.tensor([expected], dtype=torch.float64), atol=1e-15)
    assert torch.equal(positional_encoding(x, 0), x)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [0, 1, 50])
def test_shapes_and_dtypes(dtype: torch.dtype, n: int) -> None:
    field = MLPFieldConfig(width=32, depth=4).build(BOX).to(dtype)
    assert field.out_dim == 32
    xyz, t = _inputs(n, 0, dtype)
    out = field(xyz.requires_grad_(), t)
    assert out.shape == (n, 32) and out.dtype == dtype
    assert bool(torch.isfinite(out).all()) and bool((out >= 0).all())  # after a ReLU
    out.sum().backward()
    assert xyz.grad is not None and xyz.grad.shape == (n, 3)
    assert field.planes().spatial == [] and field.planes().temporal == []


def test_encoding_uses_the_box_and_time_mapping() -> None:
    field = MLPFieldConfig(position_frequencies=3, time_frequencies=2).build(BOX).double()
    corners = torch.tensor([BOX.lower, BOX.upper], dtype=torch.float64)
    t = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    encoded = field.encode(corners, t)
    assert encoded.shape == (2, field.in_dim) and field.in_dim == 3 * 7 + 5
    assert torch.equal(encoded[:, :3], torch.tensor([[-1.0] * 3, [1.0] * 3], dtype=torch.float64))
    time_raw = 3 * 7  # the time encoding starts with the raw 2t - 1
    assert encoded[:, time_raw].tolist() == [-1.0, 1.0]


def test_layers_and_skip() -> None:
    field = MLPFieldConfig(depth=6, width=16, position_frequencies=4, time_frequencies=2).build(BOX)
    in_dim = 3 * 9 + 5
    assert field.in_dim == in_dim
    fan_in = [layer.in_features for layer in field.layers]
    assert fan_in == [in_dim, 16, 16, 16 + in_dim, 16, 16]
    single = MLPFieldConfig(depth=1, width=8).build(BOX)
    xyz, t = _inputs(4, 1)
    assert single(xyz, t).shape == (4, 8)


@torch.no_grad()
def test_depends_on_time_and_is_seeded() -> None:
    config = MLPFieldConfig(width=64, depth=4)
    field = config.build(BOX, generator=torch.Generator().manual_seed(3))
    xyz, _ = _inputs(100, 2)
    a = field(xyz, torch.full((100, 1), 0.2))
    b = field(xyz, torch.full((100, 1), 0.7))
    assert float((a - b).abs().max()) > 1e-3
    again = config.build(BOX, generator=torch.Generator().manual_seed(3))
    assert torch.equal(again(xyz, torch.full((100, 1), 0.2)), a)


def test_gradient_reaches_every_parameter_and_the_inputs() -> None:
    field = MLPFieldConfig(width=32, depth=4).build(BOX, generator=torch.Generator().manual_seed(4))
    xyz, t = _inputs(200, 3)
    xyz.requires_grad_()
    t.requires_grad_()
    field(xyz, t).square().sum().backward()
    for name, p in field.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name
        assert float(p.grad.abs().sum()) > 0, name
    assert xyz.grad is not None and bool((xyz.grad.abs().sum(0) > 0).all())
    assert t.grad is not None and float(t.grad.abs().sum()) > 0


def test_outside_the_box_is_finite() -> None:
    field = MLPFieldConfig(width=16, depth=3).build(BOX)
    xyz = torch.tensor([[1e4, -1e4, 3e3]])
    out = field(xyz, torch.tensor([[5.0]]))
    assert bool(torch.isfinite(out).all())


def test_gradcheck() -> None:
    config = MLPFieldConfig(position_frequencies=3, time_frequencies=2, depth=3, width=8)
    field = config.build(BOX, generator=torch.Generator().manual_seed(5)).double()
    xyz, t = _inputs(3, 6, torch.float64)
    assert torch.autograd.gradcheck(field, (xyz.requires_grad_(), t.requires_grad_()))


@pytest.mark.parametrize(
    "kwargs",
    [{"depth": 0}, {"width": 0}, {"position_frequencies": -1}, {"time_frequencies": -2}],
)
def test_config_rejects_bad_values(kwargs: dict[str, int]) -> None:
    with pytest.raises(ConfigError, match="mlp field"):
        MLPFieldConfig(**kwargs)


def test_is_a_field() -> None:
    field: MLPField = MLPFieldConfig().build(BOX)
    xyz, t = _inputs(20, 7)
    assert field(xyz, t).shape == (20, field.out_dim) == (20, 128)
