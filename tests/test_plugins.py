"""A third party extends dyngs without touching it: an installed package (a dist-info on
the path, as pip leaves it) adds a field, a renderer, a dataset format and a loss term
through entry points, and `dyngs-train` selects them by name and trains with them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from dyngs.datamanagers.procedural import demo_path
from dyngs.registry import Registry
from tests.engine.helpers import TINY_SCENE

PLUGIN = '''
"""A dummy dyngs plugin: one of each kind of component."""

import json
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from dyngs.datamanagers.formats import FORMATS, DatasetFormat
from dyngs.fields.base import PlaneGrids
from dyngs.renderers.cpu_reference import CpuReferenceRenderer


@dataclass(frozen=True)
class TimeFeatureConfig:
    """Features that depend on time alone: a line in t per channel."""

    features: int = 4

    def build(self, box, *, generator=None):
        return TimeFeatureField(self.features)


class TimeFeatureField(nn.Module):
    def __init__(self, features):
        super().__init__()
        self.out_dim = features
        self.lines = nn.Parameter(torch.ones(2, features))

    def forward(self, xyz, t):
        return (self.lines[0] + t * self.lines[1]).expand(len(xyz), -1)

    def planes(self):
        return PlaneGrids()


@dataclass(frozen=True)
class CountingConfig:
    """cpu-reference, counting its frames in a file."""

    log: str = ""

    def build(self):
        return CountingRenderer(self.log)


class CountingRenderer:
    def __init__(self, log):
        self.inner, self.log = CpuReferenceRenderer(), log

    def __call__(self, gaussians, camera, background):
        with open(self.log, "a") as f:
            f.write(f"{camera.width}x{camera.height}\\n")
        return self.inner(gaussians, camera, background)


def _parse_pointer(path, config, seed):
    target = json.loads((path / "pointer.json").read_text())["dnerf"]
    return FORMATS.get("dnerf").parse(Path(target), config, seed)


POINTER = DatasetFormat("pointer.json", _parse_pointer, "a file naming a D-NeRF folder")


def mean_opacity(inputs):
    return inputs.gaussians.opacities.mean()
'''

ENTRY_POINTS = """
[dyngs.fields]
time-feature = dyngs_dummy:TimeFeatureConfig

[dyngs.renderers]
counting = dyngs_dummy:CountingConfig

[dyngs.formats]
pointer = dyngs_dummy:POINTER

[dyngs.losses]
mean-opacity = dyngs_dummy:mean_opacity

[dyngs.fields]
broken = dyngs_dummy:nothing_here
"""


def install_dummy_plugin(site: Path) -> None:
    """What `pip install` of a package with these entry points leaves on the path."""
    (site / "dyngs_dummy.py").write_text(textwrap.dedent(PLUGIN))
    info = site / "dyngs_dummy-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: dyngs-dummy\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)


@pytest.mark.slow
def test_a_plugin_field_renderer_format_and_loss_term_train(tmp_path: Path) -> None:
    site = tmp_path / "site"
    site.mkdir()
    install_dummy_plugin(site)
    data = tmp_path / "pointer-scene"
    data.mkdir()
    (data / "pointer.json").write_text(json.dumps({"dnerf": str(demo_path(TINY_SCENE))}))
    log = tmp_path / "frames.log"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), *sys.path]))
    result = subprocess.run(
        [sys.executable, "-m", "dyngs.cli", "hexplane-4dgs", "field:time-feature",
         "renderer:counting", "--renderer.log", str(log), "--data", str(data),
         "--losses.extra", "mean-opacity", "0.5", "--max-iters", "2", "--warmup-iters", "0",
         "--no-tensorboard", "--num-random-points", "300",
         "--output-dir", str(tmp_path), "--run-name", "run"],
        capture_output=True, text=True, env=env, timeout=600,
    )  # fmt: skip
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    run = tmp_path / "run"
    config = json.loads((run / "config.json").read_text())
    assert config["field"]["__class__"] == "dyngs_dummy:TimeFeatureConfig"
    assert config["renderer"]["__class__"] == "dyngs_dummy:CountingConfig"
    assert config["losses"]["extra"] == {"mean-opacity": 0.5}
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["renderer"] == "counting" and metrics["iterations"] == 2
    # Two training steps, then the test views (timed once after a warm-up, scored once).
    frames = log.read_text().splitlines()
    assert len(frames) == 2 + 1 + 2 * TINY_SCENE.num_test
    # The renderer cannot measure contribution: the run says so once, and trains on.
    assert output.count("cannot measure each Gaussian's contribution") == 1
    # The broken entry point is named once and skipped.
    assert "field 'broken'" in output and "failed to load" in output


def test_unknown_names_list_what_is_known() -> None:
    registry: Registry[int] = Registry("widget", "dyngs.no-such-group")
    registry.register("one", 1, "the first")
    with pytest.raises(Exception, match="unknown widget 'two': known are one"):
        registry.get("two")
    with pytest.raises(ValueError, match="already registered"):
        registry.register("one", 2)
