from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from dyngs.config import TrainConfig
from dyngs.configio import config_from_dict, config_to_dict, load_config, save_config
from dyngs.errors import ConfigError
from dyngs.fields.mlp import MLPFieldConfig
from dyngs.methods import method_presets
from dyngs.renderers import CudaTileConfig


def test_every_preset_round_trips(tmp_path: Path) -> None:
    presets, _ = method_presets()
    variants = [
        *presets.values(),
        dataclasses.replace(
            TrainConfig(), renderer=CudaTileConfig(packed=True), field=MLPFieldConfig(depth=3)
        ),
        TrainConfig(output_dir=Path("/somewhere/else"), run_name="x"),
    ]
    for config in variants:
        assert config_from_dict(config_to_dict(config)) == config
        save_config(tmp_path / "config.json", config)
        assert load_config(tmp_path / "config.json") == config


def test_bad_config_files_say_which(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no config here"):
        load_config(tmp_path / "missing.json")
    broken = tmp_path / "config.json"
    broken.write_text("{ not json")
    with pytest.raises(ConfigError, match=r"config.json: malformed JSON at line 1"):
        load_config(broken)
