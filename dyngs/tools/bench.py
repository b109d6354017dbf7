"""`dyngs-bench`: train and evaluate a sweep of configs, then compare speed and error.

    dyngs-bench --data PATH --sweep tradeoffs
    dyngs-bench --data PATH --grid max-iters=500,1000 field=hexplane,mlp
    dyngs-bench --data PATH --sweep my-sweep.toml -- --downscale 8 --max-iters 1000

A sweep is a list of points. Each point is a set of dyngs-train flags added to the
preset (--method) and to the flags every point shares (those after a bare `--`, or
--train-args="…"). Points come from a built-in sweep (SWEEPS), a TOML or JSON file,
and/or --grid axes `KEY=V1,V2,…`: KEY is a dyngs-train flag without its dashes,
`field` and `renderer` pick a component, `method` a preset; a value with spaces gives
several tokens, `true`/`false` a boolean flag.

Each point trains into OUTPUT/points/<name>/ and is evaluated there by dyngs-eval in a
fresh process (eval_<split>.json); a point whose results exist is skipped, so running
the same command again resumes an interrupted sweep. Written to OUTPUT: results.csv,
results.json, results.png (PSNR against render time and against training time, Pareto
front marked) and TensorBoard HParams entries under tensorboard/.

A sweep file:

    method = "hexplane-4dgs"          # optional: the preset every point starts from
    train_args = "--max-iters 1000"   # optional: flags shared by every point
    [grid]                            # optional: every combination of these
    max-iters = [500, 1000]
    [[points]]                        # optional: these points (× the grid, if any)
    field = "mlp"
    [[points]]
    "field.resolution" = "32 32 32 12"
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import hashlib
import io
import itertools
import json
import math
import re
import shlex
import shutil
import statistics
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import tyro
from rich.console import Console
from rich.table import Table

from dyngs.config import TrainConfig
from dyngs.configio import load_config
from dyngs.engine.trainer import CHECKPOINT_NAME
from dyngs.errors import ConfigError, UserError
from dyngs.fields.hexplane import DEFAULT_RESOLUTION, HexPlaneConfig
from dyngs.fields.mlp import MLPFieldConfig
from dyngs.io import write_json
from dyngs.renderers import renderer_name
from dyngs.runs import parse_train_args, run_training
from dyngs.tools.common import run_tool
from dyngs.tools.paired import paired_change

SUBCOMMAND_KEYS = ("field", "renderer")
"""Grid keys that choose a component: `field=mlp` becomes the subcommand `field:mlp`."""


@dataclass(frozen=True)
class Sweep:
    """Points as flag sets: every explicit point combined with every grid combination."""

    grid: dict[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)
    points: tuple[dict[str, str], ...] = ()
    method: str | None = None
    train_args: str = ""

    def expand(self) -> list[dict[str, str]]:
        bases = list(self.points) or [{}]
        axes = [[(key, value) for value in values] for key, values in self.grid.items()]
        combos = [dict(c) for c in itertools.product(*axes)]
        return [base | combo for base in bases for combo in combos]


SWEEPS: dict[str, Sweep] = {
    "iterations": Sweep(grid={"max-iters": ("250", "500", "1000", "2000", "3000")}),
    "budget": Sweep(grid={"densify.max-gaussians": ("2000", "5000", "20000", "300000")}),
    "sh": Sweep(grid={"gaussians.sh-degree": ("0", "1", "3")}),
    "fields": Sweep(
        points=(
            {},
            {"field.resolution": "32 32 32 12", "field.multires": "1"},
            {"field": "mlp"},
        )
    ),
    "renderers": Sweep(grid={"renderer": ("cpu-reference", "cuda-tile")}),
    "tradeoffs": Sweep(
        points=(
            {},
            {"max-iters": "500"},
            {"densify.max-gaussians": "5000"},
            {"field.resolution": "32 32 32 12", "field.multires": "1"},
            {"field": "mlp"},
            {"gaussians.sh-degree": "0"},
        )
    ),
    "adaptive": Sweep(
        points=(
            {
                "motion.separate": "false",
                "densify.max-gaussians": "3000000",
                "densify.prune-importance": "0",
                "gaussians.sh-evidence": "0",
            },
            {},
        )
    ),
}
"""Built-in sweeps (`--sweep NAME`). `tradeoffs` changes one thing at a time from the
preset (with --train-args applied to every point); `adaptive` compares the preset with
everything dynamic, no Gaussian budget and the SH schedule of 3DGS (first, so that --seeds
gives the preset's change from it); the others sweep one axis."""


@dataclass(frozen=True)
class BenchConfig:
    """Train, evaluate and compare a sweep of configs (speed against error)."""

    data: str = "demo"
    """Dataset folder, or `demo` for the built-in scene."""
    output_dir: Path = Path("outputs/bench")
    """Points go to OUTPUT_DIR/points/<name>/; results.{csv,json,png} to OUTPUT_DIR."""
    sweep: str | None = None
    """A built-in sweep (iterations, budget, sh, fields, renderers, tradeoffs, adaptive), or a
    sweep file (.toml or .json, format above)."""
    grid: tuple[str, ...] = ()
    """Axes KEY=V1,V2,… added to the sweep, e.g. `max-iters=500,1000 field=hexplane,mlp`."""
    method: str | None = None
    """Preset every point starts from (default: the sweep file's, else hexplane-4dgs)."""
    train_args: str = ""
    """dyngs-train flags shared by every point, as one string (`@FILE` works too).
    Write --train-args="--max-iters 500" (with the `=`), or put the flags after a bare `--`."""
    split: Literal["test", "val", "train"] = "test"
    """Split every point is evaluated on."""
    warmup: int = 3
    """Untimed renders before the timed ones in each evaluation."""
    save_images: bool = False
    """Save each point's evaluation images (render | ground truth)."""
    seeds: tuple[int, ...] = ()
    """Train every point once per seed (a `seed` axis). The results then add each point's
    mean and spread over the seeds, and its difference from the first point paired by
    seed (seeds.csv, results.json). One run cannot resolve a fraction of a dB: a seed
    alone moves a scene's PSNR by more than that."""


@dataclass(frozen=True)
class BenchPoint:
    name: str
    label: str
    """The point's own flags, e.g. `max-iters=500, field=mlp` (`preset` when none)."""
    params: dict[str, str]
    args: tuple[str, ...]
    config: TrainConfig


def parse_grid_axis(text: str) -> tuple[str, tuple[str, ...]]:
    key, sep, values = text.partition("=")
    key = key.strip().removeprefix("--").replace("_", "-")
    items = tuple(v.strip() for v in values.split(","))
    if not sep or not key or not all(items):
        raise ConfigError(f"--grid {text!r}: write axes as KEY=VALUE1,VALUE2,…")
    return key, items


def _value_text(value: object, where: str) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float, str)):
        return str(value)
    if isinstance(value, list) and all(isinstance(v, (int, float, str)) for v in value):
        return " ".join(str(v) for v in value)
    raise ConfigError(f"{where}: values must be numbers, strings or lists of them, got {value!r}")


