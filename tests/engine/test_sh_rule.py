"""The SH degree rises only when view-dependent error asks for it."""

from __future__ import annotations

from pathlib import Path

import torch

from dyngs.engine.densify import DensifyState, band_rows, probe_band
from dyngs.model import CanonicalGaussians, GaussianConfig, activate
from dyngs.renderers import CpuReferenceConfig
from dyngs.types import Camera
from tests.engine.helpers import tiny_trainer
from tests.renderers.scenes import look_at


def _probe_evidence(view_dependent: bool) -> float:
    """One grey Gaussian seen from 40 directions; the targets are its colour plus either a
    tint that depends on the view direction or per-view noise of the same size."""
    gen = torch.Generator().manual_seed(0)
    canonical = CanonicalGaussians.from_points(
        torch.zeros(1, 3), torch.full((1, 3), 0.5), GaussianConfig(sh_degree=1), gen
    )
    with torch.no_grad():
        canonical.log_scales.fill_(-1.0)
        canonical.opacity_logits.fill_(4.0)
    renderer = CpuReferenceConfig().build()
    state = DensifyState.zeros(1, torch.device("cpu"))
    for _ in range(40):
        direction = torch.randn(3, generator=gen, dtype=torch.float64)
        eye = 3.0 * direction / direction.norm()
        w2c = look_at(
            eye,
            torch.zeros(3, dtype=torch.float64),
            torch.tensor([0.3, 0.1, 1.0], dtype=torch.float64),
        )
        camera = Camera(20.0, 20.0, 8.0, 8.0, w2c.float(), 16, 16)
        sh = torch.cat((canonical.sh_dc, canonical.sh_rest), dim=1)
        drawn = activate(
            canonical.means, canonical.quats, canonical.log_scales, canonical.opacity_logits, sh, 1
        )
        out = renderer(drawn, camera, torch.zeros(3))
        if view_dependent:
            tint = 0.2 * float(direction[0] / direction.norm())
        else:
            tint = 0.2 * float(torch.randn((), generator=gen))
        target = (0.5 + tint) * out.alpha.detach()
        ((out.rgb - target) ** 2).sum().backward()
        probe_band(state, canonical.sh_rest, 1)
        assert canonical.sh_rest.grad is not None
        assert not bool(canonical.sh_rest.grad[:, band_rows(1)].any())  # the band stays frozen
        canonical.zero_grad()
    return state.sh_coherence()


def test_view_dependent_error_is_evidence_for_a_higher_band() -> None:
    # A tint linear in the view direction scores E[x²] / E|x| = 2/3 over uniform directions;
    # noise scores about 1/√views (0.16 here). The default threshold, 0.5, lies between.
    assert _probe_evidence(view_dependent=True) >= 0.6
    assert _probe_evidence(view_dependent=False) <= 0.3


def test_the_degree_rises_only_on_evidence(tmp_path: Path) -> None:
    config = GaussianConfig(sh_degree=2, sh_degree_interval=10)
    trainer = tiny_trainer(tmp_path, gaussians=config)
    n = len(trainer.model.canonical)
    state = trainer.lifecycle.state

    state.sh_pull[:, :3] = torch.randn(n, 3, 3, generator=torch.Generator().manual_seed(0))
    state.sh_pull_norm[:] = 10 * state.sh_pull[:, :3].flatten(1).norm(dim=-1)  # incoherent
    trainer.lifecycle.consider_sh_degree(10)
    assert trainer.model.active_sh_degree == 0

    state.sh_pull_norm[:] = state.sh_pull[:, :3].flatten(1).norm(dim=-1)  # perfectly coherent
    trainer.lifecycle.consider_sh_degree(15)  # not an SH interval
    assert trainer.model.active_sh_degree == 0
    trainer.lifecycle.consider_sh_degree(20)
    assert trainer.model.active_sh_degree == 1
    assert trainer.lifecycle.probe_degree() == 2


def test_training_keeps_the_probed_band_at_zero(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, gaussians=GaussianConfig(sh_degree=1, sh_degree_interval=50))
    for step in range(6):
        trainer.train_step(step)
    sh_rest = trainer.model.canonical.sh_rest
    assert trainer.model.active_sh_degree == 0 and trainer.lifecycle.probe_degree() == 1
    assert not bool(sh_rest[:, band_rows(1)].any())
    assert float(trainer.lifecycle.state.sh_pull_norm.sum()) > 0
