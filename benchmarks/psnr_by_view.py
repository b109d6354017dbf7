"""PSNR of evaluated runs by camera: which viewpoints does a model lose, and how many
training views looked from near them?

    python benchmarks/psnr_by_view.py outputs/RUN ... --split test --within 30 --output FILE

For each run, reads its evaluated frames (`eval_<split>.json` from `dyngs-eval`, or for
the test split the `metrics.json` training wrote) and its cameras (`scene.json`, no
images), and groups the frames by camera position (`Camera.viewpoint`: a fixed rig's
cameras; a camera that moves makes one group a view). Per group it prints the frames,
the camera's elevation above the scene box's centre (in degrees, +z up, the D-NeRF and
MuJoCo convention), the mean PSNR, the group's share of the split's squared error, the
training views taken from that same camera, and those whose direction from the box
centre lies within `--within` degrees of the group's. A monocular sequence sees each
time from one camera, so a viewpoint that few training views share can be fitted and
generalised worse than the rest (docs/ACCURACY.md, texture). Writes the same figures to
--output (JSON).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from statistics import mean

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.datamanagers.scene_info import SCENE_FILE, SceneInfo  # noqa: E402


def frames_of(run: Path, split: str) -> list[dict] | None:
    """The run's per-frame scores on `split`, or None when it was not evaluated on it."""
    for path, wanted in ((run / f"eval_{split}.json", None), (run / "metrics.json", split)):
        if path.is_file():
            scores = json.loads(path.read_text())
            if wanted is None or scores.get("split", "test") == wanted:
                return scores["frames"]
    return None


def by_view(scene: SceneInfo, split: str, frames: list[dict], within: float) -> list[dict]:
    """One entry per camera position of the split's evaluated frames (see the module
    docstring), worst mean PSNR first."""
    centre = torch.tensor(scene.scene_box.center, dtype=torch.float64)
    cameras = getattr(scene, split).cameras
    train = torch.stack([c.to(dtype=torch.float64).center for c in scene.train.cameras])
    train_dirs = torch.nn.functional.normalize(train - centre, dim=1)
    train_viewpoints = [c.viewpoint() for c in scene.train.cameras]
    groups: dict[tuple[float, ...], list[dict]] = {}
    for frame in frames:
        groups.setdefault(cameras[frame["index"]].viewpoint(), []).append(frame)
    total_error = sum(10 ** (-f["psnr"] / 10) for f in frames)
    rows = []
    for viewpoint, members in groups.items():
        position = cameras[members[0]["index"]].to(dtype=torch.float64).center
        direction = torch.nn.functional.normalize(position - centre, dim=0)
        cosine = (train_dirs @ direction).clamp(-1.0, 1.0)
        rows.append({
            "position": [round(v, 4) for v in position.tolist()],
            "elevation": math.degrees(math.asin(float(direction[2]))),
            "frames": len(members),
            "psnr": mean(f["psnr"] for f in members),
            "error_share": sum(10 ** (-f["psnr"] / 10) for f in members) / total_error,
            "train_same_camera": train_viewpoints.count(viewpoint),
            "train_within": int((torch.rad2deg(torch.acos(cosine)) <= within).sum()),
        })  # fmt: skip
    return sorted(rows, key=lambda row: row["psnr"])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--split", default="test", choices=("train", "val", "test"))
    parser.add_argument("--within", type=float, default=30.0,
                        help="degrees between directions that count as near")  # fmt: skip
    parser.add_argument("--output", type=Path)
    args = parser.parse_args(argv)
    if not 0 <= args.within <= 180:
        parser.error(f"--within must be in [0, 180] degrees, got {args.within}")
    report = []
    for run in args.runs:
        frames = frames_of(run, args.split)
        if frames is None or not (run / SCENE_FILE).is_file():
            print(f"{run}: no {args.split} scores or no {SCENE_FILE}, skipped", file=sys.stderr)
            continue
        rows = by_view(SceneInfo.read(run / SCENE_FILE), args.split, frames, args.within)
        report.append({"run": str(run), "views": rows})
        print(f"{run} ({args.split}, {len(frames)} frames)")
        print(f"  {'camera position':>24} {'elev':>5} {'frames':>6} {'PSNR':>6} {'error':>6} "
              f"{'same cam':>8} {f'≤{args.within:g}°':>6}")  # fmt: skip
        for row in rows:
            where = "(" + ", ".join(f"{v:.2f}" for v in row["position"]) + ")"
            print(f"  {where:>24} {row['elevation']:5.0f} {row['frames']:6d} {row['psnr']:6.2f} "
                  f"{100 * row['error_share']:5.0f}% {row['train_same_camera']:8d} "
                  f"{row['train_within']:6d}")  # fmt: skip
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        payload = {"split": args.split, "within_degrees": args.within, "runs": report}
        args.output.write_text(json.dumps(payload, indent=1) + "\n")
        print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
