"""Static/dynamic separation: evidence from pixels, measured motion, and what follows."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import torch

from dyngs.datamanagers.datamanager import DataConfig, load_scene
from dyngs.datamanagers.fixed_cameras import fixed_camera_groups
from dyngs.datamanagers.procedural import ProceduralSceneConfig, demo_path, is_on_dynamic_object
from dyngs.engine import schedules
from dyngs.engine.densify import DensifyConfig, apply_topology, plan_refinement
from dyngs.engine.lifecycle import crop_field
from dyngs.engine.motion import (
    FixedCameraMotion,
    MotionConfig,
    measure_motion,
    model_bytes,
    revisit,
    sample_times,
)
from dyngs.engine.trainer import Trainer
from dyngs.engine.writer import NullWriter
from dyngs.fields import HexPlaneField
from dyngs.fields.heads import Deltas
from dyngs.model import CanonicalGaussians, DynamicGaussians, GaussianConfig
from tests.engine.helpers import TINY_SCENE, field_calls, tiny_config, tiny_trainer

# A rig of six cameras that never move, watching the ball and the cube move.
RIG = ProceduralSceneConfig(resolution=64, num_times=12, fixed_cameras=6, num_test=3, num_val=0)


def _on_moving_object(points: torch.Tensor, config: ProceduralSceneConfig) -> torch.Tensor:
    return torch.from_numpy(is_on_dynamic_object(points.double().numpy(), 0.0, config))


def test_fixed_cameras_see_which_points_move() -> None:
    scene = load_scene(str(demo_path(RIG)), DataConfig(), seed=0)
    assert len(fixed_camera_groups(scene.train)) == RIG.fixed_cameras
    moving = _on_moving_object(scene.points, RIG)
    assert 100 < int(moving.sum()) < len(moving) // 2  # both kinds are well represented

    fixed = FixedCameraMotion.of(scene.train)
    assert fixed is not None
    evidence = fixed.evidence(scene.points, MotionConfig())

    assert float(evidence[moving].float().mean()) >= 0.98  # the ball and the cube
    assert float(evidence[~moving].float().mean()) <= 0.05  # the pedestal and the pillar


def test_fixed_cameras_on_a_still_scene_see_nothing_move() -> None:
    still = dataclasses.replace(RIG, motion=False)
    scene = load_scene(str(demo_path(still)), DataConfig(), seed=0)
    fixed = FixedCameraMotion.of(scene.train)
    assert fixed is not None and not bool(fixed.evidence(scene.points, MotionConfig()).any())


def test_moving_cameras_give_no_pixel_evidence() -> None:
    scene = load_scene(str(demo_path(TINY_SCENE)), DataConfig(), seed=0)
    assert fixed_camera_groups(scene.train) == []
    assert FixedCameraMotion.of(scene.train) is None


def test_sample_times_spread_over_the_distinct_times() -> None:
    times = torch.tensor([0.0, 0.0, 0.25, 0.5, 0.5, 0.75, 1.0])
    assert sample_times(times, 16) == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert sample_times(times, 3) == [0.0, 0.5, 1.0]


class _ScriptedMotion(DynamicGaussians):
    """Gaussian i moves by velocity[i] · t plus a constant offset, whatever the field says."""

    def __init__(self, velocity: torch.Tensor, offset: torch.Tensor) -> None:
        n = len(velocity)
        canonical = CanonicalGaussians.from_points(
            torch.randn(n, 3, generator=torch.Generator().manual_seed(0)),
            None,
            GaussianConfig(sh_degree=0),
            torch.Generator().manual_seed(0),
        )
        with torch.no_grad():
            canonical.log_scales.fill_(-6.0)  # tiny: travel is the centre's motion
        super().__init__(canonical, torch.nn.Identity(), torch.nn.Identity(), None)  # type: ignore[arg-type]
        self.velocity, self.offset = velocity, offset

    def deltas(self, t, index=None):  # type: ignore[no-untyped-def,override]
        rows = torch.arange(len(self.velocity)) if index is None else index
        means = self.velocity[rows] * t + self.offset[rows]
        return Deltas(means=means, quats=None, scales=None, opacities=None, colors=None), index


def test_measured_motion_decides_and_baking_keeps_the_mean_pose() -> None:
    velocity = torch.zeros(4, 3)
    velocity[0, 0] = 1.0  # moves one unit over the sequence
    velocity[1, 1] = 0.004  # moves a fifth of a pixel (pixel size below: 0.02)
    offset = torch.full((4, 3), 0.3)  # a constant offset is no motion, just a shifted pose
    model = _ScriptedMotion(velocity, offset)
    times = [0.0, 0.5, 1.0]

    motion = measure_motion(model, times)
    assert torch.allclose(motion.travel, torch.tensor([0.5, 0.002, 0.0, 0.0]), atol=1e-6)

    model.dynamic[3] = False  # static already, but its gradient asks for motion
    before = model.canonical.means.detach().clone()
    wants_motion = torch.tensor([False, False, False, True])
    config = MotionConfig(static_pixels=0.5)
    static_now, dynamic_now = revisit(model, config, times, 0.02, wants_motion)

    assert (static_now, dynamic_now) == (2, 1)
    assert model.dynamic.tolist() == [True, False, False, True]
    # The demoted ones now sit at their mean pose for good.
    mean_offset = offset + velocity * 0.5
    after = model.canonical.means.detach()
    assert torch.allclose(after[1:3], before[1:3] + mean_offset[1:3])
    assert torch.equal(after[0], before[0])
    # The promoted one gives the scripted mean deformation back: its mean pose is unchanged.
    assert torch.allclose(after[3], before[3] - mean_offset[3])


def test_a_static_gaussian_where_the_field_moves_becomes_dynamic() -> None:
    velocity = torch.zeros(2, 3)
    velocity[1, 2] = 1.0
    model = _ScriptedMotion(velocity, torch.zeros(2, 3))
    model.dynamic[:] = False
    before = model.canonical.means.detach().clone()
    times = [0.0, 1.0]
    revisit(model, MotionConfig(), times, 0.02, torch.zeros(2, dtype=torch.bool))
    assert model.dynamic.tolist() == [False, True]
    # It moves from now on, about the place where it stood still.
    with torch.no_grad():
        drawn = torch.stack([model.at(t, sh_degree=0).means for t in times])
    assert torch.allclose(drawn.mean(0), before, atol=1e-6)
    assert float((drawn[1, 1] - drawn[0, 1]).norm()) == pytest.approx(1.0)


def test_model_bytes_count_the_field_only_while_something_moves(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path)
    model = trainer.model
    n = len(model.canonical)
    gaussians_only = n * 4 * (3 + 4 + 3 + 1 + 3) + -(-n // 8)
    field = sum(p.numel() * 4 for p in [*model.field.parameters(), *model.head.parameters()])
    assert model_bytes(model, 0) == gaussians_only + field
    model.dynamic[:] = False
    assert model_bytes(model, 0) == gaussians_only
    assert model_bytes(model, 3) == gaussians_only + n * 4 * 3 * 15
    with torch.no_grad():  # two temporal Gaussians: their τ and σ, and the flags saying so
        model.canonical.time_log_scales[:2] = math.log(0.1)
    assert model_bytes(model, 0) == gaussians_only + 2 * 4 * 2 + -(-n // 8)


def test_flags_follow_densification_and_survive_resume(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path)
    for step in range(3):
        trainer.train_step(step)
    model, state = trainer.model, trainer.lifecycle.state
    n = len(model.canonical)
    model.dynamic[: n // 2] = False
    flags = model.dynamic.clone()
    state.grad_sum[:] = torch.linspace(0, 1, n)
    state.count[:] = 1.0
    plan = plan_refinement(DensifyConfig(reset_opacity_every=0), model, state, 100, trainer.extent)
    assert plan is not None
    apply_topology(model, trainer.optimizer, *plan)
    assert torch.equal(model.dynamic, flags[plan[0].source])  # children inherit
    trainer.lifecycle.state = type(state).zeros(len(model.canonical), trainer.device)
    trainer.save()

    resumed = Trainer(trainer.config, tmp_path, NullWriter())
    resumed.load(trainer.checkpoint_path())
    assert torch.equal(resumed.model.dynamic, model.dynamic)
    resumed.train_step(3)


@pytest.mark.slow
def test_a_still_scene_trains_as_a_static_scene(tmp_path: Path) -> None:
    still = dataclasses.replace(TINY_SCENE, motion=False)
    config = tiny_config(
        data=str(demo_path(still)),
        max_iters=240,
        warmup_iters=40,
        time_ramp=0.0,
        motion=MotionConfig(every=100),
    )
    trainer = Trainer(config, tmp_path, NullWriter())
    metrics = trainer.train()

    static = ~trainer.model.dynamic
    assert float(static.float().mean()) >= 0.95
    assert metrics["dynamic_fraction"] <= 0.05
    calls = field_calls(trainer.model.field)
    trainer.model.at(0.5, sh_degree=0)
    assert metrics["static_scene"] is (not trainer.model.any_dynamic())
    assert calls == ([] if metrics["static_scene"] else [int(trainer.model.dynamic.sum())])


def test_the_rig_splits_the_moving_objects_from_the_still_background(tmp_path: Path) -> None:
    """On a fixed-camera rig whose Gaussians all start dynamic (`start_from_pixels=False`)
    the first revisit marks those on the ball and the cube dynamic (their pixels change)
    and those on the still pedestal and pillar static (a field that has not trained yet
    moves nothing)."""
    motion = MotionConfig(start_from_pixels=False)
    config = tiny_config(data=str(demo_path(RIG)), warmup_iters=1, motion=motion)
    trainer = Trainer(config, tmp_path, NullWriter())
    trainer.train_step(0)  # the warm-up: every Gaussian starts dynamic
    assert bool(trainer.model.dynamic.all())
    # No gradient statistics yet (one view's pull is trivially coherent): pixels decide.
    n = len(trainer.model.canonical)
    trainer.lifecycle.state = type(trainer.lifecycle.state).zeros(n, trainer.device)
    trainer.lifecycle.revisit_motion(trainer.step)

    model = trainer.model
    moving = _on_moving_object(model.canonical.means.detach(), RIG)
    dynamic = model.dynamic
    assert float(dynamic[moving].float().mean()) >= 0.98
    assert float(dynamic[~moving].float().mean()) <= 0.1
    # Only the dynamic ones query the field.
    calls = field_calls(model.field)
    model.at(0.5, sh_degree=0)
    assert calls == [int(dynamic.sum())]


def test_the_rig_promotes_what_its_pixels_see_move_at_every_revisit(tmp_path: Path) -> None:
    """A rig whose split went wrong (everything static: a noisy initial cloud had nothing
    on the moving objects when the warm-up ended) is put right by the next revisit."""
    config = tiny_config(data=str(demo_path(RIG)), warmup_iters=1)
    trainer = Trainer(config, tmp_path, NullWriter())
    trainer.train_step(0)
    trainer.train_step(1)
    model = trainer.model
    model.dynamic[:] = False
    moving = _on_moving_object(model.canonical.means.detach(), RIG)

    trainer.lifecycle.revisit_motion(trainer.step)
    assert float(model.dynamic[moving].float().mean()) >= 0.98
    model.dynamic[:] = False
    trainer.lifecycle.revisit_motion(
        trainer.step, final=True
    )  # the last word is measured motion's alone
    assert not model.any_dynamic()


def test_a_promotion_only_revisit_never_demotes() -> None:
    velocity = torch.zeros(3, 3)
    velocity[2, 0] = 1.0  # moves; the other two hold still
    model = _ScriptedMotion(velocity, torch.zeros(3, 3))
    model.dynamic[:] = torch.tensor([True, False, False])
    before = model.canonical.means.detach().clone()
    wants_motion = torch.zeros(3, dtype=torch.bool)

    counts = revisit(model, MotionConfig(), [0.0, 1.0], 0.02, wants_motion, demote=False)

    assert counts == (0, 1)  # the still dynamic one stays so; the moving static one is promoted
    assert model.dynamic.tolist() == [True, False, True]
    assert torch.equal(model.canonical.means.detach()[:2], before[:2])


def test_the_pixel_start_is_scheduled_at_the_warm_up_end_and_promotions_while_it_widens() -> None:
    config = tiny_config(
        max_iters=100, warmup_iters=20, time_ramp=0.5, motion=MotionConfig(every=10)
    )
    full = schedules.window_full_step(config)
    assert full == 70
    # Steps done: after 20 the warm-up is over; the promotions follow, then full revisits.
    assert [s for s in range(100) if schedules.is_pixel_start(config, s)] == [20]
    assert [s for s in range(100) if schedules.is_promotion_step(config, s)] == [30, 40, 50, 60]
    assert [s for s in range(100) if schedules.is_motion_step(config, s)] == [70, 80, 90]
    off = dataclasses.replace(config, motion=MotionConfig(every=10, start_from_pixels=False))
    assert not any(
        schedules.is_pixel_start(off, s) or schedules.is_promotion_step(off, s) for s in range(100)
    )


def test_the_rig_starts_from_its_pixels(tmp_path: Path) -> None:
    """At the end of the warm-up only the Gaussians on the ball and the cube stay dynamic,
    before any revisit; the run then trains on with the field queried for those alone."""
    config = tiny_config(data=str(demo_path(RIG)), warmup_iters=2)
    trainer = Trainer(config, tmp_path, NullWriter())
    trainer.train_step(0)
    assert bool(trainer.model.dynamic.all())
    trainer.train_step(1)  # the warm-up's last step: the pixels decide

    model = trainer.model
    moving = _on_moving_object(model.canonical.means.detach(), RIG)
    assert float(model.dynamic[moving].float().mean()) >= 0.98
    assert float(model.dynamic[~moving].float().mean()) <= 0.1
    calls = field_calls(model.field)
    trainer.train_step(2)
    assert calls == [int(model.dynamic.sum())]


@pytest.mark.parametrize(("start_crop", "cameras"), [(0.005, 6), (None, 6), (0.005, 1)])
def test_the_rig_cuts_its_field_to_what_starts_dynamic(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], start_crop: float | None, cameras: int
) -> None:
    """The pixel start of a synchronised rig cuts the untrained field to the dynamic
    Gaussians' span (unless `--motion.start-crop None`), the optimizer's state alike, and
    training goes on; one camera, one view of each time, keeps its field whole."""
    motion = MotionConfig(start_crop=start_crop)
    rig = dataclasses.replace(RIG, fixed_cameras=cameras)
    config = tiny_config(data=str(demo_path(rig)), warmup_iters=2, motion=motion)
    trainer = Trainer(config, tmp_path, NullWriter())
    field = trainer.model.field
    assert isinstance(field, HexPlaneField)
    whole = sum(p.numel() for p in field.parameters())
    for step in range(2):
        trainer.train_step(step)
    kept = sum(p.numel() for p in field.parameters())
    said = " ".join(capsys.readouterr().out.split())
    assert "start dynamic" in said  # the split did start from the pixels
    if start_crop is None or cameras == 1:
        assert kept == whole and "field cut" not in said
        return
    assert kept < 0.7 * whole and bool((field.extent.abs() < 1.0).any())
    assert "field cut to the span of the dynamic Gaussians (0.5-99.5 % along each axis)" in said
    before = [p.detach().clone() for p in field.parameters()]
    trainer.train_step(2)  # the cut planes are the optimizer's and train
    after = list(field.parameters())
    assert all(bool(p.isfinite().all()) for p in after)
    assert any(not torch.equal(a, b) for a, b in zip(after, before, strict=True))


def test_the_rig_from_unchecked_points_keeps_every_gaussian_dynamic(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The pixel test reads what each Gaussian's pixel shows: from a cloud used unchecked
    nothing says a Gaussian sits on the surface it is drawn over, so the start is not
    made (as from random points)."""
    data = DataConfig(initial_points="file")
    config = tiny_config(data=str(demo_path(RIG)), warmup_iters=2, dataset=data)
    trainer = Trainer(config, tmp_path, NullWriter())
    for step in range(3):
        trainer.train_step(step)
    assert bool(trainer.model.dynamic.all())
    said = " ".join(capsys.readouterr().out.split())
    assert "(points3d.ply) may not lie on surfaces: every Gaussian stays dynamic" in said


