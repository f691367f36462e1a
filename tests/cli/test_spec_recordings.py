"""SPEC conformance for data made outside the project.

Recordings, rig and site files are written here as an outside tool would write them
(``cv2.imwrite``, the ``csv`` module, YAML as plain text: never ceilkit's writers),
then replayed with ``ceilrun replay RECORDING [--out DIR] [--rig FILE] [--site FILE]
[--method NAME]`` (SPEC §3), and ``poses.csv`` / ``poses.tum`` are checked field by
field against SPEC §2. The frames' pixels come from the simulator; only how they are
stored is the outside tool's.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from ceilkit.cli.ceilrun import app
from ceilkit.runtime.config.rig import Mount, Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.io.recording import load_poses
from ceilkit.runtime.sim.render import SimOptions, render_frame
from helpers import CONFIGS

runner = CliRunner()
POSES_LINE = ("t_ns,x,y,yaw_deg,lateral,method,quality,latency_ms,"
              "sigma_x,sigma_y,sigma_yaw_deg")
SIGMAS = ("sigma_x", "sigma_y", "sigma_yaw_deg")
W, H = 320, 240
T0_NS = 1_718_000_000_000_000_000          # an epoch stamp, as a real camera driver gives


def camera_yaml(name: str) -> str:
    """The packaged camera resampled to W x H, in the ROS camera_calibration layout."""
    cam = Rig.load(CONFIGS / name / "rig.yaml").camera.scaled(W, H)

    def row(a) -> str:
        return ", ".join(f"{v:.6f}" for v in np.ravel(a))

    return (f"image_width: {W}\nimage_height: {H}\ncamera_name: outside_{name}\n"
            f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: [{row(cam.K)}]\n"
            f"distortion_model: {cam.model}\n"
            f"distortion_coefficients:\n  rows: 1\n  cols: {cam.dist.size}\n"
            f"  data: [{row(cam.dist)}]\n"
            f"rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [{row(np.eye(3))}]\n"
            f"projection_matrix:\n  rows: 3\n  cols: 4\n"
            f"  data: [{row(np.hstack([cam.K, np.zeros((3, 1))]))}]\n")


def indent(text: str, n: int) -> str:
    return "".join(" " * n + line + "\n" for line in text.splitlines())


MOUNTS = {"lights": "{pan: 0.0, tilt: 90.0, swing: 0.0, x: 0.0, y: 0.0, z: 0.50}",
          "corridor": "{pan: 2.0, tilt: 45.0, swing: 1.0, x: 0.30, y: 0.05, z: 0.80}"}

# every optional section; the corridor and lamps lie beyond the lights' hall
LIGHTS_SITE = (Path(CONFIGS / "lights" / "site.yaml").read_text() + """\
corridor:
  lines_along: [20.45, 20.15, 19.85, 19.55]
  lines_across: {first: 0.0, spacing: 2.4}
lamps:
  - {x: 0.0, y: 20.0, length: 1.2, width: 0.3, pitch: 2.4, count: 20}
blocks:
  - {id: A, corners: [[2.0, 19.8], [2.6, 19.8], [2.6, 20.2], [2.0, 20.2]]}
  - {id: 7, corners: [[5.0, 19.8], [5.6, 19.8], [5.6, 20.2], [5.0, 20.2]]}
