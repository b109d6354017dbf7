"""Temporal opacity: a Gaussian of what moves is drawn around the time it was seen
(Spacetime Gaussians' temporal radial basis); an eternal one is drawn as before, bit for
bit, and its time parameters never move. Carved points get their lifetimes from the
windows whose hulls hold them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from dyngs.datamanagers import init_points
from dyngs.datamanagers.datamanager import DataConfig, load_scene
from dyngs.datamanagers.procedural import (
    ProceduralSceneConfig,
    scene_objects,
    write_procedural_scene,
)
from dyngs.fields import DeformationHeadConfig, HexPlaneConfig
from dyngs.model import ETERNAL, CanonicalGaussians, DynamicGaussians, GaussianConfig
from dyngs.types import SceneBox

BOX = SceneBox((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def _model(n: int = 6) -> DynamicGaussians:
    gen = torch.Generator().manual_seed(0)
    model = DynamicGaussians.build(GaussianConfig(), HexPlaneConfig(resolution=(8, 8, 8, 4)),
                                   DeformationHeadConfig(), BOX, n, gen)  # fmt: skip
    points = torch.rand(n, 3, generator=gen) - 0.5
    lifetimes = torch.tensor([[0.2, 0.1], [0.8, 0.05]] + [[0.5, math.inf]] * (n - 2))
    model.canonical.initialize(points, torch.rand(n, 3, generator=gen), GaussianConfig(), lifetimes)
    return model


def test_temporal_opacity_is_the_radial_basis_and_eternal_is_exactly_one() -> None:
    model = _model()
    c = model.canonical
    assert c.temporal().tolist() == [True, True, False, False, False, False]
    base = torch.sigmoid(c.opacity_logits.detach())
    for t in (0.0, 0.2, 0.35, 0.8, 1.0):
        drawn = model.at(t, deform=False).opacities.detach()
        expected = base[:2] * torch.exp(
            -0.5 * ((t - torch.tensor([0.2, 0.8])) / torch.tensor([0.1, 0.05])) ** 2
        )
        assert torch.allclose(drawn[:2], expected, rtol=1e-5, atol=1e-7)
        assert torch.equal(drawn[2:], base[2:])  # eternal: untouched, bit for bit


def test_only_temporal_gaussians_get_time_gradients() -> None:
    model = _model()
    model.at(0.3, deform=False).opacities.sum().backward()
    c = model.canonical
    assert c.time_centers.grad is not None and c.time_log_scales.grad is not None
    assert bool((c.time_centers.grad[:2] != 0).all()) and bool(
        (c.time_log_scales.grad[:2] != 0).all()
    )
    assert bool((c.time_centers.grad[2:] == 0).all()) and bool(
        (c.time_log_scales.grad[2:] == 0).all()
    )


def test_a_model_saved_before_temporal_opacity_loads_as_eternal() -> None:
    model = _model()
    state = model.state_dict()
    for key in ("canonical.time_centers", "canonical.time_log_scales"):
        del state[key]
    loaded = DynamicGaussians.load(GaussianConfig(), HexPlaneConfig(resolution=(8, 8, 8, 4)),
                                   DeformationHeadConfig(), state)  # fmt: skip
    assert not bool(loaded.canonical.temporal().any())
    assert bool((loaded.canonical.time_log_scales == ETERNAL).all())


def test_lifetimes_must_fit_the_points() -> None:
    canonical = CanonicalGaussians(3, 0)
    with pytest.raises(ValueError, match="lifetimes"):
        canonical.initialize(torch.zeros(3, 3), None, GaussianConfig(), torch.zeros(2, 2))


def test_carved_points_of_what_moves_live_when_it_was_there(tmp_path: Path) -> None:
    rig = ProceduralSceneConfig(resolution=48, num_times=16, num_test=2, num_val=1, fixed_cameras=5)
    write_procedural_scene(tmp_path, rig)
    scene = load_scene(tmp_path, DataConfig(initial_points="data", num_random_points=3000))
    assert (
        scene.point_lifetimes is not None and "seen only around some times" in scene.points_source
    )
    times = scene.point_lifetimes
    temporal = torch.isfinite(times[:, 1])
    assert 0 < int(temporal.sum()) < len(times)
    points = scene.points.double().numpy()
    # A temporal point lies on a moving object near its time τ (where the object was then)…
    near_then = []
    for point, (tau, _) in zip(points[temporal.numpy()], times[temporal].tolist(), strict=True):
        distance = min(
            obj.signed_distance(point[None])[0] for obj in scene_objects(rig, tau) if obj.dynamic
        )
        near_then.append(distance < 0.3)
    assert float(np.mean(near_then)) > 0.7
    # …and an eternal one mostly on what never moves, or in the loose parts of the hulls.
    still = np.full(int((~temporal).sum()), np.inf)
    for obj in scene_objects(rig, 0.0):
        if not obj.dynamic:
            still = np.minimum(still, obj.signed_distance(points[~temporal.numpy()]))
    assert float((still < 0.3).mean()) > 0.5
    assert bool((times[temporal, 1] > 0).all()) and bool((times[temporal, 1] <= 0.5).all())
    assert init_points.ETERNAL_SHARE > 0.5


def test_a_place_carved_into_several_temporal_gaussians_gets_its_places_scale() -> None:
    """Four Gaussians at one carved place (held by four stretches of time) would have
    their three nearest at distance 0 and start at the 1e-7 floor, drawing nothing for
    good; they get the place's distance to its nearest other places instead, and every
    other Gaussian keeps the plain mean distance to its three nearest."""
    gen = torch.Generator().manual_seed(3)
    others = torch.rand(40, 3, generator=gen) - 0.5
    place = torch.tensor([[0.05, -0.02, 0.1]])
    points = torch.cat((others, place.expand(4, 3)))
    stretches = torch.tensor([[0.1, 0.05], [0.4, 0.05], [0.6, 0.05], [0.9, 0.05]])
    lifetimes = torch.cat((torch.full((40, 2), math.inf), stretches))
    model = CanonicalGaussians(len(points), 0)
    model.initialize(points, None, GaussianConfig(), lifetimes)
    scales = model.log_scales.detach()[:, 0].exp()
    to_others = (place - others).norm(dim=-1).sort().values[:3].mean()
    torch.testing.assert_close(scales[40:], to_others.expand(4), rtol=1e-6, atol=0)
    # The others: the plain rule, which counts the place once per Gaussian at it.
    everything = (others[:, None, :] - points[None, :, :]).norm(dim=-1)
    everything[torch.arange(40), torch.arange(40)] = math.inf  # not itself
    plain = everything.sort(dim=1).values[:, :3].mean(dim=1)
    torch.testing.assert_close(scales[:40], plain, rtol=1e-6, atol=0)
