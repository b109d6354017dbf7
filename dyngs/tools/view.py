"""`dyngs-view`: an interactive viewer of a trained run in the web browser, e.g.
`dyngs-view --load-dir outputs/RUN`, then open the address it prints.

The page shows the run from its first training view: drag to turn the camera, scroll to
zoom, right-drag to move; the Camera list jumps to any training, validation or test view.
The Time slider, Play and Speed run the sequence. Toggles show the canonical scene
(deformation off), static and dynamic Gaussians in two colours, and depth. Frames are
drawn smaller while the view moves and at full size when it stops. It serves on this
machine only unless --host says otherwise; it needs only the run folder.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console

from dyngs.errors import ConfigError
from dyngs.renderers import RENDERERS, CudaTileConfig, default_renderer, renderer_name
from dyngs.runs import LoadedRun, RunOverrides, load_run
from dyngs.tools.common import run_tool
from dyngs.viewer.frames import fastest_renderer
from dyngs.viewer.options import ViewerOptions


@dataclass(frozen=True)
class ViewConfig:
    """Serve an interactive web viewer of a trained run."""

    load_dir: Path
    """Run folder written by dyngs-train."""
    renderer: str = "fastest"
    """Renderer to draw with: `fastest` (cuda-tile with a GPU and gsplat, else
    cpu-tile), `run` (the one trained with) or a registered name."""
    device: str | None = None
    """Device to load onto (default: where the renderer runs)."""
    viewer: Annotated[ViewerOptions, tyro.conf.OmitArgPrefixes] = field(
        default_factory=ViewerOptions
    )

    def __post_init__(self) -> None:
        if self.renderer not in ("fastest", "run") and self.renderer not in RENDERERS:
            known = ", ".join(["fastest", "run", *RENDERERS.names()])
            raise ConfigError(f"--renderer must be one of {known}, got {self.renderer!r}")


def load_for_viewing(config: ViewConfig) -> LoadedRun:
    """The run, with the renderer and device the viewer draws with."""
    if config.renderer != "fastest":
        overrides = RunOverrides(device=config.device, renderer=config.renderer)
        return load_run(config.load_dir, overrides=overrides)
    fastest = default_renderer()  # cuda-tile where it runs, and then the model goes there
    device = config.device or ("cuda" if isinstance(fastest, CudaTileConfig) else "cpu")
    name = renderer_name(fastest_renderer(device))
    return load_run(config.load_dir, overrides=RunOverrides(device=device, renderer=name))


def run_view(config: ViewConfig, console: Console, stop: threading.Event | None = None) -> None:
    """Serve the viewer until `stop` is set (or Ctrl-C)."""
    from dyngs.viewer.server import Viewer  # the web server loads only when used

    run = load_for_viewing(config)
    viewer = Viewer(run.scene, run.renderer, config.viewer, title=f"dyngs · {run.run_dir.name}")
    viewer.show(run.model, f"step {run.step:,} · {renderer_name(run.config.renderer)}")
    url = viewer.start()
    console.print(f"viewer of {run.run_dir} at {url}  (Ctrl-C stops it)", highlight=False)
    stop = stop or threading.Event()
    try:
        while not stop.wait(0.5):  # short waits, so Ctrl-C is seen at once
            pass
    finally:
        viewer.stop()


def main(argv: Sequence[str] | None = None) -> None:
    def body(console: Console) -> None:
        config = tyro.cli(ViewConfig, args=argv, prog="dyngs-view", description=__doc__)
        run_view(config, console)

    run_tool(body)


if __name__ == "__main__":
    main()
