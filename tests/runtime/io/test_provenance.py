"""Every output names the version that wrote it (issue 37): ``run.yaml`` beside
``poses.csv`` (whose first line is its SPEC header), a comment in TUM and YAML files."""

from __future__ import annotations

from datetime import datetime, timezone

import yaml

from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.io.provenance import VERSION, run_metadata, version_line
from ceilkit.runtime.io.recording import PoseWriter, RecordingWriter
from ceilkit.runtime.io.tables import POSES_HEADER


def test_run_metadata_is_yaml_naming_version_time_and_command():
    text = run_metadata("poses.csv", command='ceilrun --option "a=b c"',
                        now=datetime(2026, 1, 2, 3, 4, 5, tzinfo=timezone.utc))
    assert yaml.safe_load(text) == {"written_by": f"ceilkit {VERSION}", "what": "poses.csv",
                                    "written": "2026-01-02T03:04:05+00:00",
                                    "command": 'ceilrun --option "a=b c"'}
    assert version_line() == f"ceilkit {VERSION}"


def test_poses_folder_has_run_yaml_and_tum_a_comment(tmp_path):
    with PoseWriter(tmp_path / "poses.csv", tmp_path / "poses.tum") as w:
        w.write(PoseEstimate(10, "lights", 1.0, 2.0, 0.1, 0.9), 1.0)
    assert (tmp_path / "poses.csv").read_text().splitlines()[0] == ",".join(POSES_HEADER)
    meta = yaml.safe_load((tmp_path / "run.yaml").read_text())
    assert meta["written_by"] == version_line() and meta["what"].startswith("poses.csv")
    first = (tmp_path / "poses.tum").read_text().splitlines()[0]
    assert first == f"# t_s x y z qx qy qz qw; written by {version_line()}"


def test_a_recordings_rig_and_site_name_the_version(tmp_path, lights_rig, lights_site):
    with RecordingWriter(tmp_path / "rec", lights_rig, lights_site):
        pass
    for name in ("rig.yaml", "site.yaml"):
        assert (tmp_path / "rec" / name).read_text().startswith(
            f"# recorded by {version_line()}\n")
