"""dyngs-bench: a two-point sweep writes its CSV, JSON, plot and TensorBoard entries,
and running it again trains nothing."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from dyngs.errors import ConfigError
from dyngs.tools.bench import (
    SWEEPS,
    BenchConfig,
    load_sweep_file,
    main,
    pareto_front,
    plan_points,
    point_tokens,
    resolve_sweep,
)
from tests.tools.conftest import TINY_FLAGS


def _bench(out: Path, data: Path, *extra: str) -> None:
    main(["--data", str(data), "--output-dir", str(out), "--grid", "max-iters=2,3",
          "--warmup", "0", *extra, "--", *TINY_FLAGS])  # fmt: skip


@pytest.mark.slow
def test_sweep_writes_results_and_resumes(tmp_path: Path, tiny_data: Path) -> None:
    out = tmp_path / "bench"
    _bench(out, tiny_data)
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert [r["status"] for r in rows] == ["trained", "trained"]
    assert [r["iterations"] for r in rows] == [2, 3]
    for row in rows:
        assert 0 < row["psnr"] < 100 and row["render_ms_median"] > 0 and row["train_seconds"] > 0
    with (out / "results.csv").open() as f:
        table = list(csv.DictReader(f))
    assert [r["param:max-iters"] for r in table] == ["2", "3"]
    image = cv2.imread(str(out / "results.png"))
    assert image is not None and image.shape[0] > 400 and image.shape[1] > 1000
    for row in rows:
        events = EventAccumulator(str(out / "tensorboard" / row["name"]))
        events.Reload()
        assert "_hparams_/session_start_info" in events.PluginTagToContent("hparams")
        assert events.Scalars("bench/psnr")[0].value == pytest.approx(row["psnr"])

    # Run again with one point's evaluation gone: that point is evaluated again, nothing
    # is retrained, and the other point's files are not touched.
    (Path(rows[0]["run_dir"]) / "eval_test.json").unlink()
    stamps = {p: p.stat().st_mtime_ns for p in (out / "points").glob("*/*.json")}
    checkpoints = {p: p.stat().st_mtime_ns for p in (out / "points").glob("*/checkpoint.pt")}
    _bench(out, tiny_data)
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert [r["status"] for r in rows] == ["evaluated", "skipped"]
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert {p: p.stat().st_mtime_ns for p in checkpoints} == checkpoints
    assert (Path(rows[0]["run_dir"]) / "eval_test.json").is_file()


def test_bad_sweep_flag_is_one_line(
    tmp_path: Path, tiny_data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--data", str(tiny_data), "--output-dir", str(tmp_path), "--grid", "max-iterz=1,2"])
    assert exit_info.value.code == 2
    out = capsys.readouterr().out.strip()
    assert out.startswith("error:") and "--max-iterz" in out and "\n" not in out
    assert not (tmp_path / "points").exists()  # nothing trained before every point parsed


def test_pareto_front() -> None:
    costs = [10.0, 5.0, 20.0, 5.0, 1.0, 30.0]
    psnr = [25.0, 24.0, 28.0, 23.0, 20.0, 27.0]
    # 1 beats 3 (same cost, higher), 2 beats 5 (cheaper and higher).
    assert pareto_front(costs, psnr) == [4, 1, 0, 2]


def test_grid_and_points_become_train_flags(tmp_path: Path) -> None:
    assert point_tokens({"method": "mlp-4dgs", "field": "hexplane", "max-iters": "9",
                         "field.resolution": "4 4 4 2", "renderer.antialiased": "false"}) == (
        "mlp-4dgs", ["field:hexplane"],
        ["--max-iters", "9", "--field.resolution", "4", "4", "4", "2", "--renderer.no-antialiased"],
    )  # fmt: skip
    sweep = resolve_sweep(BenchConfig(sweep="fields", grid=("max_iters=5,6",)))
    points = plan_points(BenchConfig(output_dir=tmp_path), sweep)
    assert len(points) == 2 * len(SWEEPS["fields"].points)
    assert [p.config.max_iters for p in points[:2]] == [5, 6]
    assert points[4].config.method == "hexplane-4dgs" and points[4].params["field"] == "mlp"
    assert len({p.name for p in points}) == len(points)


def test_sweep_files(tmp_path: Path) -> None:
    toml = tmp_path / "s.toml"
    toml.write_text('method = "mlp-4dgs"\n[grid]\nmax_iters = [1, 2]\n[[points]]\nseed = 3\n')
    sweep = load_sweep_file(toml)
    assert sweep.method == "mlp-4dgs" and sweep.expand() == [
        {"seed": "3", "max-iters": "1"}, {"seed": "3", "max-iters": "2"}
    ]  # fmt: skip
    as_json = tmp_path / "s.json"
    as_json.write_text('{"points": [{"field": "mlp"}, {}], "bogus": 1}')
    with pytest.raises(ConfigError, match="unknown sweep keys"):
        load_sweep_file(as_json)


@pytest.mark.parametrize("name", sorted(SWEEPS))
def test_builtin_sweeps_are_valid_train_flags(name: str, tmp_path: Path) -> None:
    points = plan_points(BenchConfig(output_dir=tmp_path), resolve_sweep(BenchConfig(sweep=name)))
    assert len(points) >= 2 and len({p.name for p in points}) == len(points)


@pytest.mark.slow
def test_seeds_give_each_point_a_spread_and_a_paired_change(
    tmp_path: Path, tiny_data: Path
) -> None:
    out = tmp_path / "bench"
    _bench(out, tiny_data, "--seeds", "0", "1")
    results = json.loads((out / "results.json").read_text())
    rows = {(r["param:max-iters"], r["param:seed"]): r for r in results["rows"]}
    assert sorted(rows) == [("2", "0"), ("2", "1"), ("3", "0"), ("3", "1")]
    assert rows["2", "0"]["psnr"] != rows["2", "1"]["psnr"]  # the seed reaches training
    first, second = results["seeds"]
    assert (first["point"], second["point"]) == ("max-iters=2", "max-iters=3")
    assert first["seeds"] == second["seeds"] == [0, 1]
    psnr = [rows["3", s]["psnr"] for s in "01"]
    assert second["psnr"]["mean"] == pytest.approx(sum(psnr) / 2)
    assert second["psnr"]["std"] == pytest.approx(abs(psnr[0] - psnr[1]) / 2**0.5)
    assert (second["psnr"]["min"], second["psnr"]["max"]) == (min(psnr), max(psnr))
    assert "versus" not in first and second["versus"] == "max-iters=2"
    differences = [rows["3", s]["psnr"] - rows["2", s]["psnr"] for s in "01"]
    assert second["change:psnr"]["mean"] == pytest.approx(sum(differences) / 2)
    assert second["change:psnr"]["stderr"] == pytest.approx(
        abs(differences[0] - differences[1]) / 2
    )  # std / √2 of two differences
    # Two pairs: p = 1 unless both changed the same way (then the 2 of 4 sign choices).
    same_way = differences[0] * differences[1] > 0
    assert second["change:psnr"]["p"] == (0.5 if same_way else 1.0)
    ratios = [rows["3", s]["model_bytes"] / rows["2", s]["model_bytes"] - 1 for s in "01"]
    assert second["change:model_bytes"]["mean"] == pytest.approx(sum(ratios) / 2)
    with (out / "seeds.csv").open() as f:
        table = list(csv.DictReader(f))
    assert [r["point"] for r in table] == ["max-iters=2", "max-iters=3"]
    assert float(table[1]["change:psnr:mean"]) == pytest.approx(second["change:psnr"]["mean"])


def test_seeds_are_given_once(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="a seed repeats"):
        resolve_sweep(BenchConfig(seeds=(0, 0)))
    with pytest.raises(ConfigError, match="already sets `seed`"):
        resolve_sweep(BenchConfig(grid=("seed=1,2",), seeds=(0,)))
    sweep = resolve_sweep(BenchConfig(sweep="adaptive", seeds=(0, 1)))
    points = plan_points(BenchConfig(output_dir=tmp_path), sweep)
    assert [p.params.get("seed") for p in points] == ["0", "1", "0", "1"]
    assert [p.config.seed for p in points] == [0, 1, 0, 1]
    assert not points[0].config.motion.separate and points[2].config.motion.separate
