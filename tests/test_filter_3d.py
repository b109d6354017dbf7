"""Mip-Splatting's 3D smoothing filter: the widened Gaussian against its covariance, the
sampling rates it is sized by, its refresh schedule, and that a model keeps it (state,
topology changes, checkpoints, and those from before it existed). Exports:
tests/tools/test_export.py."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import torch

from dyngs.config import TrainConfig
from dyngs.engine import schedules
from dyngs.engine.smoothing import PRESENT, finest_sampling_rates, sampling_rates
from dyngs.geometry import normalize_quaternion, quaternion_to_rotation
from dyngs.model import DynamicGaussians, GaussianConfig, smooth_3d
from dyngs.types import Camera
from tests.engine.helpers import tiny_config, tiny_trainer

FILTERED = GaussianConfig(filter_3d=0.2)


def _covariance(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    rot = quaternion_to_rotation(normalize_quaternion(quats))
    return rot @ torch.diag_embed(scales.square()) @ rot.transpose(-1, -2)


def test_the_filter_adds_its_variance_and_keeps_the_mass() -> None:
    # Reference: Σ' = Σ + σ²I, and the unnormalised Gaussian's mass o·√det Σ (×(2π)^{3/2})
    # is unchanged, whatever the Gaussian's rotation.
    g = torch.Generator().manual_seed(0)
    n = 64
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(torch.randn(n, 3, generator=g, dtype=torch.float64) * 2)
    opacities = torch.rand(n, generator=g, dtype=torch.float64)
    std = torch.exp(torch.randn(n, generator=g, dtype=torch.float64))
    widened, faded = smooth_3d(scales, opacities, std)
    eye = torch.eye(3, dtype=torch.float64)
    expected = _covariance(quats, scales) + std.square()[:, None, None] * eye
    torch.testing.assert_close(_covariance(quats, widened), expected, rtol=1e-12, atol=1e-12)
    mass = opacities * torch.linalg.det(_covariance(quats, scales)).sqrt()
    torch.testing.assert_close(faded * torch.linalg.det(expected).sqrt(), mass, rtol=1e-10, atol=0)
    assert bool((faded <= opacities).all()) and bool((widened >= scales).all())


def test_no_filter_is_the_identity_bit_for_bit() -> None:
    scales = torch.tensor([[1e-30, 2.0, 3.0], [1e20, 1.0, 1e-3]])
    opacities = torch.tensor([0.3, 0.9])
    widened, faded = smooth_3d(scales, opacities, torch.zeros(2))
    assert torch.equal(widened, scales) and torch.equal(faded, opacities)


def test_extreme_scales_stay_finite_in_float32() -> None:
    # √(s² + σ²) in float32 would underflow s² for the speck (a zero-width blob beside
    # the filter is still the filter) and overflow it for the giant (scales → inf).
    scales = torch.tensor([[1e-30, 1e-30, 1e-30], [1e25, 1e25, 1e25], [1.0, 1.0, 1.0]])
    opacities = torch.tensor([0.5, 0.5, 0.5])
    std = torch.tensor([1e-3, 1e-3, 1.0])
    widened, faded = smooth_3d(scales, opacities, std)
    assert bool(torch.isfinite(widened).all()) and bool(torch.isfinite(faded).all())
    torch.testing.assert_close(widened[0], torch.full((3,), 1e-3))
    assert float(faded[0]) == 0.0  # (1e-27)³ of its opacity: below float32's range
    torch.testing.assert_close(widened[1], scales[1])
    assert float(faded[1]) == pytest.approx(0.5)
    torch.testing.assert_close(widened[2], torch.full((3,), math.sqrt(2.0)))
    assert float(faded[2]) == pytest.approx(0.5 / 2**1.5)


def test_non_finite_rows_pass_through_and_send_back_no_nan() -> None:
    scales = torch.tensor([[1.0, 2.0, 3.0], [math.inf, 1.0, 1.0], [math.nan, 1.0, 1.0]])
    scales.requires_grad_(True)
    opacities = torch.full((3,), 0.5, requires_grad=True)
    widened, faded = smooth_3d(scales, opacities, torch.full((3,), 0.1))
    torch.testing.assert_close(widened[1:], scales[1:], rtol=0, atol=0, equal_nan=True)
    (widened.nan_to_num(0, 0, 0).sum() + faded.sum()).backward()
    assert scales.grad is not None and opacities.grad is not None
    assert bool(torch.isfinite(scales.grad).all()) and bool(torch.isfinite(opacities.grad).all())


def test_gradients_match_finite_differences() -> None:
    g = torch.Generator().manual_seed(1)
    scales = torch.exp(torch.randn(5, 3, generator=g, dtype=torch.float64)).requires_grad_(True)
    opacities = torch.rand(5, generator=g, dtype=torch.float64).requires_grad_(True)
    std = torch.exp(torch.randn(5, generator=g, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(smooth_3d, (scales, opacities, std))


def _camera(fx: float, fy: float, eye_z: float) -> Camera:
    w2c = torch.eye(4)
    w2c[2, 3] = eye_z  # the world origin is eye_z in front of the camera
    return Camera(fx=fx, fy=fy, cx=16.0, cy=16.0, world_to_camera=w2c, width=32, height=32)


def test_sampling_rate_is_focal_over_depth_where_the_view_sees_a_present_gaussian() -> None:
    means = torch.tensor(
        [
            [0.0, 0.0, 0.0],  # depth 3
            [0.1, -0.2, 2.0],  # depth 5
            [0.0, 0.0, -5.0],  # behind the camera
            [0.0, 0.0, 0.0],  # not present at the view's time
            [2.0, 0.0, 0.0],  # projects to x = 16 + 50·2/3 ≈ 49 > 32·1.15: outside
            [1.0, 0.0, 0.0],  # x ≈ 32.7: beyond the edge, within the 15 % margin
        ]
    )
    present = torch.tensor([True, True, True, False, True, True])
    rates = sampling_rates(means, present, _camera(40.0, 50.0, 3.0))
    # the finer focal length counts: 50
    torch.testing.assert_close(rates, torch.tensor([50 / 3, 10.0, 0.0, 0.0, 0.0, 50 / 3]))


def test_set_filter_sizes_by_the_finest_rate_and_gives_the_unseen_the_widest(
    tmp_path: Path,
) -> None:
    model = tiny_trainer(tmp_path).model
    n = len(model.canonical)
    rates = torch.zeros(n)
    rates[: n // 2] = torch.linspace(10.0, 20.0, n // 2)
    model.set_filter(rates, 0.2)
    std = model.filter_std
    torch.testing.assert_close(std[: n // 2], math.sqrt(0.2) / rates[: n // 2])
    assert bool((std[n // 2 :] == math.sqrt(0.2) / 10.0).all())  # the coarsest rate's
    before = std.clone()
    model.set_filter(torch.zeros(n), 0.2)  # nothing seen: nothing to go by
    assert torch.equal(model.filter_std, before)
    with pytest.raises(ValueError, match="rates for"):
        model.set_filter(torch.ones(n + 1), 0.2)


def test_the_model_draws_through_its_filter_and_keeps_it(tmp_path: Path) -> None:
    model = tiny_trainer(tmp_path).model
    plain = model.at(0.5)
    std = torch.rand(len(model.canonical)) * 0.05
    model.filter_std.copy_(std)
    drawn = model.at(0.5)
    scales, opacities = smooth_3d(plain.scales, plain.opacities, std)
    assert torch.equal(drawn.scales, scales) and torch.equal(drawn.opacities, opacities)
    assert torch.equal(drawn.means, plain.means)
    # a topology change carries each source's filter to its row
    source = torch.tensor([3, 0, 3, 1])
    model.on_topology(source, torch.tensor([False, False, True, True]))
    assert torch.equal(model.filter_std, std[source])


def test_a_model_saved_before_the_filter_loads_without_one(tmp_path: Path) -> None:
    model = tiny_trainer(tmp_path).model
    model.filter_std.fill_(0.5)
    state = {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in
             model.state_dict().items()}  # fmt: skip
    twin = tiny_trainer(tmp_path / "twin").model
    twin.load_state_dict(state)
    assert torch.equal(twin.filter_std, model.filter_std)
    del state["filter_std"]
    twin.load_state_dict(state)
    assert not twin.filtered and len(twin.filter_std) == len(model.canonical)


@pytest.mark.parametrize(
    ("steps", "strength", "due"),
    [(1000, 0.2, [100, 200, 300, 400, 500, 600, 700, 800, 900]), (250, 0.2, [100]),
     (1000, 0.0, [])],
)  # fmt: skip
def test_the_filter_is_refreshed_every_refinement_interval_but_not_at_the_end(
    steps: int, strength: float, due: list[int]
) -> None:
    config = dataclasses.replace(
        TrainConfig(max_iters=steps), gaussians=GaussianConfig(filter_3d=strength)
    )
    assert [s for s in range(steps + 1) if schedules.is_filter_step(config, s)] == due


def _finest_by_hand(model: DynamicGaussians, poses: list[tuple[Camera, float]]) -> torch.Tensor:
    """The finest rate over the poses, the model drawn afresh for each one."""
    rates = torch.zeros(len(model.canonical))
    with torch.no_grad():
        for camera, t in poses:
            present = model.canonical.temporal_factor(t) > PRESENT
            rates = torch.maximum(rates, sampling_rates(model.raw_at(t)["means"], present, camera))
    return rates


def test_training_sets_the_filter_from_every_training_view_and_a_resume_keeps_it(
    tmp_path: Path,
) -> None:
    densify = dataclasses.replace(tiny_config().densify, refine_every=10)
    trainer = tiny_trainer(tmp_path, max_iters=25, densify=densify, gaussians=FILTERED)
    poses = trainer.data.train_poses()
    assert len({t for _, t in poses}) < len(poses)  # times with several views: grouped

    def assert_asked_by_every_view() -> None:
        rates = _finest_by_hand(trainer.model, poses)
        seen = rates > 0
        assert 0 < int(seen.sum()) <= len(rates)
        expected = math.sqrt(0.2) / torch.where(seen, rates, rates[seen].min())
        torch.testing.assert_close(trainer.model.filter_std, expected, rtol=1e-6, atol=0)

    assert_asked_by_every_view()  # the initial Gaussians' filter, before any step
    refreshed = []
    for step in range(25):
        before = trainer.model.filter_std.clone()
        trainer.train_step(step)
        if not torch.equal(trainer.model.filter_std, before):
            refreshed.append(step)
        if step == 9:  # refreshed after this step (10 steps done)
            assert_asked_by_every_view()
    assert refreshed == [9]  # after 10 steps; not after 20, within the last 10 of 25
    trainer.save()
    resumed = tiny_trainer(tmp_path / "resumed", max_iters=25, densify=densify, gaussians=FILTERED)
    resumed.load(trainer.checkpoint_path())
    assert torch.equal(resumed.model.filter_std, trainer.model.filter_std)
    assert torch.equal(resumed.model.at(0.5).scales, trainer.model.at(0.5).scales)


def test_no_filter_trains_without_one(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, max_iters=12, gaussians=GaussianConfig(filter_3d=0.0))
    for step in range(12):
        trainer.train_step(step)
    assert not trainer.model.filtered


def test_a_temporal_gaussian_counts_only_for_views_of_its_time_whatever_its_opacity(
    tmp_path: Path,
) -> None:
    trainer = tiny_trainer(tmp_path)
    model, poses = trainer.model, trainer.data.train_poses()
    c = model.canonical
    half = len(c) // 2
    with torch.no_grad():
        c.time_centers[:half] = 0.0  # alive around t = 0 only (presence e^-200 at t = 1)
        c.time_log_scales[:half] = math.log(0.05)
        c.opacity_logits[half:] = -12.0  # the others nearly transparent: still counted
    late = [(camera, t) for camera, t in poses if t == 1.0]
    early = [(camera, t) for camera, t in poses if t == 0.0]
    assert late and early
    rates_late = finest_sampling_rates(model, late)
    in_view = rates_late[half:] > 0
    assert bool((rates_late[:half] == 0).all()) and bool(in_view.any())
    assert bool((finest_sampling_rates(model, early)[:half] > 0).any())
