"""`ceilcal simulate`: simulated data with truth: a recording (frames + truth) for a rig
and site, board views through a lens, or placement images with their placements file.

Parses, calls :func:`ceilkit.calib.workflow.simulate`, prints one line. A bad value is
reported with the flag the user typed (``cli/common.py`` maps the library's names).
"""

from __future__ import annotations

from pathlib import Path

import typer

from ceilkit.calib import workflow
from ceilkit.calib.boards import parse_board
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.io.outputs import claimed


def register(app: typer.Typer) -> None:
    """Add ``simulate`` to ``app`` (made by :func:`ceilkit.cli.common.make_app`, whose
    group callback keeps it a subcommand)."""
    @app.command("simulate")
    def simulate(
        out: Path = typer.Option(..., "--out", help="Folder to write (new)."),
        kind: str = typer.Option("drive", "--kind", help="drive: a recording with truth; "
                                 "boards: board views for ceilcal intrinsics; placements: "
                                 "parked images and placements.yaml for ceilcal mount."),
        rig: Path = typer.Option(None, "--rig", help="rig.yaml (default: packaged corridor)."),
        site: Path = typer.Option(None, "--site",
                                  help="site.yaml (default: packaged corridor)."),
        frames: int = typer.Option(300, "--frames", help="Number of frames."),
        fps: float = typer.Option(30.0, "--fps", help="Frame rate, Hz."),
        trajectory: str = typer.Option("drive", "--trajectory",
                                       help="drive, random, or a truth.csv-layout file."),
        lateral: float = typer.Option(0.0, "--lateral", help="y of the drive, m."),
        weave: float = typer.Option(0.0, "--weave", help="Sideways weave amplitude, m."),
        wobble: float = typer.Option(0.0, "--wobble", help="Heading wobble amplitude, deg."),
        speed: float = typer.Option(0.5, "--speed", help="Drive speed, m/s."),
        noise: float = typer.Option(2.0, "--noise", help="Sensor noise sigma, grey levels."),
        blur: float = typer.Option(0.8, "--blur", help="Optical blur sigma, px."),
        supersample: int = typer.Option(3, "--supersample", help="Anti-aliasing factor."),
        clutter: bool = typer.Option(False, "--clutter", help="Add distractor lines."),
        seed: int = typer.Option(0, "--seed", help="Seed for noise and trajectory."),
        sim_preset: str = typer.Option(None, "--sim-preset", help="Realism preset from the "
                                       "presets.yaml beside the site (e.g. realistic)."),
        sim_fault: list[str] = typer.Option(None, "--sim-fault", metavar="KNOB=VALUE",
                                            help="A realism knob (repeatable), on top of "
                                            "--sim-preset; see docs/simulator.md."),
        scene: Path = typer.Option(None, "--scene", help="Scene file: the ceiling's scatter "
                                   "(panels, vents, sprinklers, ...; default: the "
                                   "scene.yaml beside the site, if any)."),
        board: str = typer.Option(None, "--board", help="boards: chess:COLSxROWS or "
                                  "charuco:SXxSY[:DICT] (as ceilcal intrinsics)."),
        square: float = typer.Option(None, "--square", help="boards: square side, metres."),
        marker: float = typer.Option(None, "--marker", help="boards: ChArUco marker side, m."),
        camera: Path = typer.Option(None, "--camera", help="boards: the lens (camera.yaml; "
                                    "default: the --rig's camera)."),
        views: int = typer.Option(30, "--views", help="boards: number of views."),
        placement: list[str] = typer.Option(None, "--placement", metavar="Y,YAW",
                                            help="placements: lateral m, heading deg "
                                            "(repeatable; default 5: 0,0 0.25,0 -0.25,0 "
                                            "0.1,12 -0.1,-12)."),
    ) -> None:
        """Render simulated data with its truth: a recording, board views or placements."""
        inputs = [p for p in (rig, site, scene, camera) if p is not None]
        with claimed({}, folders={"out": [out]}, inputs=inputs):  # locked while written
            if kind == "boards":
                if board is None or square is None:
                    raise ConfigError(None, "board", "--kind boards needs --board and --square")
                typer.echo("\n".join(workflow.simulate_boards(
                    out, parse_board(board, square, marker), camera=camera, rig=rig,
                    views=views, seed=seed, noise_sigma=noise, blur_px=blur,
                    supersample=supersample).lines()))
                return
            if kind not in ("drive", "placements"):
                raise ConfigError(None, "kind", f"expected drive, boards or placements, found "
                                  f"{kind!r}")
            run = workflow.simulate(out, rig=rig, site=site, frames=frames, fps=fps,
                                    trajectory=trajectory, lateral_m=lateral, weave_m=weave,
                                    wobble_deg=wobble, speed_mps=speed, noise_sigma=noise,
                                    blur_px=blur, supersample=supersample, clutter=clutter,
                                    seed=seed, sim_preset=sim_preset,
                                    sim_faults=tuple(sim_fault or ()),
                                    placements=None if kind == "drive" else
                                    workflow.parse_placements(placement or ()), scene=scene)
            typer.echo("\n".join(run.lines()))
