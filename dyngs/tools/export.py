"""`dyngs-export`: the deformed Gaussians at one time as a PLY that 3DGS viewers read,
e.g. `dyngs-export --load-dir outputs/RUN --time 0.5` (or `--all-times`).

The vertex layout is the one 3D Gaussian Splatting writes (Kerbl et al. 2023) and its
viewers expect: x y z, nx ny nz (zeros), f_dc_0..2, f_rest_0..3·(K−1)−1 stored
channel-major (every higher coefficient of red, then green, then blue), opacity (logit),
scale_0..2 (log standard deviations), rot_0..3 (unit quaternion w, x, y, z), all float32
binary little endian.

Letters: N Gaussians, K SH coefficients per channel.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import tyro
from jaxtyping import Float
from rich.console import Console
from rich.progress import Progress
from torch import Tensor

from dyngs.errors import ConfigError, DatasetError
from dyngs.geometry import normalize_quaternion
from dyngs.model import DRAWN_PARAMS, smooth_3d
from dyngs.ply import read_ply, write_ply
from dyngs.runs import LoadedRun, RunOverrides, load_run
from dyngs.sh import num_sh_bases
from dyngs.tools.common import run_tool

NORMALS = ("nx", "ny", "nz")


def _rest_names(rest: int) -> list[str]:
    return [f"f_rest_{i}" for i in range(3 * rest)]


def write_gaussians_ply(path: Path | str, raw: dict[str, Tensor]) -> None:
    """Write raw Gaussians (keys of `dyngs.model.DRAWN_PARAMS`: means [N,3], quats
    [N,4], log_scales [N,3], opacity_logits [N], sh_dc [N,1,3], sh_rest [N,K−1,3]) in
    the 3DGS vertex layout. Values are stored as given (float32)."""
    means = raw["means"].detach().float().cpu().numpy()
    n = len(means)
    columns: dict[str, np.ndarray] = {}
    for i, axis in enumerate("xyz"):
        columns[axis] = means[:, i]
    for name in NORMALS:
        columns[name] = np.zeros(n, dtype=np.float32)
    dc = raw["sh_dc"].detach().float().cpu().reshape(n, 3).numpy()
    for c in range(3):
        columns[f"f_dc_{c}"] = dc[:, c]
    # [N, K−1, 3] → [N, 3, K−1] → flat: channel-major, as 3DGS stores features_rest.
    rest = raw["sh_rest"].detach().float().cpu().transpose(1, 2).reshape(n, -1).numpy()
    for i, name in enumerate(_rest_names(rest.shape[1] // 3)):
        columns[name] = rest[:, i]
    columns["opacity"] = raw["opacity_logits"].detach().float().cpu().reshape(n).numpy()
    scales = raw["log_scales"].detach().float().cpu().numpy()
    for i in range(3):
        columns[f"scale_{i}"] = scales[:, i]
    quats = raw["quats"].detach().float().cpu().numpy()
    for i in range(4):
        columns[f"rot_{i}"] = quats[:, i]
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_ply(path, columns)


def read_gaussians_ply(path: Path | str) -> dict[str, Tensor]:
    """Read a 3DGS-layout PLY back into raw tensors (the keys `write_gaussians_ply` takes).

    Accepts any SH degree 0–3 (inferred from the number of f_rest properties).
    """
    columns = read_ply(path)
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    required += [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    missing = [name for name in required if name not in columns]
    if missing:
        raise DatasetError(f"{path}: not a 3DGS Gaussian PLY (no {', '.join(missing)})")
    rest_count = sum(1 for name in columns if name.startswith("f_rest_"))
    if rest_count % 3 or (rest_count // 3 + 1) not in (1, 4, 9, 16):
        raise DatasetError(f"{path}: {rest_count} f_rest properties is not an SH degree 0–3")
    rest = rest_count // 3

    def stack(names: Sequence[str]) -> Tensor:
        return torch.from_numpy(np.stack([columns[n].astype(np.float32) for n in names], 1))

    n = len(columns["x"])
    sh_rest = stack(_rest_names(rest)) if rest else torch.zeros(n, 0)
    return {
        "means": stack(["x", "y", "z"]),
        "quats": stack([f"rot_{i}" for i in range(4)]),
        "log_scales": stack([f"scale_{i}" for i in range(3)]),
        "opacity_logits": stack(["opacity"]).reshape(n),
        "sh_dc": stack(["f_dc_0", "f_dc_1", "f_dc_2"]).reshape(n, 1, 3),
        "sh_rest": sh_rest.reshape(n, 3, rest).transpose(1, 2).contiguous(),
    }


def unit_quaternions(quats: Float[Tensor, "N 4"]) -> Float[Tensor, "N 4"]:
    """Normalised quaternions; a zero one (which the renderers draw unrotated) becomes the
    identity, so viewers that normalise again never divide by zero."""
    q = normalize_quaternion(quats)
    zero = q.abs().amax(dim=-1) == 0
    return torch.where(zero[:, None], q.new_tensor([1.0, 0.0, 0.0, 0.0]), q)


@torch.no_grad()
def export_raw(run: LoadedRun, t: float, sh_degree: int | None = None) -> dict[str, Tensor]:
    """The run's Gaussians at time t as raw 3DGS values (deformed when the run deforms).

    Coefficients above the SH degree the run was drawing with are written as zeros, so a
    viewer shows what dyngs renders; `sh_degree` (default: the model's full degree)
    sets how many coefficients the file holds.
    """
    if not 0.0 <= t <= 1.0:
        raise ConfigError(f"--time must be in [0, 1], got {t}")
    full = run.model.canonical.sh_degree
    degree = full if sh_degree is None else sh_degree
    if not 0 <= degree <= full:
        raise ConfigError(f"--sh-degree must be in 0..{full} for this run, got {degree}")
    every = run.model.raw_at(t)
    raw = {k: every[k].detach().clone() for k in DRAWN_PARAMS}
    # Fold what `at` applies after activation into the raw values, as drawn: temporal
    # opacity (a snapshot) and the 3D filter. Rows neither touches keep their exact values.
    canonical, model = run.model.canonical, run.model
    logits, log_scales = raw["opacity_logits"], raw["log_scales"]
    opacity = torch.sigmoid(logits.double())
    folded = torch.zeros_like(logits, dtype=torch.bool)
    if bool(canonical.temporal().any()):
        presence = canonical.temporal_factor(t).double()
        opacity = opacity * presence
        folded |= presence < 1
    if model.filtered:
        std = model.filter_std.double()
        scales, opacity = smooth_3d(log_scales.double().exp(), opacity, std)
        widened = std > 0
        as_logs = scales.log().to(log_scales.dtype)
        raw["log_scales"] = torch.where(widened[:, None], as_logs, log_scales)
        folded |= widened
    as_logits = (opacity.log() - torch.log1p(-opacity)).to(logits.dtype)
    raw["opacity_logits"] = torch.where(folded, as_logits, logits)
    raw["quats"] = unit_quaternions(raw["quats"])
    rest = raw["sh_rest"][:, : num_sh_bases(degree) - 1]
    rest[:, max(num_sh_bases(run.model.active_sh_degree) - 1, 0) :] = 0.0
    raw["sh_rest"] = rest
    return raw


@dataclass(frozen=True)
class ExportConfig:
    """Export the Gaussians of a trained run at one time (or every training time) as PLY."""

    load_dir: Path
    """Run folder written by dyngs-train."""
    time: float | None = None
    """Time in [0, 1] to export the deformed Gaussians at."""
    all_times: bool = False
    """Write one PLY per distinct training timestamp instead (into OUTPUT as a folder)."""
    output: Path | None = None
    """PLY file (default: LOAD_DIR/export/gaussians_t<T>.ply).
    With --all-times, a folder (default: LOAD_DIR/export/all_times/)."""
    sh_degree: int | None = None
    """SH degree of the file (default: the model's; 3DGS viewers expect 3)."""
    run: Annotated[RunOverrides, tyro.conf.OmitArgPrefixes] = field(default_factory=RunOverrides)

    def __post_init__(self) -> None:
        if self.all_times == (self.time is not None):
            raise ConfigError("give either --time T or --all-times (exactly one)")


def run_export(config: ExportConfig, console: Console | None = None) -> list[Path]:
    """Write the PLY file(s); returns their paths."""
    console = console or Console()
    run = load_run(config.load_dir, overrides=config.run)
    export = run.run_dir / "export"
    written: list[Path] = []
    if config.time is not None:
        path = config.output or export / f"gaussians_t{config.time:.4f}.ply"
        write_gaussians_ply(path, export_raw(run, config.time, config.sh_degree))
        written.append(path)
    else:
        folder = config.output or export / "all_times"
        times = sorted({float(t) for t in run.scene.train.times.tolist()})
        with Progress(console=console, transient=True) as progress:
            task = progress.add_task("export", total=len(times))
            for i, t in enumerate(times):
                path = folder / f"gaussians_{i:04d}_t{t:.4f}.ply"
                write_gaussians_ply(path, export_raw(run, t, config.sh_degree))
                written.append(path)
                progress.advance(task)
    where = written[0] if len(written) == 1 else f"{len(written)} files in {written[0].parent}"
    console.print(f"wrote {len(run.model.canonical):,} Gaussians: {where}")
    return written


def main(argv: Sequence[str] | None = None) -> None:
    def body(console: Console) -> None:
        config = tyro.cli(ExportConfig, args=argv, prog="dyngs-export", description=__doc__)
        run_export(config, console)

    run_tool(body)


if __name__ == "__main__":
    main()