def _flags_table(table: object, where: str) -> dict[str, str]:
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: expected a table of KEY = VALUE")
    return {
        str(k).removeprefix("--").replace("_", "-"): _value_text(v, f"{where}.{k}")
        for k, v in table.items()
    }


def load_sweep_file(path: Path) -> Sweep:
    """A sweep from a TOML or JSON file (keys: method, train_args, grid, points)."""
    try:
        text = path.read_text()
    except OSError as error:
        raise ConfigError(f"{path}: cannot read sweep file ({error.strerror})") from None
    try:
        if path.suffix == ".json":
            data = json.loads(text)
        else:
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                raise ConfigError(
                    f"{path}: TOML sweep files need Python ≥ 3.11; use JSON"
                ) from None
            data = tomllib.loads(text)
    except ValueError as error:  # JSONDecodeError and TOMLDecodeError both are
        raise ConfigError(f"{path}: malformed sweep file ({error})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a sweep file holds a table (method, train_args, grid, points)")
    unknown = set(data) - {"method", "train_args", "grid", "points"}
    if unknown:
        raise ConfigError(f"{path}: unknown sweep keys {sorted(unknown)}")
    grid: dict[str, tuple[str, ...]] = {}
    raw_grid = data.get("grid", {})
    if not isinstance(raw_grid, dict):
        raise ConfigError(f"{path}: grid must be a table of KEY = [VALUES]")
    for key, values in raw_grid.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{path}: grid.{key} must be a non-empty list")
        grid[str(key).replace("_", "-")] = tuple(
            _value_text(v, f"{path}: grid.{key}") for v in values
        )
    raw_points = data.get("points", [])
    if not isinstance(raw_points, list):
        raise ConfigError(f"{path}: points must be a list of tables")
    points = tuple(_flags_table(p, f"{path}: points[{i}]") for i, p in enumerate(raw_points))
    method = data.get("method")
    train_args = data.get("train_args", "")
    if not (method is None or isinstance(method, str)) or not isinstance(train_args, str):
        raise ConfigError(f"{path}: method and train_args must be strings")
    return Sweep(grid=grid, points=points, method=method, train_args=train_args)


