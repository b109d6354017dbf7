"""The `dyngs-train` command line: presets, swapping components, override files, plugins,
and one-line errors for bad input."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

from dyngs.cli import main
from dyngs.fields.hexplane import HexPlaneConfig
from dyngs.fields.mlp import MLPFieldConfig
from dyngs.renderers import CpuReferenceConfig, CudaTileConfig
from dyngs.runs import parse_train_args

ROOT = Path(__file__).resolve().parents[1]


def test_canonical_call_and_common_flags() -> None:
    config = parse_train_args(
        [
            "hexplane-4dgs",
            "--data",
            "some/path",
            "--output-dir",
            "out",
            "--max-iters",
            "7",
            "--seed",
            "3",
        ]
    )
    assert config.method == "hexplane-4dgs"
    assert (config.data, str(config.output_dir), config.max_iters, config.seed) == (
        "some/path",
        "out",
        7,
        3,
    )
    assert isinstance(config.field, HexPlaneConfig)


def test_swapping_components_and_flags_after_subcommands() -> None:
    config = parse_train_args(
        ["hexplane-4dgs", "renderer:cuda-tile", "field:mlp", "--data", "x", "--field.width", "32",
         "--renderer.packed", "--max-iters", "9", "--downscale", "4"]
    )  # fmt: skip
    assert isinstance(config.renderer, CudaTileConfig) and config.renderer.packed
    assert isinstance(config.field, MLPFieldConfig) and config.field.width == 32
    assert config.max_iters == 9 and config.dataset.downscale == 4

    mlp = parse_train_args(["mlp-4dgs", "renderer:cpu-reference", "--renderer.tile-size", "16"])
    assert isinstance(mlp.field, MLPFieldConfig) and mlp.method == "mlp-4dgs"
    assert isinstance(mlp.renderer, CpuReferenceConfig) and mlp.renderer.tile_size == 16


@pytest.mark.parametrize("path", sorted((ROOT / "configs").glob("*.args")), ids=lambda p: p.name)
def test_override_files_load(path: Path) -> None:
    config = parse_train_args(["hexplane-4dgs", f"@{path}"])
    assert config.method == "hexplane-4dgs"
    mentioned = path.read_text()
    if "--downscale" in mentioned:
        assert config.dataset.downscale > 1
    if "--data" in mentioned:
        assert config.data != ""


def test_plugin_preset_from_an_entry_point(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "dummy_dyngs_plugin.py").write_text(
        textwrap.dedent(
            """
            from dyngs.config import TrainConfig

            def preset():
                return TrainConfig(max_iters=1234, warmup_iters=11)
            """
        )
    )
    info = tmp_path / "dummy_dyngs_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: dummy-dyngs-plugin\nVersion: 0.1\n"
    )
    (info / "entry_points.txt").write_text(
        "[dyngs.methods]\ndummy-4dgs = dummy_dyngs_plugin:preset\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    config = parse_train_args(["dummy-4dgs", "--seed", "5"])
    assert (config.method, config.max_iters, config.warmup_iters, config.seed) == (
        "dummy-4dgs",
        1234,
        11,
        5,
    )
    sys.modules.pop("dummy_dyngs_plugin", None)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["hexplane-4dgs", "--max-iters", "-5"], "--max-iters must be ≥ 0"),
        (["hexplane-4dgs", "--downscale", "0"], "--downscale must be ≥ 1"),
        (["hexplane-4dgs", "--losses.change-weight", "-1"], "--losses.change-weight must be ≥ 0"),
        (["hexplane-4dgs", "--losses.arap", "nan"], "--losses.arap must be ≥ 0"),
        (
            ["hexplane-4dgs", "--losses.plane-roughness", "-1"],
            "--losses.plane-roughness must be ≥ 0",
        ),
        (
            ["hexplane-4dgs", "--losses.plane-roughness", "nan"],
            "--losses.plane-roughness must be ≥ 0",
        ),
        (
            ["hexplane-4dgs", "--gaussians.filter-3d", "-1"],
            "--gaussians.filter-3d must be ≥ 0 and finite",
        ),
        (
            ["hexplane-4dgs", "--gaussians.filter-3d", "nan"],
            "--gaussians.filter-3d must be ≥ 0 and finite",
        ),
        (
            ["hexplane-4dgs", "--gaussians.filter-3d", "inf"],
            "--gaussians.filter-3d must be ≥ 0 and finite",
        ),
        (["hexplane-4dgs", "--losses.dssim", "1.5"], "--losses.dssim must be in [0, 1]"),
        (["hexplane-4dgs", "--losses.arap-neighbors", "0"], "--losses.arap-neighbors must be ≥ 1"),
        (["hexplane-4dgs", "--data", "/no/such/folder"], "/no/such/folder: does not exist"),
        (
            ["hexplane-4dgs", "@/no/such/file.args"],
            "/no/such/file.args: argument file does not exist",
        ),
    ],
)
def test_bad_values_end_in_one_line(
    args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main([*args, "--output-dir", str(tmp_path)] if args[-1] != "@/no/such/file.args" else args)
    assert exit_info.value.code == 2
    out = capsys.readouterr()
    text = (out.out + out.err).strip()
    assert message in text
    assert "Traceback" not in text
    assert len(text.splitlines()) == 1, text


def test_unknown_renderer_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["hexplane-4dgs", "renderer:opengl"])
    assert exit_info.value.code == 2
    out = capsys.readouterr()
    assert "renderer:opengl" in out.out + out.err