def test_without_fixed_cameras_the_pixel_start_changes_nothing(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, warmup_iters=2)
    assert trainer.lifecycle.motion.fixed_motion is None
    for step in range(4):
        trainer.train_step(step)
    assert bool(trainer.model.dynamic.all())


def test_the_field_is_cut_to_the_dynamic_gaussians_and_a_run_resumes(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, max_iters=40)
    for step in range(4):
        trainer.train_step(step)
    model = trainer.model
    # Only the Gaussians near the box centre move: the field is needed only there.
    box = model.box
    centre = torch.tensor(box.center, dtype=model.canonical.means.dtype)
    half = 0.5 * torch.tensor(box.size, dtype=centre.dtype)
    with torch.no_grad():
        model.dynamic[:] = ((model.canonical.means - centre).abs() < 0.3 * half).all(dim=1)
    assert 0 < int(model.dynamic.sum()) < len(model.dynamic)
    with torch.no_grad():
        before = model.deltas(0.3)[0].means.clone()
    bytes_before = model_bytes(model, 0)

    assert crop_field(model, trainer.optimizer) is not None

    with torch.no_grad():
        assert torch.allclose(model.deltas(0.3)[0].means, before, rtol=1e-5, atol=1e-6)
    assert model_bytes(model, 0) < bytes_before
    grids = list(model.field.parameters())
    for p in grids:  # Adam follows the cut planes
        assert trainer.optimizer.state[p]["exp_avg"].shape == p.shape
    trainer.train_step(4)
    trainer.save()

    resumed = Trainer(trainer.config, tmp_path, NullWriter())
    resumed.load(trainer.checkpoint_path())
    assert [p.shape for p in resumed.model.field.parameters()] == [p.shape for p in grids]
    with torch.no_grad():
        assert torch.equal(resumed.model.deltas(0.3)[0].means, model.deltas(0.3)[0].means)
    resumed.train_step(5)
