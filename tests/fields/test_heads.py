"""DeformationHead: zero at initialisation, where the first gradients go, the position
scale, and gradcheck; plus the field → head road at step 0."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor, nn

from dyngs.errors import ConfigError
from dyngs.fields import DeformationHead, DeformationHeadConfig, Deltas, HexPlaneConfig
from dyngs.types import SceneBox

BOX = SceneBox((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))  # half-diagonal √3
ALL = DeformationHeadConfig(width=16, rotation=True, scale=True, opacity=True, color=True)
NAMES = ("means", "quats", "scales", "opacities", "colors")
WIDTHS = {"means": 3, "quats": 4, "scales": 3, "opacities": 1, "colors": 3}


def _present(deltas: Deltas) -> dict[str, Tensor]:
    return {name: v for name in NAMES if (v := getattr(deltas, name)) is not None}


def _branches(head: DeformationHead) -> dict[str, nn.Sequential]:
    return {name: b for name in NAMES if isinstance(b := getattr(head, name), nn.Sequential)}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [0, 1, 64])
def test_zero_at_initialisation(dtype: torch.dtype, n: int) -> None:
    g = torch.Generator().manual_seed(0)
    head = ALL.build(24, BOX, generator=g).to(dtype)
    features = torch.randn(n, 24, generator=g, dtype=dtype) * 10
    deltas = _present(head(features))
    assert set(deltas) == set(NAMES)
    for name, value in deltas.items():
        shape = (n,) if name == "opacities" else (n, WIDTHS[name])
        assert value.shape == shape and value.dtype == dtype, name
        assert bool((value == 0).all()), name


def test_disabled_attributes_are_none_and_have_no_parameters() -> None:
    head = DeformationHeadConfig(width=8).build(5, BOX)  # defaults: position and rotation
    deltas = head(torch.randn(3, 5))
    assert deltas.scales is None and deltas.opacities is None and deltas.colors is None
    assert deltas.quats is not None
    assert head.scales is None and head.opacities is None and head.colors is None
    minimal = DeformationHeadConfig(width=8, rotation=False, scale=False).build(5, BOX)
    assert set(_present(minimal(torch.randn(3, 5)))) == {"means"}
    # Trunk 5→8 and one position branch (8→8, 8→3).
    assert sum(p.numel() for p in minimal.parameters()) == (5 * 8 + 8) + (8 * 8 + 8) + (8 * 3 + 3)


def test_first_backward_reaches_the_last_layers_only_then_everything() -> None:
    g = torch.Generator().manual_seed(1)
    head = ALL.build(12, BOX, generator=g)
    features = torch.randn(256, 12, generator=g)
    targets = {n: torch.randn(v.shape, generator=g) for n, v in _present(head(features)).items()}

    def loss() -> Tensor:
        deltas = _present(head(features))
        return torch.stack([((deltas[n] - targets[n]) ** 2).sum() for n in deltas]).sum()

    optimizer = torch.optim.Adam(head.parameters(), lr=1e-2)
    loss().backward()
    for name, branch in _branches(head).items():
        last = branch[-1]
        assert isinstance(last, nn.Linear)
        assert last.weight.grad is not None and bool((last.weight.grad != 0).any()), name
        assert last.bias.grad is not None and bool((last.bias.grad != 0).all()), name
        # Behind a zero layer the gradient is exactly zero at step 0 ...
        middle = branch[1]
        assert isinstance(middle, nn.Linear)
        assert middle.weight.grad is not None and bool((middle.weight.grad == 0).all()), name
    assert head.trunk.weight.grad is not None and bool((head.trunk.weight.grad == 0).all())
    before = {n: v.detach().clone() for n, v in _present(head(features)).items()}
    optimizer.step()
    optimizer.zero_grad()
    with torch.no_grad():
        after = _present(head(features))
    for name in NAMES:
        assert float((after[name] - before[name]).abs().max()) > 1e-3, name
    # ... and from the second step on every parameter gets a gradient.
    loss().backward()
    for name, p in head.named_parameters():
        assert p.grad is not None and float(p.grad.abs().sum()) > 0, name


def test_position_scale_follows_the_box() -> None:
    small = SceneBox((0.0, 0.0, 0.0), (1.0, 2.0, 2.0))  # diagonal 3
    large = SceneBox((-50.0, 10.0, 10.0), (-40.0, 30.0, 30.0))  # diagonal 30
    head_small = ALL.build(6, small, generator=torch.Generator().manual_seed(2))
    head_large = ALL.build(6, large, generator=torch.Generator().manual_seed(2))
    assert head_small.position_scale == pytest.approx(1.5)
    assert head_large.position_scale == pytest.approx(15.0)
    for head in (head_small, head_large):  # the same non-zero last layers in both
        g = torch.Generator().manual_seed(3)
        with torch.no_grad():
            for branch in _branches(head).values():
                for p in branch[-1].parameters():
                    p.copy_(torch.randn(p.shape, generator=g))
    features = torch.randn(10, 6, generator=torch.Generator().manual_seed(4))
    a, b = head_small(features), head_large(features)
    assert torch.allclose(b.means, 10 * a.means, rtol=1e-6)
    assert float(a.means.detach().abs().max()) > 0
    for name in ("quats", "scales", "opacities", "colors"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_gradcheck() -> None:
    g = torch.Generator().manual_seed(5)
    head = ALL.build(4, BOX, generator=g).double()
    with torch.no_grad():  # non-zero last layers, or every derivative is trivially 0
        for branch in _branches(head).values():
            for p in branch[-1].parameters():
                p.copy_(torch.randn(p.shape, generator=g, dtype=torch.float64))
    features = torch.randn(3, 4, generator=g, dtype=torch.float64, requires_grad=True)
    trunk = head.trunk.weight.detach().clone().requires_grad_()

    def run(x: Tensor, w: Tensor) -> tuple[Tensor, ...]:
        deltas = torch.func.functional_call(head, {"trunk.weight": w}, (x,))
        return tuple(_present(deltas).values())

    assert torch.autograd.gradcheck(run, (features, trunk))


def test_rejects_wrong_feature_width() -> None:
    head = DeformationHeadConfig().build(7, BOX)
    with pytest.raises(ValueError, match=r"features must be \[N, 7\]"):
        head(torch.zeros(2, 8))
    with pytest.raises(ConfigError, match="width"):
        DeformationHeadConfig(width=0)


def test_field_and_head_start_static_then_learn() -> None:
    """The whole deformation road: exact zero deltas at step 0 whatever t; the field's
    planes get their first gradient at the second step, once the last layers moved."""
    g = torch.Generator().manual_seed(6)
    field = HexPlaneConfig(resolution=(6, 6, 6, 4), multires=(1, 2), features=4).build(
        BOX, generator=g
    )
    head = DeformationHeadConfig(width=16).build(field.out_dim, BOX, generator=g)
    xyz = torch.rand(128, 3, generator=g) * 2 - 1
    t = torch.rand(128, 1, generator=g)
    deltas = head(field(xyz, t))
    assert all(bool((v == 0).all()) for v in _present(deltas).values())
    params = list(field.parameters()) + list(head.parameters())
    optimizer = torch.optim.Adam(params, lr=1e-2)
    target = torch.randn(128, 3, generator=g)
    for step in range(2):
        optimizer.zero_grad()
        ((head(field(xyz, t)).means - target) ** 2).sum().backward()
        plane_grads = [float(p.grad.abs().sum()) for p in field.parameters() if p.grad is not None]
        if step == 0:
            assert plane_grads == [0.0] * len(plane_grads)
        else:
            assert len(plane_grads) == len(list(field.parameters())) and min(plane_grads) > 0
        optimizer.step()


def _grad(tensor: Tensor) -> Tensor:
    assert tensor.grad is not None
    return tensor.grad.clone()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_shared_relu_draws_what_a_relu_per_branch_draws(dtype: torch.dtype) -> None:
    """The head applies ReLU(trunk) once for all branches; the reference applies it at the
    head of each branch, as the head once did. Outputs and every parameter's and feature's
    gradient agree to the bit, and the state_dict keys are the reference's."""
    g = torch.Generator().manual_seed(3)
    head = ALL.build(12, BOX, generator=g).to(dtype)
    for branch in _branches(head).values():  # trained-looking: no zero last layer
        last = branch[3]
        assert isinstance(last, nn.Linear)
        nn.init.normal_(last.weight, std=0.3, generator=g)
        nn.init.normal_(last.bias, std=0.3, generator=g)
    features = torch.randn(300, 12, generator=g, dtype=dtype, requires_grad=True)

    def reference(x: Tensor) -> dict[str, Tensor]:
        hidden = head.trunk(x)
        out = {name: b[3](b[2](b[1](torch.relu(hidden)))) for name, b in _branches(head).items()}
        out["means"] = out["means"] * head.position_scale
        out["opacities"] = out["opacities"].squeeze(-1)
        return out

    weights = {n: torch.randn(v.shape, generator=g, dtype=dtype)
               for n, v in reference(features).items()}  # fmt: skip
    results = []
    for run in (lambda x: _present(head(x)), reference):
        head.zero_grad(set_to_none=True)
        features.grad = None
        out = run(features)
        torch.stack([(out[n] * weights[n]).sum() for n in NAMES]).sum().backward()
        grads = {name: _grad(p) for name, p in head.named_parameters()}
        results.append((out, grads, _grad(features)))
    (out, grads, feature_grad), (ref_out, ref_grads, ref_feature_grad) = results
    for name in NAMES:
        assert torch.equal(out[name], ref_out[name]), name
    for name in ref_grads:
        assert torch.equal(grads[name], ref_grads[name]), name
    assert torch.equal(feature_grad, ref_feature_grad)
    assert "means.1.weight" in head.state_dict() and "means.3.bias" in head.state_dict()
