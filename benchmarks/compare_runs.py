"""Compare two recipes' runs pair by pair: per scene and pooled, with a verdict.

    python benchmarks/compare_runs.py --base 'outputs/base/{}' --variant 'outputs/rough/{}'

Each pattern names a run folder (one that holds `metrics.json`) with `{}` where the pair's
name goes; the names are those the base pattern finds (`{}` as a wildcard) that the
variant pattern has too, e.g. `mujoco-texture-s0`, as `bench_accuracy.py` names its runs
(train a variant with its `--flags` into another `--output-dir`). A name's scene is the
name without its trailing `-sSEED`.

For every scene and for all pairs together it prints the base and variant means and the
paired change of test PSNR (variant − base): its mean, standard error, how many pairs went
up, and the p-value of Fisher's exact sign-flip test (`dyngs.tools.paired`), which calls
it a gain or a loss only when p < 0.05. One run of each recipe cannot say that: seeds
alone move a scene by more than the changes worth testing. It also gives the mean
change of SSIM and LPIPS, and the relative change of training time and Gaussians (what
the accuracy costs). Writes every pair and
the summaries to `--output` (JSON).
"""

from __future__ import annotations

import argparse
import glob
import json
import re
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.tools.paired import paired_change  # noqa: E402

SEED_SUFFIX = re.compile(r"-s\d+$")
KEYS = ("psnr", "ssim", "lpips", "train_seconds", "num_gaussians")


def find_pairs(base: str, variant: str) -> dict[str, tuple[Path, Path]]:
    """Pair name → (base run, variant run), for every name both patterns have a finished
    run for (a folder with metrics.json), in name order."""
    for pattern in (base, variant):
        if pattern.count("{}") != 1:
            raise SystemExit(f"{pattern}: a pattern needs exactly one {{}} where the name goes")
    head, tail = base.split("{}")
    name_of = re.compile(re.escape(head) + "(.+)" + re.escape(tail))
    pairs = {}
    for found in sorted(glob.glob(glob.escape(head) + "*" + glob.escape(tail))):
        name = name_of.fullmatch(found).group(1)  # type: ignore[union-attr]
        one, other = Path(found), Path(variant.replace("{}", name))
        if (one / "metrics.json").is_file() and (other / "metrics.json").is_file():
            pairs[name] = (one, other)
    return pairs


def _metrics(run: Path) -> dict:
    try:
        return json.loads((run / "metrics.json").read_text())
    except (OSError, ValueError) as error:
        raise SystemExit(f"{run / 'metrics.json'}: unreadable ({error})") from None


def compare(pairs: dict[str, tuple[Path, Path]]) -> dict:
    """Per-pair figures and the per-scene and pooled summaries."""
    rows = []
    for name, (base, variant) in pairs.items():
        b, v = _metrics(base), _metrics(variant)
        rows.append({"name": name, "scene": SEED_SUFFIX.sub("", name),
                     **{f"base:{k}": b.get(k) for k in KEYS},
                     **{f"variant:{k}": v.get(k) for k in KEYS}})  # fmt: skip
    groups = {scene: [r for r in rows if r["scene"] == scene]
              for scene in dict.fromkeys(r["scene"] for r in rows)}  # fmt: skip
    summaries = [summarize(scene, group) for scene, group in groups.items()]
    if len(groups) > 1:
        summaries.append(summarize("all pairs", rows))
    return {"pairs": rows, "summaries": summaries}


def summarize(label: str, rows: list[dict]) -> dict:
    change = paired_change([r["base:psnr"] for r in rows], [r["variant:psnr"] for r in rows])

    def measured(key: str) -> list[tuple[float, float]]:
        """(base, variant) of the pairs where both runs report `key`."""
        both = [(r[f"base:{key}"], r[f"variant:{key}"]) for r in rows]
        return [(b, v) for b, v in both if b is not None and v is not None]

    def difference(key: str) -> float | None:
        changes = [v - b for b, v in measured(key)]
        return statistics.fmean(changes) if changes else None

    def relative(key: str) -> float | None:
        ratios = [v / b - 1 for b, v in measured(key) if b]
        return statistics.fmean(ratios) if ratios else None

    return {
        "label": label, "pairs": change.n,
        "base_psnr": statistics.fmean(r["base:psnr"] for r in rows),
        "variant_psnr": statistics.fmean(r["variant:psnr"] for r in rows),
        "change": change.mean, "stderr": change.stderr, "std": change.std, "p": change.p,
        "wins": change.wins, "verdict": change.verdict(),
        "ssim_change": difference("ssim"), "lpips_change": difference("lpips"),
        "train_seconds_change": relative("train_seconds"),
        "gaussians_change": relative("num_gaussians"),
    }  # fmt: skip


def table(summaries: list[dict]) -> str:
    headers = ("scene", "pairs", "base dB", "variant dB", "change ± SE", "up", "p", "verdict",
               "Δ SSIM", "Δ LPIPS", "train time", "Gaussians")  # fmt: skip
    lines = ["| " + " | ".join(headers) + " |", "|" + " --- |" * len(headers)]

    def percent(value: float | None) -> str:
        return "—" if value is None else f"{100 * value:+.0f} %"

    def signed(value: float | None) -> str:
        return "—" if value is None else f"{value:+.4f}"

    for s in summaries:
        se = "" if s["stderr"] is None else f" ± {s['stderr']:.2f}"
        lines.append(
            f"| {s['label']} | {s['pairs']} | {s['base_psnr']:.2f} | {s['variant_psnr']:.2f} | "
            f"{s['change']:+.2f}{se} | {s['wins']} | {s['p']:.2g} | {s['verdict']} | "
            f"{signed(s['ssim_change'])} | {signed(s['lpips_change'])} | "
            f"{percent(s['train_seconds_change'])} | {percent(s['gaussians_change'])} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--base", required=True, help="run folder pattern, {} for the name")
    parser.add_argument("--variant", required=True, help="run folder pattern, {} for the name")
    parser.add_argument("--output", type=Path, default=None, help="JSON of every pair")
    args = parser.parse_args(argv)
    pairs = find_pairs(args.base, args.variant)
    if not pairs:
        raise SystemExit(f"no finished runs in both {args.base} and {args.variant}")
    result = compare(pairs)
    print(table(result["summaries"]))
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps({"base": args.base, "variant": args.variant,
                                           **result}, indent=1) + "\n")  # fmt: skip
        print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