def resolve_sweep(config: BenchConfig) -> Sweep:
    sweep = Sweep()
    if config.sweep is not None:
        if config.sweep in SWEEPS:
            sweep = SWEEPS[config.sweep]
        elif Path(config.sweep).suffix in (".toml", ".json"):
            sweep = load_sweep_file(Path(config.sweep))
        else:
            raise ConfigError(
                f"--sweep {config.sweep!r}: not a built-in sweep ({', '.join(SWEEPS)}) "
                "nor a .toml/.json file"
            )
    grid = dict(sweep.grid)
    for axis in config.grid:
        key, values = parse_grid_axis(axis)
        grid[key] = values
    if config.seeds:
        if "seed" in grid or any("seed" in point for point in sweep.points):
            raise ConfigError("--seeds: the sweep already sets `seed`; give the seeds once")
        if len(set(config.seeds)) != len(config.seeds):
            raise ConfigError(f"--seeds {' '.join(map(str, config.seeds))}: a seed repeats")
        grid["seed"] = tuple(str(seed) for seed in config.seeds)
    return dataclasses.replace(
        sweep,
        grid=grid,
        method=config.method or sweep.method or "hexplane-4dgs",
        train_args=f"{sweep.train_args} {config.train_args}".strip(),
    )


def point_tokens(params: dict[str, str]) -> tuple[str | None, list[str], list[str]]:
    """(preset, component subcommands, flags) that dyngs-train takes for a point."""
    method: str | None = None
    subcommands: list[str] = []
    flags: list[str] = []
    for key, value in params.items():
        if key == "method":
            method = value
        elif key in SUBCOMMAND_KEYS:
            subcommands.append(f"{key}:{value}")
        elif value.lower() in ("true", "false"):
            prefix, dot, last = key.rpartition(".")
            flags.append(f"--{key}" if value.lower() == "true" else f"--{prefix}{dot}no-{last}")
        else:
            flags += [f"--{key}", *value.split()]
    return method, subcommands, flags


def _label(params: dict[str, str]) -> str:
    """A point's own flags as `key=value, …` (`preset` when it has none)."""
    return ", ".join(f"{k}={v}" for k, v in params.items()) or "preset"


def _slug(params: dict[str, str]) -> str:
    text = "_".join(f"{k}-{v}" for k, v in params.items()) or "preset"
    return re.sub(r"[^A-Za-z0-9.=-]+", "-", text.replace(" ", "-"))[:80].strip("-")


def _parse_quietly(args: list[str], label: str) -> TrainConfig:
    """dyngs-train's parser; its multi-line error box becomes a one-line ConfigError."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured), contextlib.redirect_stderr(captured):
            return parse_train_args(args)
    except SystemExit:
        # tyro's box: a title, a rule, then the problem until the next rule or blank line.
        lines = [line.strip() for line in captured.getvalue().splitlines()]
        rules = [i for i, line in enumerate(lines) if line and set(line) <= set("-─━")]
        body: list[str] = []
        for line in lines[rules[0] + 1 if rules else 0 :]:
            if not line or set(line) <= set("-─━"):
                break
            body.append(re.sub(r"\s*\(applied to [^)]*\)", "", line))
        reason = " ".join(body[:2]) or "rejected"
        raise ConfigError(
            f"sweep point {label}: dyngs-train rejects `{shlex.join(args)}` ({reason})"
        ) from None


def plan_points(config: BenchConfig, sweep: Sweep) -> list[BenchPoint]:
    """Every point's name and resolved training config (all parsed before any trains)."""
    data = config.data if config.data == "demo" else str(Path(config.data).resolve())
    points_dir = config.output_dir / "points"
    planned: list[BenchPoint] = []
    for params in sweep.expand():
        label = _label(params)
        preset, subcommands, flags = point_tokens(params)
        method = preset or sweep.method or "hexplane-4dgs"
        args = [method, *subcommands, *shlex.split(sweep.train_args), *flags]
        digest = hashlib.sha1("\0".join([*args, data]).encode(), usedforsecurity=False).hexdigest()[
            :8
        ]
        name = f"{_slug(params)}_{digest}"
        # Set after parsing rather than as flags: --data may also come in the shared
        # flags (configs/*.args hold one), and --data here wins.
        train = dataclasses.replace(
            _parse_quietly(args, label), data=data, output_dir=points_dir, run_name=name
        )
        planned.append(BenchPoint(name, label, params, tuple(args), train))
    names = [p.name for p in planned]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise ConfigError(f"the sweep repeats points: {', '.join(duplicates)}")
    return planned


