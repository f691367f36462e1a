"""``ceilcal``: calibrate a rig, survey a site, simulate recordings."""

from __future__ import annotations

from . import (
    ceilcal_board,
    ceilcal_calibrate,
    ceilcal_exposure,
    ceilcal_intrinsics,
    ceilcal_lightmap,
    ceilcal_mount,
    ceilcal_simulate,
)
from .common import make_app, quiet_opencv

app = make_app("ceilcal", "Calibrate a ceiling-vision rig: intrinsics, mount, light map; "
               "simulate recordings.")

for _module in (ceilcal_simulate, ceilcal_intrinsics, ceilcal_mount, ceilcal_lightmap,
                ceilcal_calibrate, ceilcal_board, ceilcal_exposure):
    _module.register(app)

from . import ceilcal_autopilot  # noqa: E402 - registered after the calibration commands

ceilcal_autopilot.register(app)


def main() -> None:
    quiet_opencv()
    app(prog_name="ceilcal")


if __name__ == "__main__":
    main()
