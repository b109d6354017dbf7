"""benchmarks/rerender.py: every run is timed with every code version; bad ones are refused."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from dyngs.tools.common import cpu_model, machine_info
from tests.tools.conftest import BENCHMARKS, load_benchmark

ROOT = BENCHMARKS.parent
rerender = load_benchmark("rerender")


def test_code_versions_are_parsed_and_bad_ones_refused(tmp_path: Path) -> None:
    assert rerender.parse_codes([]) == {"installed": None}
    assert rerender.parse_codes([f"a={ROOT}", f"b={ROOT}"]) == {"a": ROOT, "b": ROOT}
    for bad in (str(ROOT), f"={ROOT}", f"a={tmp_path}"):
        with pytest.raises(SystemExit, match="LABEL=PATH"):
            rerender.parse_codes([bad])
    with pytest.raises(SystemExit, match="given twice"):
        rerender.parse_codes([f"a={ROOT}", f"a={ROOT}"])


@pytest.mark.slow
def test_every_run_is_timed_with_every_code_version(
    tiny_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    output = tmp_path / "rerender.json"
    argv = ["rerender.py", str(tiny_run), "--repeats", "1", "--output", str(output)]
    monkeypatch.setattr(sys, "argv", [*argv, "--code", f"one={ROOT}", f"two={ROOT}"])
    rerender.main()
    rows = json.loads(output.read_text())["results"]
    assert [row["code"] for row in rows] == ["one", "two"]
    for row in rows:
        assert row["run"] == str(tiny_run) and row["repeats"] == 1
        assert row["render_ms_median"] > 0 and row["deformation_ms"] >= 0


@pytest.mark.slow
def test_threads_reach_each_evaluation(
    tiny_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    output = tmp_path / "rerender.json"
    argv = ["rerender.py", str(tiny_run), "--repeats", "1", "--output", str(output)]
    monkeypatch.setattr(sys, "argv", [*argv, "--threads", "1"])
    rerender.main()
    result = json.loads(output.read_text())
    assert result["machine"]["threads"] == 1
    assert [row["cpu_threads"] for row in result["results"]] == [1]
    monkeypatch.setattr(sys, "argv", [*argv, "--threads", "0"])
    with pytest.raises(SystemExit, match="--threads must be ≥ 1"):
        rerender.main()


def test_machine_info_names_the_processor_and_the_threads() -> None:
    info = machine_info(3)
    assert info["threads"] == 3 and info["processor"] and info["torch"] and info["platform"]
    assert machine_info()["threads"] == torch.get_num_threads()
    assert info["cpu_capability"] == torch.backends.cpu.get_cpu_capability()


def test_the_cpu_model_is_read_from_cpuinfo(tmp_path: Path) -> None:
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(
        "processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 26\nmodel\t\t: 2\n"
        "model name\t: AMD EPYC\n\nprocessor\t: 1\ncpu family\t: 25\nmodel\t\t: 1\n"
    )
    assert cpu_model(cpuinfo) == "AMD EPYC, family 26 model 2"  # the first CPU's
    assert cpu_model(tmp_path / "missing") == ""