""")
CORRIDOR_SITE = (CONFIGS / "corridor" / "site.yaml").read_text()
POSES = {"lights": [(6.0 + 0.04 * k, 0.5, math.radians(30.0)) for k in range(4)],
         "corridor": [(2.0 + 0.04 * k, 0.05, math.radians(1.0)) for k in range(4)]}
"""Frame k's vehicle pose, 1/30 s apart (1.2 m/s: within the vehicle's stated limits,
``prior.MAX_SPEED_MPS``, so the fusion keeps one track through them)."""


@pytest.fixture(scope="module")
def images() -> dict[str, list[np.ndarray]]:
    """Grey frames (H, W) uint8 of each example at POSES, rendered once."""
    out = {}
    for name, poses in POSES.items():
        cam = Rig.load(CONFIGS / name / "rig.yaml")
        rig = Rig(cam.camera.scaled(W, H), cam.mount)
        site = Site.load(CONFIGS / name / "site.yaml")
        out[name] = [render_frame(rig, site, *p, SimOptions(), np.random.default_rng(k))
                     for k, p in enumerate(poses)]
    return out


def write_recording(folder: Path, name: str, images: list[np.ndarray], *,
                    bgr: bool = False, camera_inline: bool = False,
                    indices: list[int] | None = None, newline: str = "\n",
                    site_text: str | None = None, truth: bool = True) -> Path:
    """A SPEC recording written with cv2.imwrite, csv and plain YAML text."""
    (folder / "frames").mkdir(parents=True)
    indices = list(range(len(images))) if indices is None else indices
    t_ns = [T0_NS + k * 33_333_333 for k in range(len(images))]
    for i, img in zip(indices, images, strict=True):
        out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if bgr else img
        assert cv2.imwrite(str(folder / "frames" / f"{i:06d}.png"), out)
    with open(folder / "frames.csv", "w", newline="") as fh:
        w = csv.writer(fh, lineterminator=newline)
        w.writerow(["index", "t_ns"])
        w.writerows(zip(indices, t_ns, strict=True))
    if truth:
        with open(folder / "truth.csv", "w", newline="") as fh:
            w = csv.writer(fh, lineterminator=newline)
            w.writerow(["t_ns", "x", "y", "yaw_deg"])
            for t, (x, y, yaw) in zip(t_ns, POSES[name], strict=True):
                w.writerow([t, x, y, math.degrees(yaw)])
    if camera_inline:
        rig = f"camera:\n{indent(camera_yaml(name), 2)}mount: {MOUNTS[name]}\n"
    else:
        (folder / "camera.yaml").write_text(camera_yaml(name), newline="")
        rig = f"camera: camera.yaml\nmount: {MOUNTS[name]}\n"
    (folder / "rig.yaml").write_text(rig.replace("\n", newline), newline="")
    site = site_text if site_text is not None else (
        LIGHTS_SITE if name == "lights" else CORRIDOR_SITE)
    (folder / "site.yaml").write_text(site.replace("\n", newline), newline="")
    return folder


def read_poses(path: Path) -> tuple[str, list[dict[str, str]]]:
    """The header line as written and the rows as dicts of raw strings."""
    text = path.read_text()
    lines = text.splitlines()
    assert text.endswith("\n") and "\r" not in text
    rows = list(csv.DictReader(lines))
    for r in rows:
        assert None not in r and len(r) == 11            # exactly eleven fields
    return lines[0], rows


def frame_stamps(folder: Path) -> list[int]:
    with open(folder / "frames.csv", newline="", encoding="utf-8-sig") as fh:
        return [int(r["t_ns"]) for r in csv.DictReader(fh)]


def check_rows(rows: list[dict[str, str]], folder: Path, method: str,
               unobserved: tuple[str, ...]) -> list[dict[str, str]]:
    """SPEC §2 on every row; returns the rows that hold a pose."""
    assert [int(r["t_ns"]) for r in rows] == frame_stamps(folder)
    poses = []
    for r in rows:
        assert r["method"] == method
        q = float(r["quality"])
        assert 0.0 <= q <= 1.0
        assert float(r["latency_ms"]) >= 0.0
        if r["yaw_deg"] == "":                            # a failure: no pose fields
            assert r["x"] == r["y"] == r["lateral"] == "" and q == 0.0
            assert all(r[key] == "" for key in SIGMAS)
            continue
        poses.append(r)
        for key in unobserved:
            assert r[key] == "", (key, r)
            if key in ("x", "y"):                         # nor its 1-sigma
                assert r[f"sigma_{key}"] == "", (key, r)
        for key in SIGMAS:                                # 1-sigma: empty or finite >= 0
            assert r[key] == "" or (math.isfinite(float(r[key])) and float(r[key]) >= 0)
        for key in ("x", "y", "yaw_deg", "lateral"):
            if key not in unobserved and r[key] != "":
                assert math.isfinite(float(r[key]))
    return poses


def truth_by_stamp(folder: Path) -> dict[int, tuple[float, float, float]]:
    with open(folder / "truth.csv", newline="") as fh:
        return {int(r["t_ns"]): (float(r["x"]), float(r["y"]), float(r["yaw_deg"]))
                for r in csv.DictReader(fh)}


# --------------------------------------------------------------------------- replays
@pytest.mark.parametrize("bgr,inline,newline", [(False, False, "\n"), (True, True, "\r\n")])
def test_lights_recording_from_outside(tmp_path, images, bgr, inline, newline):
    """Grey or BGR PNGs, camera beside or inline, LF or CRLF, a site with every
    optional section; the default out dir, the site's default method (lights)."""
    rec = write_recording(tmp_path / "rec", "lights", images["lights"], bgr=bgr,
                          camera_inline=inline, newline=newline)
    res = runner.invoke(app, ["replay", str(rec), "--tum"])
    assert res.exit_code == 0, res.output
    header, rows = read_poses(rec / "replay" / "poses.csv")
    assert header == POSES_LINE
    poses = check_rows(rows, rec, "lights", unobserved=())
    assert len(poses) >= 3
    truth = truth_by_stamp(rec)
    for r in poses:                     # metres and degrees, as truth.csv has them
        x, y, yaw_deg = truth[int(r["t_ns"])]
        assert abs(float(r["x"]) - x) < 0.02 and abs(float(r["y"]) - y) < 0.02
        assert abs(float(r["yaw_deg"]) - yaw_deg) < 0.5
    # TUM: t_s x y z qx qy qz qw, one line per full pose, stamps to the nanosecond
    tum = [line.split() for line in (rec / "replay" / "poses.tum").read_text().splitlines()
           if not line.startswith("#")]     # the first line: a comment naming the version
    assert len(tum) == sum(1 for r in poses if r["x"] and r["y"])
    for fields, r in zip(tum, poses, strict=True):
        assert len(fields) == 8
        sec, frac = fields[0].split(".")
        assert int(sec) * 10**9 + int(frac) == int(r["t_ns"]) and len(frac) == 9
        assert float(fields[1]) == pytest.approx(float(r["x"]), abs=1e-6)
        assert float(fields[2]) == pytest.approx(float(r["y"]), abs=1e-6)
        assert [float(v) for v in fields[3:6]] == [0.0, 0.0, 0.0]
        qz, qw = float(fields[6]), float(fields[7])
        assert qz * qz + qw * qw == pytest.approx(1.0, abs=1e-8)
        assert math.degrees(2 * math.atan2(qz, qw)) == pytest.approx(float(r["yaw_deg"]),
                                                                     abs=1e-5)


