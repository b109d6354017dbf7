"""dyngs-export: the 3DGS PLY layout, an exact write/read round trip, and exports that
equal what the model draws at that time."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from dyngs.cli import main as cli_main
from dyngs.model import DRAWN_PARAMS, GAUSSIAN_PARAMS, activate
from dyngs.ply import read_ply
from dyngs.runs import load_run
from dyngs.tools.export import export_raw, main, read_gaussians_ply, write_gaussians_ply
from tests.engine.helpers import TINY_SCENE, output_layer
from tests.tools.conftest import TINY_FLAGS


def _random_raw(n: int, rest: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    shapes = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,),
              "sh_dc": (n, 1, 3), "sh_rest": (n, rest, 3)}  # fmt: skip
    return {k: torch.randn(*s, generator=g) for k, s in shapes.items()}


@pytest.mark.parametrize("rest", [0, 3, 8, 15])
def test_round_trip_is_exact(rest: int, tmp_path: Path) -> None:
    raw = _random_raw(17, rest)
    write_gaussians_ply(tmp_path / "g.ply", raw)
    back = read_gaussians_ply(tmp_path / "g.ply")
    assert set(back) == set(DRAWN_PARAMS)
    for name in DRAWN_PARAMS:
        assert back[name].dtype == torch.float32 and torch.equal(back[name], raw[name]), name


def test_layout_is_that_of_3dgs(tmp_path: Path) -> None:
    raw = _random_raw(4, 15)
    # Coefficient k of channel c gets a value that names it, to check the channel-major order.
    for k in range(15):
        for c in range(3):
            raw["sh_rest"][:, k, c] = 100 * c + k
    write_gaussians_ply(tmp_path / "g.ply", raw)
    header = (tmp_path / "g.ply").read_bytes().split(b"end_header\n")[0].decode().splitlines()
    assert header[1] == "format binary_little_endian 1.0" and header[2] == "element vertex 4"
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(45)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert header[3:] == [f"property float {n}" for n in names]
    columns = read_ply(tmp_path / "g.ply")
    for c in range(3):
        for k in range(15):
            assert columns[f"f_rest_{c * 15 + k}"][0] == 100 * c + k
    assert (columns["nx"] == 0).all() and torch.equal(
        torch.from_numpy(columns["rot_0"]), raw["quats"][:, 0]
    )


def test_raw_at_is_what_at_draws(tiny_run: Path) -> None:
    run = load_run(tiny_run)
    model = run.model
    model.dynamic[:] = True  # the tiny run learned no motion: make every Gaussian deform
    with torch.no_grad():
        for branch in ("means", "quats", "scales"):
            layer = output_layer(model.head, branch)
            if layer is not None:
                layer.bias.uniform_(-0.1, 0.1)  # a visible deformation
    raw = model.raw_at(0.4)
    assert not torch.equal(raw["means"], model.canonical.means)
    sh = torch.cat((raw["sh_dc"], raw["sh_rest"]), 1)
    expected = activate(raw["means"], raw["quats"], raw["log_scales"], raw["opacity_logits"], sh, 0)
    drawn = model.at(0.4, sh_degree=0)
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.equal(getattr(drawn, name), getattr(expected, name)), name
    still = model.raw_at(0.4, deform=False)
    assert all(torch.equal(still[k], getattr(model.canonical, k)) for k in GAUSSIAN_PARAMS)


def test_export_at_time_matches_the_model(tiny_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "t.ply"
    main(["--load-dir", str(tiny_run), "--time", "0.25", "--output", str(out)])
    back = read_gaussians_ply(out)
    run = load_run(tiny_run)
    expected = export_raw(run, 0.25)
    for name in DRAWN_PARAMS:
        assert torch.equal(back[name], expected[name].float()), name
    drawn = run.model.at(0.25)
    assert torch.equal(back["means"], drawn.means)
    assert torch.allclose(back["log_scales"].exp(), drawn.scales)
    assert torch.allclose(torch.sigmoid(back["opacity_logits"]), drawn.opacities)
    assert torch.allclose(back["quats"].norm(dim=1), torch.ones(len(back["quats"])))
    assert back["sh_rest"].shape[1] == 15  # the model's full degree, 3, as viewers expect


def test_an_export_holds_the_gaussians_as_drawn_through_the_3d_filter(
    tiny_data: Path, tmp_path: Path
) -> None:
    cli_main(
        ["hexplane-4dgs", "renderer:cpu-reference", "--data", str(tiny_data),
         "--output-dir", str(tmp_path), "--run-name", "run", "--max-iters", "12",
         "--densify.refine-every", "5", "--gaussians.filter-3d", "0.2", *TINY_FLAGS]
    )  # fmt: skip
    run = load_run(tmp_path / "run")
    assert run.model.filtered  # refreshed at step 5 (not at 10: within the last interval)
    raw = export_raw(run, 0.5)
    drawn = run.model.at(0.5)
    torch.testing.assert_close(raw["log_scales"].exp(), drawn.scales, rtol=1e-6, atol=0)
    torch.testing.assert_close(torch.sigmoid(raw["opacity_logits"]), drawn.opacities,
                               rtol=1e-5, atol=1e-8)  # fmt: skip
    plain = export_raw(run, 0.5)
    run.model.filter_std.zero_()
    unfiltered = export_raw(run, 0.5)
    assert bool((plain["log_scales"] > unfiltered["log_scales"]).all())


def test_unused_sh_coefficients_are_zero(tiny_run: Path) -> None:
    run = load_run(tiny_run)
    assert run.model.active_sh_degree == 0  # three steps: only the DC term is active
    with torch.no_grad():
        run.model.canonical.sh_rest.fill_(0.5)
    raw = export_raw(run, 0.5, sh_degree=1)
    assert raw["sh_rest"].shape[1] == 3 and bool((raw["sh_rest"] == 0).all())


def test_all_times_writes_one_file_per_timestamp(tiny_run: Path, tmp_path: Path) -> None:
    main(["--load-dir", str(tiny_run), "--all-times", "--output", str(tmp_path / "all")])
    files = sorted((tmp_path / "all").glob("*.ply"))
    assert len(files) == TINY_SCENE.num_times
    assert files[0].name == "gaussians_0000_t0.0000.ply" and files[-1].name.endswith("t1.0000.ply")


@pytest.mark.parametrize(
    "args",
    [[], ["--time", "0.5", "--all-times"], ["--time", "1.5"], ["--time", "0", "--sh-degree", "4"]],
)
def test_bad_requests_are_one_line(
    args: list[str], tiny_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--load-dir", str(tiny_run), "--output", str(tmp_path / "x.ply"), *args])
    assert exit_info.value.code == 2
    out = capsys.readouterr().out.strip()
    assert out.startswith("error:") and "\n" not in out