def run_point(point: BenchPoint, config: BenchConfig, console: Console) -> str:
    """Train (or resume) and evaluate one point unless done; says which it did."""
    run_dir = config.output_dir / "points" / point.name
    eval_path = run_dir / f"eval_{config.split}.json"
    status = "skipped"
    if not (run_dir / "metrics.json").is_file():
        if (run_dir / CHECKPOINT_NAME).is_file() and (run_dir / "config.json").is_file():
            run_training(load_config(run_dir / "config.json"), run_dir, console, resume=True)
            status = "resumed"
        else:
            run_dir.mkdir(parents=True, exist_ok=True)
            run_training(point.config, run_dir, console)
            status = "trained"
        eval_path.unlink(missing_ok=True)  # a new checkpoint makes an old evaluation stale
    if not eval_path.is_file():
        evaluate_in_subprocess(run_dir, eval_path, config)
        status = status if status != "skipped" else "evaluated"
    return status


def evaluate_in_subprocess(run_dir: Path, output: Path, config: BenchConfig) -> None:
    """`dyngs-eval` on a point in a fresh process, so that its peak memory and render
    times are its own rather than left over from the training and points before it."""
    command = [
        sys.executable, "-m", "dyngs.tools.eval", "--load-dir", str(run_dir),
        "--split", config.split, "--warmup", str(config.warmup), "--output", str(output),
        "--save-images" if config.save_images else "--no-save-images",
    ]  # fmt: skip
    code = subprocess.run(command, check=False).returncode
    if code != 0:
        raise UserError(f"{run_dir}: evaluation failed (dyngs-eval exited with {code})")


def _describe(config: TrainConfig) -> dict[str, Any]:
    """What identifies a point's config in the table, the CSV and TensorBoard."""
    field = config.field
    if isinstance(field, HexPlaneConfig):
        field_name = "hexplane"
        resolution = "x".join(str(r) for r in field.resolution or DEFAULT_RESOLUTION)
        resolution += "" if field.multires == (1,) else f"@{'/'.join(map(str, field.multires))}"
    else:
        field_name = "mlp" if isinstance(field, MLPFieldConfig) else type(field).__name__
        resolution = ""
    return {
        "method": config.method,
        "field": field_name,
        "hexplane_resolution": resolution,
        "renderer": renderer_name(config.renderer),
        "max_iters": config.max_iters,
        "max_sh_degree": config.gaussians.sh_degree,
        "max_gaussians": config.densify.max_gaussians,
    }


RESULT_KEYS = (
    "psnr",
    "ssim",
    "lpips",
    "render_ms_median",
    "render_ms_p95",
    "deformation_ms",
    "train_seconds",
    "num_gaussians",
    "sh_degree",
    "dynamic_fraction",
    "model_bytes",
    "peak_memory_mb",
    "iterations",
    "device",
)


def collect(point: BenchPoint, config: BenchConfig, swept: Sequence[str]) -> dict[str, Any]:
    """One results row; `swept` lists every key the sweep sets (a point that leaves one
    at the preset's value shows `default`, so every row has the same columns)."""
    run_dir = config.output_dir / "points" / point.name
    evaluation = json.loads((run_dir / f"eval_{config.split}.json").read_text())
    row: dict[str, Any] = {"name": point.name, "label": point.label}
    row |= {f"param:{k}": point.params.get(k, "default") for k in swept}
    row |= _describe(load_config(run_dir / "config.json"))
    row |= {key: evaluation.get(key) for key in RESULT_KEYS}
    row["run_dir"] = str(run_dir)
    row["command"] = shlex.join(["dyngs-train", *point.args, "--data", point.config.data])
    return row