def test_corridor_recording_leaves_x_empty(tmp_path, images):
    """The corridor method does not observe x: the field is empty, lateral is given,
    and the TUM file holds no made-up x."""
    rec = write_recording(tmp_path / "rec", "corridor", images["corridor"], bgr=True)
    out = tmp_path / "elsewhere"
    # the corridor is symmetric about its centre line: the user states the heading
    res = runner.invoke(app, ["replay", str(rec), "--out", str(out), "--method", "corridor",
                              "--tum", "--option", "assume_heading_deg=0"])
    assert res.exit_code == 0, res.output
    assert not (rec / "replay").exists()
    header, rows = read_poses(out / "poses.csv")
    assert header == POSES_LINE
    poses = check_rows(rows, rec, "corridor", unobserved=("x",))
    assert len(poses) >= 3
    truth = truth_by_stamp(rec)
    for r in poses:
        _, y, yaw_deg = truth[int(r["t_ns"])]
        assert abs(float(r["y"]) - y) < 0.02 and abs(float(r["yaw_deg"]) - yaw_deg) < 0.3
        assert abs(float(r["lateral"]) - y) < 0.02        # the corridor's axis is y = 0
    assert (out / "poses.tum").read_text().startswith("# ")  # a comment alone, no row
    assert len((out / "poses.tum").read_text().splitlines()) == 1


def test_rig_and_site_overrides(tmp_path, images):
    """--rig and --site replace the recording's own files (a camera path in --rig is
    relative to that file)."""
    rec = write_recording(tmp_path / "rec", "lights", images["lights"],
                          site_text="ceiling_height: 3.0\ncorridor: {lines_along: [0.0]}\n")
    # the recording's own site has no lights: the default method would be corridor
    other = tmp_path / "cfg"
    other.mkdir()
    (other / "cam.yaml").write_text(camera_yaml("lights"))
    (other / "rig.yaml").write_text(f"camera: cam.yaml\nmount: {MOUNTS['lights']}\n")
    (other / "site.yaml").write_text(LIGHTS_SITE)
    (rec / "camera.yaml").unlink()                     # the recording's rig is unusable
    res = runner.invoke(app, ["replay", str(rec), "--rig", str(other / "rig.yaml"),
                              "--site", str(other / "site.yaml"), "--method", "paper-lights"])
    assert res.exit_code == 0, res.output
    _, rows = read_poses(rec / "replay" / "poses.csv")
    assert len(check_rows(rows, rec, "paper-lights", unobserved=())) >= 3


def test_exit_0_whatever_share_is_estimated(tmp_path):
    """Blank frames: every row a failure, and still exit 0 (the run completed)."""
    blank = [np.full((H, W), 20, np.uint8) for _ in range(3)]
    rec = write_recording(tmp_path / "rec", "corridor", blank, truth=False)
    res = runner.invoke(app, ["replay", str(rec)])
    assert res.exit_code == 0, res.output
    header, rows = read_poses(rec / "replay" / "poses.csv")
    assert header == POSES_LINE and len(rows) == 3
    assert check_rows(rows, rec, "corridor", unobserved=("x",)) == []


