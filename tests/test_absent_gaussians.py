"""Gaussians absent at a time are not deformed there: a temporal Gaussian whose presence
at t is under the renderers' α floor draws nothing at t, so `DynamicGaussians.at(t,
absent_below=ABSENT_BELOW)` leaves it undeformed, and the field and head run on the
Gaussians present at t only. The image, what is visible and every gradient are those of
the model deformed whole (cpu-reference, the specification, draws both)."""

from __future__ import annotations

import math

import pytest
import torch

from dyngs.config import LossConfig
from dyngs.engine.objective import Objective
from dyngs.fields import DeformationHeadConfig, HexPlaneConfig
from dyngs.model import DynamicGaussians, GaussianConfig
from dyngs.renderers import RENDERERS
from dyngs.renderers.base import ABSENT_BELOW
from dyngs.types import Camera, SceneBox

BOX = SceneBox((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def _model(n: int = 300) -> DynamicGaussians:
    """n Gaussians in front of `_camera`: a third eternal, the rest temporal with
    lifetimes of 0.02-0.1 spread over the sequence, and a deformation far from zero."""
    gen = torch.Generator().manual_seed(0)
    model = DynamicGaussians.build(GaussianConfig(), HexPlaneConfig(resolution=(8, 8, 8, 6)),
                                   DeformationHeadConfig(), BOX, n, gen)  # fmt: skip
    points = (torch.rand(n, 3, generator=gen) - 0.5) * 1.2
    centres = torch.rand(n, generator=gen)
    widths = 0.02 + 0.08 * torch.rand(n, generator=gen)
    lifetimes = torch.stack((centres, widths), dim=1)
    lifetimes[: n // 3, 1] = math.inf
    model.canonical.initialize(points, torch.rand(n, 3, generator=gen), GaussianConfig(), lifetimes)
    with torch.no_grad():
        for p in model.parameters():
            if p.dtype.is_floating_point and p is not model.canonical.means:
                p.add_(0.05 * torch.randn(p.shape, generator=gen))
        model.canonical.opacity_logits.fill_(2.0)  # mostly opaque: presence decides
    model.deforming = True
    return model


def _camera() -> Camera:
    pose = torch.eye(4)
    pose[2, 3] = 3.0  # the box 2-4 units in front
    return Camera.from_fov(math.radians(50), 40, 32, pose)


def _draw(model: DynamicGaussians, t: float, absent_below: float) -> tuple:
    model.zero_grad(set_to_none=True)
    rows: list[int] = []
    field = model.field
    assert isinstance(field, torch.nn.Module)
    handle = field.register_forward_hook(lambda _m, args, _o: rows.append(len(args[0])))
    try:
        out = RENDERERS.get("cpu-reference")().build()(
            model.at(t, absent_below=absent_below), _camera(), torch.ones(3)
        )
        (out.rgb.square().sum() + out.alpha.sum()).backward()
    finally:
        handle.remove()
    grads = {name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None}
    return out, grads, rows


@pytest.mark.parametrize("t", [0.0, 0.31, 0.77, 1.0])
def test_absent_gaussians_are_not_deformed_and_draw_the_same(t: float) -> None:
    model = _model()
    presence = model.canonical.temporal_factor(t).detach()
    absent = int((presence < ABSENT_BELOW).sum())
    assert absent > 50  # the case is not vacuous
    whole, whole_grads, whole_rows = _draw(model, t, 0.0)
    culled, culled_grads, culled_rows = _draw(model, t, ABSENT_BELOW)
    assert whole_rows == [len(presence)] and culled_rows == [len(presence) - absent]
    assert int(whole.visible.sum()) > 50
    assert torch.equal(whole.visible, culled.visible)
    torch.testing.assert_close(culled.rgb, whole.rgb, rtol=0, atol=1e-6)
    torch.testing.assert_close(culled.alpha, whole.alpha, rtol=0, atol=1e-6)
    assert whole_grads.keys() == culled_grads.keys()
    for name, grad in whole_grads.items():
        scale = float(grad.abs().max()) + 1e-30
        assert float((culled_grads[name] - grad).abs().max()) <= 1e-5 * scale, name


def test_present_gaussians_move_as_before_and_absent_ones_stay_put() -> None:
    model = _model()
    t = 0.4
    with torch.no_grad():
        presence = model.canonical.temporal_factor(t)
        whole = model.at(t).means
        culled = model.at(t, absent_below=ABSENT_BELOW).means
    here = presence.double() >= ABSENT_BELOW
    torch.testing.assert_close(culled[here], whole[here], rtol=1e-6, atol=1e-7)
    assert torch.equal(culled[~here], model.canonical.means.detach()[~here])
    assert bool((whole[~here] != culled[~here]).any())  # they would have moved


def test_with_no_gaussian_present_nothing_is_deformed() -> None:
    model = _model(30)
    with torch.no_grad():
        model.canonical.time_log_scales[:] = math.log(0.01)  # every Gaussian temporal, short
        model.canonical.time_centers[:] = 0.9
    out, _, rows = _draw(model, 0.1, ABSENT_BELOW)
    assert rows == []  # the field never ran
    assert not bool(out.visible.any())
    assert torch.equal(out.rgb, torch.ones_like(out.rgb))


def test_steps_deform_every_gaussian_when_a_term_reads_them() -> None:
    generator = torch.Generator()
    assert Objective(LossConfig(), None, 0.1, generator).absent_below == ABSENT_BELOW  # type: ignore[arg-type]
    rigid = Objective(LossConfig(arap=0.1), None, 0.1, generator)  # type: ignore[arg-type]
    assert rigid.absent_below == 0.0
