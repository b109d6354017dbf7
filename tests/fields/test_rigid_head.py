"""The rigid deformation head (`--head.rigid`): its turn quaternion, and the model folding
the turn into Δμ and Δq as a rigid motion about the scene box's centre, checked against
Rodrigues' formula in float64."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from torch import Tensor, nn

from dyngs.errors import ConfigError
from dyngs.fields import DeformationHead, DeformationHeadConfig, HexPlaneConfig
from dyngs.fields.heads import Deltas, turn_quaternion
from dyngs.geometry import normalize_quaternion, quaternion_to_rotation
from dyngs.model import DynamicGaussians, GaussianConfig, resolve_turn
from dyngs.types import SceneBox
from tests.engine.helpers import gradients_reaching, output_layer, tiny_trainer

BOX = SceneBox((-1.0, 0.0, 2.0), (3.0, 2.0, 4.0))  # centre (1, 1, 3), off the origin


def _rodrigues(axis: Tensor, angle: float) -> Tensor:
    """The rotation by `angle` about the unit `axis` (float64), written out independently
    of the quaternion helpers."""
    k = torch.tensor(
        [[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]],
        dtype=torch.float64,
    )
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def test_turn_quaternion_is_the_identity_at_zero_and_turns_by_two_atan_half() -> None:
    zero = turn_quaternion(torch.zeros(2, 3, dtype=torch.float64))
    assert torch.equal(zero, torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64))
    axis = torch.tensor([2.0, -1.0, 2.0], dtype=torch.float64) / 3
    for length in (1e-6, 0.3, 2.0, 40.0):
        q = turn_quaternion((axis * length)[None])
        angle = 2 * math.atan(length / 2)
        assert torch.allclose(q.norm(dim=-1), torch.ones(1, dtype=torch.float64))
        assert torch.allclose(quaternion_to_rotation(q)[0], _rodrigues(axis, angle), atol=1e-12)


def test_turn_quaternion_has_finite_gradients_at_zero() -> None:
    v = torch.zeros(3, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(turn_quaternion, (v,))
    turn_quaternion(v).sum().backward()
    assert v.grad is not None and bool(torch.isfinite(v.grad).all())


def test_rigid_needs_the_rotation_branch() -> None:
    with pytest.raises(ConfigError, match=r"--head\.rigid .* needs --head\.rotation"):
        DeformationHeadConfig(rigid=True, rotation=False)


def _model(count: int, dtype: torch.dtype = torch.float64) -> DynamicGaussians:
    g = torch.Generator().manual_seed(0)
    field = HexPlaneConfig(resolution=(4, 4, 4, 3), multires=(1,), features=4)
    head = DeformationHeadConfig(width=8, rigid=True)
    model = DynamicGaussians.build(GaussianConfig(sh_degree=0), field, head, BOX, count, g)
    model = model.to(dtype)
    with torch.no_grad():
        c = model.canonical
        c.means.copy_(
            torch.rand(count, 3, generator=g, dtype=dtype) * 4 + c.means.new_tensor(BOX.lower)
        )
        c.quats.copy_(torch.randn(count, 4, generator=g, dtype=dtype) * 2)
    return model


def test_rigid_head_draws_the_canonical_scene_at_step_zero() -> None:
    model = _model(50)
    raw = model.raw_at(0.7)
    for name in ("means", "quats"):
        assert torch.equal(raw[name], getattr(model.canonical, name)), name


def test_constant_outputs_move_every_gaussian_by_one_rigid_motion() -> None:
    """Last layers all zero but their biases: every Gaussian gets the same turn and Δμ, so
    the model must draw the canonical scene turned about the box's centre and shifted,
    orientations turned with it."""
    model = _model(40)
    head = model.head
    assert isinstance(head, DeformationHead)
    turn, move = output_layer(head, "quats"), output_layer(head, "means")
    assert turn is not None and move is not None
    axis = torch.tensor([1.0, 2.0, 2.0], dtype=torch.float64) / 3
    length, shift = 0.8, torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    with torch.no_grad():
        turn.bias.copy_(axis * length)
        move.bias.copy_(shift / head.position_scale)
    raw = model.raw_at(0.4)
    rot = _rodrigues(axis, 2 * math.atan(length / 2))
    centre = torch.tensor(BOX.center, dtype=torch.float64)
    c = model.canonical
    expected = centre + (c.means - centre) @ rot.T + shift
    assert torch.allclose(raw["means"], expected, atol=1e-12)
    drawn = quaternion_to_rotation(normalize_quaternion(raw["quats"]))
    canonical = quaternion_to_rotation(normalize_quaternion(c.quats))
    assert torch.allclose(drawn, rot @ canonical, atol=1e-12)

    # A rigid motion keeps every distance.
    def distances(x: Tensor) -> Tensor:
        return (x[:, None] - x[None]).norm(dim=-1)

    assert torch.allclose(distances(raw["means"]), distances(c.means), atol=1e-12)


def test_resolve_turn_gradcheck() -> None:
    g = torch.Generator().manual_seed(3)
    args = [torch.randn(5, k, generator=g, dtype=torch.float64, requires_grad=True)
            for k in (3, 3, 3, 4)]  # fmt: skip

    def run(v: Tensor, dmu: Tensor, xyz: Tensor, quats: Tensor) -> tuple[Tensor, Tensor]:
        d = Deltas(means=dmu, quats=None, scales=None, opacities=None, colors=None,
                   turn=turn_quaternion(v))  # fmt: skip
        out = resolve_turn(d, xyz, quats, BOX)
        assert out.turn is None and out.quats is not None
        return out.means, out.quats

    assert torch.autograd.gradcheck(run, tuple(args))


def test_a_non_finite_quaternion_does_not_reach_the_head() -> None:
    model = _model(30, torch.float32)
    head = model.head
    assert isinstance(head, DeformationHead)
    with torch.no_grad():
        for branch in ("quats", "means"):
            last = output_layer(head, branch)
            assert last is not None
            nn.init.normal_(last.weight, std=0.1)
        model.canonical.quats[7] = float("nan")
    raw = model.raw_at(0.5)
    finite = torch.ones(30, dtype=torch.bool)
    finite[7] = False
    (raw["means"][finite].sum() + raw["quats"][finite].sum()).backward()
    for name, p in head.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name


def test_a_rigid_run_trains_every_parameter_and_reloads_to_the_same_drawing(
    tmp_path: Path,
) -> None:
    trainer = tiny_trainer(tmp_path, warmup_iters=0, head=DeformationHeadConfig(rigid=True))
    named, reached = gradients_reaching(trainer.model)
    for step in range(3):  # the head's inner layers get a gradient from the second step
        trainer.train_step(step)
    assert {n for n in named if n.startswith(("head.", "field."))} <= reached
    model = trainer.model
    again = DynamicGaussians.load(
        trainer.config.gaussians, trainer.config.field, trainer.config.head, model.state_dict()
    )
    for t in (0.0, 0.45, 1.0):
        a, b = model.at(t), again.at(t)
        for name in ("means", "quats", "scales", "opacities"):
            assert torch.equal(getattr(a, name), getattr(b, name)), (t, name)
    with torch.no_grad():
        assert float((model.raw_at(0.45)["means"] - model.canonical.means).abs().max()) > 0