def test_indices_late_with_gaps_and_unlisted_files(tmp_path, images):
    rec = write_recording(tmp_path / "rec", "lights", images["lights"],
                          indices=[5, 6, 9, 20])
    cv2.imwrite(str(rec / "frames" / "000000.png"), images["lights"][0])   # not listed
    res = runner.invoke(app, ["replay", str(rec)])
    assert res.exit_code == 0, res.output
    _, rows = read_poses(rec / "replay" / "poses.csv")
    assert len(rows) == 4 and len(check_rows(rows, rec, "lights", ())) >= 3


def test_tilt_90_only_pan_plus_swing_counts(tmp_path, images):
    """At tilt 90 deg pan and swing turn about the same axis (SPEC §1): recordings whose
    rig.yaml says pan 20, swing 10 or pan 30, swing 0 (angles in degrees) give the same
    frames and the same poses; pan 20, swing -20 does not."""
    site = Site.load(CONFIGS / "lights" / "site.yaml")
    cam = Rig.load(CONFIGS / "lights" / "rig.yaml").camera.scaled(W, H)
    results = []
    for pan, swing in ((20.0, 10.0), (30.0, 0.0), (20.0, -20.0)):
        mount = MOUNTS["lights"].replace("pan: 0.0", f"pan: {pan}").replace(
            "swing: 0.0", f"swing: {swing}")
        folder = tmp_path / f"rec{pan:g}_{swing:g}"
        m = Mount(math.radians(pan), math.pi / 2, math.radians(swing), 0.0, 0.0, 0.5)
        imgs = [render_frame(Rig(cam, m), site, *p, SimOptions(), np.random.default_rng(k))
                for k, p in enumerate(POSES["lights"][:2])]
        write_recording(folder, "lights", imgs, truth=False)
        (folder / "rig.yaml").write_text(f"camera: camera.yaml\nmount: {mount}\n")
        rig = Rig.load(folder / "rig.yaml")
        assert np.allclose(rig.mount.R_vehicle_cam, m.R_vehicle_cam)   # degrees in files
        res = runner.invoke(app, ["replay", str(folder)])
        assert res.exit_code == 0, res.output
        results.append((imgs, load_poses(folder / "replay" / "poses.csv")))
    (a_imgs, a), (b_imgs, b), (c_imgs, c) = results
    np.testing.assert_array_equal(a_imgs[0], b_imgs[0])     # the same view
    assert np.any(a_imgs[0] != c_imgs[0])                   # pan + swing differs
    assert np.all(np.isfinite(a.x_m)) and np.all(np.isfinite(c.x_m))
    np.testing.assert_allclose(a.x_m, b.x_m, atol=1e-9)
    np.testing.assert_allclose(a.yaw_rad, b.yaw_rad, atol=1e-9)
    # and every rig read its own frames right: the same vehicle poses from all three
    np.testing.assert_allclose(c.yaw_rad, a.yaw_rad, atol=math.radians(0.3))


# --------------------------------------------------------------------------- bad data
@pytest.mark.parametrize("breakage,words", [
    (lambda r: (r / "frames" / "000002.png").unlink(), "frames.csv: line 4: frame file "
     "frames/000002.png is missing"),
    (lambda r: (r / "frames.csv").write_text("index,t_ns,exposure\n0,1,5\n"),
     "frames.csv: header: expected `index,t_ns`"),
    (lambda r: (r / "frames.csv").write_text("index,t_ns\n0,1.5e9\n"),
     "frames.csv: line 2: t_ns: expected an integer"),
    (lambda r: (r / "camera.yaml").write_text(camera_yaml("lights") + "binning_x: 0\n"),
     "camera.yaml: binning_x: unknown key"),
    (lambda r: (r / "rig.yaml").write_text(
        "camera: camera.yaml\nmount: {pan: 0, tilt: 1.5708, swing: 0, z: 0.5, roll: 0}\n"),
     "rig.yaml: mount.roll: unknown key"),
    (lambda r: (r / "rig.yaml").write_text(
        "camera: camera.yaml\nmount: {pan: 0, tilt: 95, swing: 0, z: 0.5}\n"),
     "rig.yaml: mount.tilt: expected a number in [0, 90] degrees, found 95"),
    (lambda r: (r / "site.yaml").write_text(LIGHTS_SITE + "doors: []\n"),
     "site.yaml: doors: unknown key"),
    (lambda r: cv2.imwrite(str(r / "frames" / "000001.png"), np.zeros((120, 160), np.uint8)),
     "000001.png: the image is 160x120 but the camera"),
])
def test_bad_outside_data_is_one_line_naming_file_and_key(tmp_path, images, breakage, words):
    rec = write_recording(tmp_path / "rec", "lights", images["lights"])
    breakage(rec)
    res = runner.invoke(app, ["replay", str(rec)])
    assert res.exit_code == 1
    lines = res.output.strip().splitlines()
    assert lines[-1].startswith("ceilrun: error: ") and words in lines[-1], res.output
    assert "Traceback" not in res.output
