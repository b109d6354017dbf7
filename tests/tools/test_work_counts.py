"""benchmarks/work_counts.py: the counted pairs are the pairs the renderer bins."""

from __future__ import annotations

import statistics
from pathlib import Path

import torch

from dyngs.renderers import cpu_reference, stages
from dyngs.runs import load_run
from tests.tools.conftest import load_benchmark

work_counts = load_benchmark("work_counts")


def test_counts_match_the_renderers_binning(tiny_run: Path) -> None:
    run = load_run(tiny_run)
    row = work_counts.count_run(run, "test")
    renderer = run.renderer
    assert isinstance(renderer, cpu_reference.CpuReferenceRenderer)
    binned, pixels, visible = [], [], []
    with torch.no_grad():
        for view in run.data().views("test"):
            gaussians = run.model.at(view.time)
            screen = stages.project(
                gaussians, view.camera, renderer.guards, renderer.config.antialiased
            )
            w, h = view.camera.width, view.camera.height
            tile = renderer.config.tile_size or cpu_reference.choose_tile_size(screen, w, h)
            bins = stages.bin_tiles(screen, w, h, tile)
            binned.append(int(bins.tile_count.sum()))
            pixels.append(int(bins.tile_count.sum()) * tile * tile)
            visible.append(int(screen.visible.sum()))
    assert row["views"] == len(binned) > 0
    assert row["tile_pairs"] == statistics.mean(binned) > 0
    assert row["pixel_pairs"] == statistics.mean(pixels)
    assert row["visible"] == statistics.mean(visible)
    assert row["gaussians"] == len(run.model.canonical)
    expected_deformed = int(run.model.dynamic.sum()) if run.model.deforming else 0
    assert row["deformed"] == expected_deformed