def pareto_front(costs: Sequence[float], scores: Sequence[float]) -> list[int]:
    """Indices of the points no other point beats (score at least as high and cost at most
    as low, one of them strictly), in increasing cost."""
    order = sorted(range(len(costs)), key=lambda i: (costs[i], -scores[i]))
    front: list[int] = []
    best = -math.inf
    for i in order:
        if scores[i] > best:
            front.append(i)
            best = scores[i]
    return front


MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*", "<", ">", "h", "p")


def _log_scale_when_wide(ax: Any, values: list[float]) -> None:
    """A logarithmic x axis, labelled 1, 2, 5, 10, 20, … (not 2×10⁰), when the values span
    more than a factor of 20."""
    from matplotlib import ticker

    if values and min(values) > 0 and max(values) / min(values) > 20:
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(ticker.LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(ticker.NullFormatter())


def plot_results(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    """Two panels, PSNR against median render time and against training time; one marker
    per point (legend), the Pareto front (higher PSNR, lower cost) joined and ringed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (
        ("render_ms_median", "render time per frame, median (ms)"),
        ("train_seconds", "training time (s)"),
    )
    colors = plt.get_cmap("tab20" if len(rows) > 10 else "tab10")
    figure, axes = plt.subplots(1, 2, figsize=(13, 5.2), dpi=120)
    handles: dict[str, Any] = {}
    for ax, (key, xlabel) in zip(axes, panels, strict=True):
        usable = [i for i, r in enumerate(rows) if r["psnr"] is not None and r[key] is not None]
        for i in usable:
            handles[rows[i]["label"]] = ax.scatter(
                rows[i][key],
                rows[i]["psnr"],
                marker=MARKERS[i % len(MARKERS)],
                color=colors(i % colors.N),
                s=60,
                zorder=3,
                label=rows[i]["label"],
            )
        front = [
            usable[j]
            for j in pareto_front([rows[i][key] for i in usable], [rows[i]["psnr"] for i in usable])
        ]
        if front:
            xs = [rows[i][key] for i in front]
            ys = [rows[i]["psnr"] for i in front]
            handles["Pareto front (ringed)"] = ax.plot(
                xs, ys, "-", color="crimson", linewidth=1.5, zorder=2, label="Pareto front (ringed)"
            )[0]
            ax.scatter(xs, ys, s=220, facecolors="none", edgecolors="crimson", linewidths=1.8,
                       zorder=4)  # fmt: skip
        _log_scale_when_wide(ax, [rows[i][key] for i in usable])
        ax.set_xlabel(xlabel)
        ax.set_ylabel("PSNR (dB)")
        ax.grid(True, alpha=0.3)
    figure.suptitle(title)
    figure.legend(
        list(handles.values()),
        list(handles),
        loc="center left",
        bbox_to_anchor=(0.79, 0.5),
        fontsize="small",
        frameon=False,
        title="one marker per run",
    )
    figure.tight_layout(rect=(0, 0, 0.79, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)


def _number(text: str) -> int | float | str:
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def write_hparams(rows: list[dict[str, Any]], log_dir: Path) -> None:
    """One TensorBoard run per point under `log_dir` with its HParams entry (written
    afresh each time, so re-running never duplicates one)."""
    from torch.utils.tensorboard import SummaryWriter
    from torch.utils.tensorboard.summary import hparams

    keys = ("psnr", "ssim", "lpips", "render_ms_median", "train_seconds", "num_gaussians",
            "peak_memory_mb")  # fmt: skip
    for row in rows:
        folder = log_dir / row["name"]
        shutil.rmtree(folder, ignore_errors=True)
        params: dict[str, Any] = {}
        for k, v in row.items():
            if k in RESULT_KEYS or k in ("name", "run_dir", "status", "command"):
                continue
            params[k] = _number(v) if isinstance(v, str) else v if v is not None else "null"
        metrics = {f"bench/{k}": float(row[k]) for k in keys if row.get(k) is not None}
        experiment, start, end = hparams(params, metrics)
        with SummaryWriter(str(folder)) as writer:
            file_writer = writer._get_file_writer()
            for summary in (experiment, start, end):
                file_writer.add_summary(summary)
            for tag, value in metrics.items():
                writer.add_scalar(tag, value)


def write_csv(rows: list[dict[str, Any]], path: Path) -> None:
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in columns})
    path.write_text(buffer.getvalue())


def results_table(rows: list[dict[str, Any]], front: set[int], title: str) -> Table:
    table = Table(title=title)
    columns = (
        ("point", "label", None),
        ("PSNR dB", "psnr", 2),
        ("SSIM", "ssim", 3),
        ("LPIPS", "lpips", 3),
        ("render ms", "render_ms_median", 1),
        ("train s", "train_seconds", 1),
        ("Gaussians", "num_gaussians", None),
        ("dynamic", "dynamic_fraction", 2),
        ("model bytes", "model_bytes", None),
    )
    for header, _, _ in columns:
        if header == "point":
            table.add_column(header, max_width=36, overflow="fold")
        else:
            table.add_column(header, justify="right")
    for i, row in enumerate(rows):
        cells = []
        for _, key, digits in columns:
            value = row.get(key)
            cells.append(
                "null" if value is None else f"{value:.{digits}f}" if digits else str(value)
            )
        table.add_row(*cells, style="bold" if i in front else None)
    return table


SEED_QUALITY = ("psnr", "ssim", "lpips")
"""Compared with the first point as a difference, seed by seed."""
SEED_COST = ("render_ms_median", "deformation_ms", "num_gaussians", "model_bytes", "train_seconds")
"""Compared with the first point as a relative change, seed by seed."""
SEED_OTHER = ("dynamic_fraction",)


def _spread(values: Sequence[float]) -> dict[str, float | None]:
    """Mean, sample standard deviation (None for one value), min and max."""
    std = statistics.stdev(values) if len(values) > 1 else None
    return {"mean": statistics.mean(values), "std": std, "min": min(values), "max": max(values)}


def summarize_seeds(
    rows: Sequence[dict[str, Any]], points: Sequence[BenchPoint]
) -> list[dict[str, Any]]:
    """One entry per point of the sweep without its seed: each metric's spread over the
    seeds, and its change from the first such point, paired by seed (a difference for
    PSNR, SSIM and LPIPS; a relative change, 0.1 = 10 % more, for the costs). Pairing
    removes what a seed does to both points alike (its initial cloud, its view order)."""
    groups: dict[str, dict[str, dict[str, Any]]] = {}
    for row, point in zip(rows, points, strict=True):
        label = _label({k: v for k, v in point.params.items() if k != "seed"})
        groups.setdefault(label, {})[point.params["seed"]] = row
    reference_label, reference = next(iter(groups.items()))
    summary: list[dict[str, Any]] = []
    for label, by_seed in groups.items():
        entry: dict[str, Any] = {"point": label, "seeds": [int(s) for s in by_seed]}
        for key in (*SEED_QUALITY, *SEED_COST, *SEED_OTHER):
            values = [r[key] for r in by_seed.values() if r.get(key) is not None]
            entry[key] = _spread(values) if values else None
        if label != reference_label:
            entry["versus"] = reference_label
            for key in (*SEED_QUALITY, *SEED_COST):
                pairs = [
                    (row[key], reference[seed][key])
                    for seed, row in by_seed.items()
                    if seed in reference
                    and row.get(key) is not None
                    and reference[seed].get(key) is not None
                ]
                if key in SEED_QUALITY:
                    changes = [a - b for a, b in pairs]
                else:
                    changes = [a / b - 1 for a, b in pairs if b]
                entry[f"change:{key}"] = _spread(changes) if changes else None
                if changes and key in SEED_QUALITY:  # is it a change at all? (dyngs.tools.paired)
                    paired = paired_change([b for _, b in pairs], [a for a, _ in pairs])
                    entry[f"change:{key}"] |= {"stderr": paired.stderr, "p": paired.p}
        summary.append(entry)
    return summary


def _flatten(entry: dict[str, Any]) -> dict[str, Any]:
    flat: dict[str, Any] = {"point": entry["point"], "seeds": " ".join(map(str, entry["seeds"]))}
    for key, value in entry.items():
        if isinstance(value, dict):
            flat |= {f"{key}:{stat}": v for stat, v in value.items()}
        elif key not in flat:
            flat[key] = value
    return flat


def _plus_minus(spread: dict[str, float | None] | None, digits: int, signed: bool = False) -> str:
    """`mean ± std` (just the mean for one seed)."""
    if spread is None:
        return "null"
    mean, std = spread["mean"], spread["std"]
    text = f"{mean:{'+' if signed else ''}.{digits}f}"
    return text if std is None else f"{text} ± {std:.{digits}f}"


def _percent(spread: dict[str, float | None] | None) -> str:
    return "" if spread is None or spread["mean"] is None else f"{100 * spread['mean']:+.0f} %"


def seeds_table(summary: Sequence[dict[str, Any]], title: str) -> Table:
    table = Table(title=title)
    for header in ("point", "seeds", "PSNR dB", "Δ PSNR", "Δ PSNR min..max", "p", "SSIM",
                   "render ms", "Δ render", "model MiB", "Δ size", "dynamic"):  # fmt: skip
        table.add_column(header, justify="left" if header == "point" else "right",
                         max_width=36 if header == "point" else None, overflow="fold")  # fmt: skip
    for entry in summary:
        psnr_change = entry.get("change:psnr")
        size = entry["model_bytes"]
        table.add_row(
            entry["point"],
            str(len(entry["seeds"])),
            _plus_minus(entry["psnr"], 2),
            _plus_minus(psnr_change, 2, signed=True) if psnr_change else "",
            f"{psnr_change['min']:+.2f}..{psnr_change['max']:+.2f}" if psnr_change else "",
            f"{psnr_change['p']:.2g}" if psnr_change else "",
            _plus_minus(entry["ssim"], 3),
            _plus_minus(entry["render_ms_median"], 1),
            _percent(entry.get("change:render_ms_median")),
            f"{size['mean'] / 2**20:.2f}" if size else "null",
            _percent(entry.get("change:model_bytes")),
            _plus_minus(entry["dynamic_fraction"], 2),
        )
    return table


def run_bench(config: BenchConfig, console: Console | None = None) -> list[dict[str, Any]]:
    """Run the sweep (skipping finished points) and write every result file; returns rows."""
    console = console or Console()
    if config.warmup < 0:
        raise ConfigError(f"--warmup must be ≥ 0, got {config.warmup}")
    sweep = resolve_sweep(config)
    points = plan_points(config, sweep)
    statuses: dict[str, str] = {}
    for i, point in enumerate(points):
        console.rule(f"[{i + 1}/{len(points)}] {point.label}")
        statuses[point.name] = run_point(point, config, console)
        console.print(f"{point.name}: {statuses[point.name]}")
    swept = list(dict.fromkeys(k for p in points for k in p.params))
    rows = [collect(p, config, swept) | {"status": statuses[p.name]} for p in points]
    out = config.output_dir
    write_csv(rows, out / "results.csv")
    results: dict[str, Any] = {"data": config.data, "split": config.split, "rows": rows}
    summary = summarize_seeds(rows, points) if config.seeds else []
    if summary:
        results["seeds"] = summary
        write_csv([_flatten(entry) for entry in summary], out / "seeds.csv")
    write_json(out / "results.json", results)
    dataset = "demo" if config.data == "demo" else Path(config.data).resolve().name
    device = rows[0]["device"] if rows else "?"
    title = f"{dataset}: {config.split} split, {device}"
    plot_results(rows, out / "results.png", title)
    write_hparams(rows, out / "tensorboard")
    usable = [i for i, r in enumerate(rows) if r["psnr"] is not None]
    front = {
        usable[j]
        for j in pareto_front(
            [rows[i]["render_ms_median"] for i in usable], [rows[i]["psnr"] for i in usable]
        )
    }
    console.print(results_table(rows, front, f"{title} (bold: Pareto front in render time)"))
    if summary:
        heading = f"{title}: mean ± std over seeds {' '.join(map(str, config.seeds))}"
        console.print(
            seeds_table(summary, f"{heading}; Δ: against {summary[0]['point']}, paired by seed")
        )
    console.print(f"wrote {out / 'results.csv'}, results.json, results.png and tensorboard/")
    return rows


def main(argv: Sequence[str] | None = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)
    # Flags after a bare `--` go to every point's dyngs-train (argparse would take a
    # --train-args value that starts with a dash for a flag of its own).
    shared: list[str] = []
    if "--" in args:
        cut = args.index("--")
        args, shared = args[:cut], args[cut + 1 :]

    def body(console: Console) -> None:
        config = tyro.cli(BenchConfig, args=args, prog="dyngs-bench", description=__doc__)
        if shared:
            joined = f"{config.train_args} {shlex.join(shared)}".strip()
            config = dataclasses.replace(config, train_args=joined)
        run_bench(config, console)

    run_tool(body)


if __name__ == "__main__":
    main()
