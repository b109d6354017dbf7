"""benchmarks/compare_runs.py: runs are paired by name, summarised per scene and pooled,
and bad patterns or unreadable metrics stop it with the file named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dyngs.tools.paired import paired_change
from tests.tools.conftest import load_benchmark

compare_runs = load_benchmark("compare_runs")

BASE = {"texture-s0": 27.5, "texture-s1": 28.0, "texture-s2": 28.2, "collision-s0": 41.2,
        "collision-s1": 41.0}  # fmt: skip
VARIANT = {"texture-s0": 28.3, "texture-s1": 27.3, "texture-s2": 28.8, "collision-s0": 43.0,
           "collision-s1": 41.3, "collision-s9": 40.0}  # fmt: skip


def _runs(root: Path, psnrs: dict[str, float], seconds: float) -> None:
    for name, psnr in psnrs.items():
        (root / name).mkdir(parents=True)
        metrics = {"psnr": psnr, "ssim": psnr / 100, "lpips": None, "train_seconds": seconds,
                   "num_gaussians": 1000}  # fmt: skip
        (root / name / "metrics.json").write_text(json.dumps(metrics))


def test_pairs_by_name_per_scene_and_pooled(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    _runs(tmp_path / "base", BASE, 100.0)
    _runs(tmp_path / "variant", VARIANT, 110.0)
    (tmp_path / "base" / "texture-s3").mkdir()  # unfinished: no metrics, no pair
    output = tmp_path / "out" / "compare.json"
    compare_runs.main(["--base", f"{tmp_path}/base/{{}}", "--variant",
                       f"{tmp_path}/variant/{{}}", "--output", str(output)])  # fmt: skip
    result = json.loads(output.read_text())
    assert [p["name"] for p in result["pairs"]] == sorted(BASE)  # collision-s9 has no base
    collision, texture, pooled = result["summaries"]  # scenes in name order
    names = sorted(BASE)
    expected = paired_change([BASE[n] for n in names], [VARIANT[n] for n in names])
    assert (pooled["label"], pooled["pairs"], pooled["wins"]) == ("all pairs", 5, 4)
    assert pooled["change"] == pytest.approx(expected.mean)
    assert pooled["stderr"] == pytest.approx(expected.stderr)
    assert pooled["p"] == pytest.approx(expected.p)
    assert pooled["train_seconds_change"] == pytest.approx(0.10)
    assert pooled["ssim_change"] == pytest.approx(expected.mean / 100)
    assert pooled["lpips_change"] is None  # not measured: no figure rather than a zero
    assert texture["label"] == "texture" and texture["pairs"] == 3
    assert texture["change"] == pytest.approx((0.8 - 0.7 + 0.6) / 3)
    assert collision["verdict"] == "within noise"  # two pairs can never say more
    printed = capsys.readouterr().out
    assert "| all pairs | 5 |" in printed and f"wrote {output}" in printed


def test_bad_patterns_and_metrics(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="exactly one"):
        compare_runs.main(["--base", f"{tmp_path}/base", "--variant", f"{tmp_path}/v/{{}}"])
    with pytest.raises(SystemExit, match="no finished runs"):
        compare_runs.main(["--base", f"{tmp_path}/b/{{}}", "--variant", f"{tmp_path}/v/{{}}"])
    _runs(tmp_path / "b", {"x-s0": 30.0}, 1.0)
    (tmp_path / "v" / "x-s0").mkdir(parents=True)
    (tmp_path / "v" / "x-s0" / "metrics.json").write_text("{not json")
    with pytest.raises(SystemExit, match=r"v/x-s0/metrics.json: unreadable"):
        compare_runs.main(["--base", f"{tmp_path}/b/{{}}", "--variant", f"{tmp_path}/v/{{}}"])
