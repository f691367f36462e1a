"""`ceilcal exposure`: sweep a camera's manual exposure and gain, keep the best.

    ceilcal exposure --device /dev/video0 [--method lights|corridor|block] [--site FILE] \\
        [--exposures 12.5,25,50,100,200,400] [--gains 0,6,12] --out capture.yaml

Parses, calls :func:`ceilkit.calib.exposure.assist`, prints the sweep's table on stdout
and progress on stderr; the best setting goes to ``--out`` (``ceilrun --capture``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from ceilkit.calib import exposure as assistant
from ceilkit.cli.common import FOURCC_OPTION, FPS_OPTION, HEIGHT_OPTION, WIDTH_OPTION
from ceilkit.runtime.errors import ConfigError


def _numbers(text: str, key: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ConfigError(None, key, f"expected numbers separated by commas, found "
                          f"{text!r}") from None


def _progress(s: assistant.Setting) -> None:
    why = f" ({s.score.reason})" if s.score.reason else ""
    typer.echo(f"exposure {s.exposure:g}, gain {s.gain:g}: score {s.score.value:.2f}{why}",
               err=True)


def register(app: typer.Typer) -> None:
    """Add ``exposure`` to ``app``."""

    @app.command("exposure")
    def exposure(
        device: str = typer.Option(..., "--device", help="A live camera: index (0) or path "
                                   "(/dev/video0); sim:NAME for the simulator's camera."),
        out: Path = typer.Option(Path("capture.yaml"), "--out",
                                 help="The capture file to write (ceilrun --capture)."),
        method: str = typer.Option(None, "--method", help="lights, corridor or block "
                                   "(default: from --site)."),
        rig: Path = typer.Option(None, "--rig", help="rig.yaml (sim: the example's)."),
        site: Path = typer.Option(None, "--site", help="site.yaml (sim: the example's)."),
        exposures: str = typer.Option(",".join(f"{e:g}" for e in assistant.DEFAULT_EXPOSURES),
                                      "--exposures", help="Exposures to try, the driver's "
                                      "units (V4L2: 100 us), comma-separated."),
        gains: str = typer.Option(",".join(f"{g:g}" for g in assistant.DEFAULT_GAINS),
                                  "--gains", help="Gains to try (the driver's units; sim: "
                                  "dB), comma-separated."),
        settle: int = typer.Option(3, "--settle", help="Frames skipped after each change."),
        frames: int = typer.Option(3, "--frames", help="Frames scored per setting."),
        width: int = WIDTH_OPTION,
        height: int = HEIGHT_OPTION,
        fps: float = FPS_OPTION,
        fourcc: str = FOURCC_OPTION,
        force: bool = typer.Option(False, "--force", help="Replace an existing --out "
                                   "(refused otherwise)."),
    ) -> None:
        """Sweep exposure and gain on a camera; write the best for the method."""
        run = assistant.assist(
            device, out, method, rig, site, _numbers(exposures, "exposures"),
            _numbers(gains, "gains"), settle, frames, (width, height, fps, fourcc),
            _progress, command=" ".join(["ceilcal", *sys.argv[1:]]), force=force)
        typer.echo("\n".join(run.lines()))
