import math
import os

import numpy as np
import pytest

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.errors import ConfigError, OutputError
from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from ceilkit.runtime.io.recording import (
    POSES_HEADER,
    PoseWriter,
    Recording,
    RecordingWriter,
    Truth,
    load_poses,
    load_truth,
)
from ceilkit.runtime.io.sources import Frame


def _rig(rig, shape=(24, 32)):
    """The rig with its camera resampled to the test frames' size."""
    return Rig(rig.camera.scaled(shape[1], shape[0]), rig.mount)


def _frames(n, shape=(24, 32)):
    rng = np.random.default_rng(3)
    return [Frame(rng.integers(0, 255, shape, dtype=np.uint8), 1_000_000 * (k + 1), k)
            for k in range(n)]


def test_write_read_round_trip(tmp_path, corridor_rig, corridor_site):
    corridor_rig = _rig(corridor_rig)
    frames = _frames(4)
    with RecordingWriter(tmp_path / "rec", corridor_rig, corridor_site, truth=True) as rec:
        for k, f in enumerate(frames):
            rec.write(f)
            rec.write_truth(f.t_ns, 0.1 * k, -0.2, math.radians(5 * k))
    back = Recording(tmp_path / "rec")
    assert len(back) == 4
    for f, g in zip(frames, back, strict=True):
        assert g.t_ns == f.t_ns and np.array_equal(g.image, f.image)
    assert back.rig.mount == corridor_rig.mount
    assert back.site.to_dict() == corridor_site.to_dict()
    assert np.allclose(back.truth.lookup(frames[2].t_ns), (0.2, -0.2, math.radians(10)))
    assert back.truth.lookup(5) is None


def test_truth_of_a_source_is_written_with_its_frames(tmp_path, corridor_rig, corridor_site):
    frames = _frames(3)
    truth = Truth(np.array([frames[0].t_ns, frames[2].t_ns]), np.array([1.0, 3.0]),
                  np.array([-0.1, -0.3]), np.array([0.0, math.radians(20)]))
    with RecordingWriter(tmp_path / "rec", _rig(corridor_rig), corridor_site,
                         truth_of=truth) as rec:
        for f in frames:
            rec.write(f)
    back = Recording(tmp_path / "rec").truth
    assert back.t_ns.tolist() == [frames[0].t_ns, frames[2].t_ns]   # no row for frame 1
    assert np.allclose(back.lookup(frames[2].t_ns), (3.0, -0.3, math.radians(20)))


def test_bgr_frames_are_kept_as_captured(tmp_path, corridor_rig, corridor_site):
    img = np.zeros((8, 8, 3), np.uint8)
    img[..., 2] = 200
    with RecordingWriter(tmp_path / "rec", _rig(corridor_rig, (8, 8)), corridor_site) as rec:
        rec.write(Frame(img, 5, 0))
    got = Recording(tmp_path / "rec").frame(0)
    assert got.image.shape == (8, 8, 3) and np.array_equal(got.image, img)
    assert got.grey.shape == (8, 8)


def test_writer_never_overwrites_a_recording(tmp_path, corridor_rig, corridor_site):
    with RecordingWriter(tmp_path / "rec", corridor_rig, corridor_site) as rec:
        rec.write(_frames(1)[0])
    with pytest.raises(ConfigError, match="already there"):
        RecordingWriter(tmp_path / "rec", corridor_rig, corridor_site)
    assert len(Recording(tmp_path / "rec")) == 1


def test_killed_recording_is_readable(tmp_path, corridor_rig, corridor_site):
    rec = RecordingWriter(tmp_path / "rec", corridor_rig, corridor_site)
    for f in _frames(3):
        rec.write(f)
    # no close(): rows were flushed frame by frame
    assert len(Recording(tmp_path / "rec")) == 3


def _make(tmp_path, corridor_rig, corridor_site, n=2):
    with RecordingWriter(tmp_path / "rec", _rig(corridor_rig), corridor_site) as rec:
        for f in _frames(n):
            rec.write(f)
    return tmp_path / "rec"


@pytest.mark.parametrize("text,key,words", [
    ("idx,t_ns\n0,1\n", "header", "expected `index,t_ns`"),
    ("index,t_ns\n0,abc\n", "line 2: t_ns", "integer"),
    ("index,t_ns\n0,5\n1,5\n", "line 3: t_ns", "increase"),
    ("index,t_ns\n0,5\n7,9\n", "line 3", "frames/000007.png is missing"),
    ("index,t_ns\n0\n", "line 2", "2 fields"),
    ("index,t_ns\n-1,5\n", "line 2: index", ">= 0"),
    ("index,t_ns\n1,5\n1,9\n", "line 3: index", "already listed on line 2"),
    ("index,t_ns,exposure\n0,5,1.0\n", "header", "found `index,t_ns,exposure`"),
])
def test_broken_recordings(tmp_path, corridor_rig, corridor_site, text, key, words):
    folder = _make(tmp_path, corridor_rig, corridor_site)
    (folder / "frames.csv").write_text(text)
    with pytest.raises(ConfigError) as err:
        Recording(folder)
    assert "frames.csv" in str(err.value) and key in str(err.value) and words in str(err.value)


def test_corrupt_frame_and_bad_truth(tmp_path, corridor_rig, corridor_site):
    folder = _make(tmp_path, corridor_rig, corridor_site)
    (folder / "frames" / "000001.png").write_bytes(b"not a png")
    rec = Recording(folder)
    rec.frame(0)
    bad = rec.frame(1)  # a damaged file is a damaged frame (bad_frame), not a stop
    assert bad.image.size == 0 and "000001.png: cannot decode" in bad.damage
    (folder / "truth.csv").write_text("t_ns,x,y,yaw\n")
    with pytest.raises(ConfigError, match="truth.csv: header"):
        Recording(folder)
    (folder / "truth.csv").write_text("t_ns,x,y,yaw_deg\n1,0,nan,0\n")
    with pytest.raises(ConfigError, match="line 2: y"):
        load_truth(folder / "truth.csv")


def test_poses_file_layout_and_round_trip(tmp_path):
    path = tmp_path / "out" / "poses.csv"
    with PoseWriter(path, tmp_path / "out" / "poses.tum") as w:
        w.write(PoseEstimate(10, "corridor", None, 0.25, math.radians(2.5), 0.9, 0.25), 1.5)
        w.write(Failure(20, "corridor", "too_few_lines"), 1.0)
        w.write(PoseEstimate(30, "lights", 1.0, 2.0, -0.1, 0.5), None)
    lines = path.read_text().splitlines()
    assert lines[0] == ",".join(POSES_HEADER)
    assert lines[1] == "10,,0.250000,2.500000,0.250000,corridor,0.900,1.500,,,"
    assert lines[2] == "20,,,,,corridor,0.000,1.000,,,"
    t = load_poses(path)
    assert np.isnan(t.x_m[0]) and t.x_m[2] == 1.0 and t.method == ["corridor"] * 2 + ["lights"]
    header, *rows = (tmp_path / "out" / "poses.tum").read_text().splitlines()
    assert header.startswith("# t_s x y z qx qy qz qw; written by ceilkit ")
    tum = " ".join(rows).split()
    # TUM holds only full positions: the corridor pose (no x) and the failure are left out
    assert len(tum) == 8 and tum[0] == "0.000000030" and tum[1:4] == ["1.000000", "2.000000", "0"]


def test_tum_keeps_every_nanosecond_of_epoch_stamps(tmp_path):
    t_ns = 1_718_000_000_123_456_789
    with PoseWriter(tmp_path / "poses.csv", tmp_path / "poses.tum") as w:
        w.write(PoseEstimate(t_ns, "lights", 1.0, 2.0, math.radians(90.0), 0.8), 2.0)
    t_s, x, y, z, qx, qy, qz, qw = (
        (tmp_path / "poses.tum").read_text().splitlines()[1].split())
    assert t_s == "1718000000.123456789"
    assert math.degrees(2 * math.atan2(float(qz), float(qw))) == pytest.approx(90.0)
    assert (float(z), float(qx), float(qy)) == (0.0, 0.0, 0.0)


def test_outside_tool_quirks_are_read(tmp_path, corridor_rig, corridor_site):
    """CRLF line endings, a byte-order mark, spaces after commas, indices that start
    late and have gaps, frame files that no row lists (ignored)."""
    folder = _make(tmp_path, corridor_rig, corridor_site, n=3)
    fr = folder / "frames"
    (fr / "000001.png").rename(fr / "000007.png")
    (fr / "000002.png").rename(fr / "000012.png")
    (folder / "frames.csv").write_bytes(
        b"\xef\xbb\xbfindex,t_ns\r\n0, 100\r\n7,200\r\n12,300\r\n\r\n")
    (folder / "truth.csv").write_bytes(b"t_ns,x,y,yaw_deg\r\n300,1.5,0.25,-90\r\n")
    rec = Recording(folder)
    assert list(rec.index) == [0, 7, 12] and list(rec.t_ns) == [100, 200, 300]
    assert [f.index for f in rec] == [0, 7, 12]
    assert rec.truth.lookup(300) == pytest.approx((1.5, 0.25, -math.pi / 2))


@pytest.mark.parametrize("image,words", [
    (np.zeros((24, 32), np.uint16), "8-bit"),
    (np.zeros((24, 32, 4), np.uint8), "4 channels"),
    (np.zeros((48, 64), np.uint8), "64x48 but the camera"),
])
def test_frames_the_camera_cannot_have_taken(tmp_path, corridor_rig, corridor_site, image,
                                            words):
    import cv2

    folder = _make(tmp_path, corridor_rig, corridor_site, n=1)
    cv2.imwrite(str(folder / "frames" / "000000.png"), image)
    with pytest.raises(ConfigError, match=words) as err:
        Recording(folder).frame(0)
    assert "000000.png" in str(err.value)


def test_an_empty_frame_is_a_clear_error_and_the_recording_stays_whole(
        tmp_path, corridor_rig, corridor_site):
    w = RecordingWriter(tmp_path / "rec", corridor_rig, corridor_site)
    good = np.zeros((corridor_rig.camera.height, corridor_rig.camera.width), np.uint8)
    w.write(Frame(good, 5, 0))
    with pytest.raises(OutputError, match="cannot write the frame image"):
        w.write(Frame(np.zeros((0, 0), np.uint8), 6, 1))
    w.close()
    assert len(Recording(tmp_path / "rec")) == 1


def test_poses_header_is_the_specs_and_sigmas_come_from_the_covariance(tmp_path):
    path = tmp_path / "poses.csv"
    cov = np.diag([0.01 ** 2, 0.002 ** 2, math.radians(0.5) ** 2])
    corridor_cov = np.diag([np.inf, 0.003 ** 2, math.radians(0.2) ** 2])
    with PoseWriter(path) as w:
        w.write(PoseEstimate(10, "lights", 1.0, 2.0, 0.0, 0.9, cov=cov), 1.0)
        w.write(PoseEstimate(20, "corridor", None, 0.1, 0.0, 0.9, 0.1, cov=corridor_cov), 1.0)
    lines = path.read_text().splitlines()
    assert lines[0] == ("t_ns,x,y,yaw_deg,lateral,method,quality,latency_ms,"
                        "sigma_x,sigma_y,sigma_yaw_deg")
    assert lines[1].endswith(",0.010000,0.002000,0.500000")
    assert lines[2].endswith(",,0.003000,0.200000")   # x unobserved: empty, never inf
    t = load_poses(path)
    assert t.sigma_x_m[0] == pytest.approx(0.01) and np.isnan(t.sigma_x_m[1])
    assert t.sigma_yaw_rad[1] == pytest.approx(math.radians(0.2))


def test_poses_of_the_first_eight_columns_still_read(tmp_path):
    path = tmp_path / "poses.csv"
    path.write_text("t_ns,x,y,yaw_deg,lateral,method,quality,latency_ms\n"
                    "10,1.0,2.0,90.0,,lights,0.800,1.5\n")
    t = load_poses(path)
    assert t.x_m[0] == 1.0 and t.yaw_rad[0] == pytest.approx(math.pi / 2)
    assert np.isnan(t.sigma_x_m[0])
    path.write_text("t_ns,x,y,yaw\n10,1,2,3\n")
    with pytest.raises(ConfigError, match="header.*sigma_x"):
        load_poses(path)
    path.write_text(",".join(POSES_HEADER) + "\n10,1.0,2.0,90.0,,lights,0.8,1.5,abc,,\n")
    with pytest.raises(ConfigError, match="line 2: sigma_x"):
        load_poses(path)


def test_a_failed_poses_write_is_an_output_error(tmp_path):
    (tmp_path / "file").write_text("x")  # a file where the folder should be
    with pytest.raises(OutputError, match="file: cannot create"):
        PoseWriter(tmp_path / "file" / "poses.csv")


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_a_full_disk_is_an_output_error_naming_the_file(tmp_path):
    w = PoseWriter(tmp_path / "poses.csv")
    w._csv.close()
    w._csv.fd = os.open("/dev/full", os.O_WRONLY)  # every write fails with ENOSPC
    with pytest.raises(OutputError, match="poses.csv: cannot write: No space left"):
        w.write(Failure(1, "lights", "no_lights"))
    w.close()


def test_truth_rows_without_truth_open_the_file(tmp_path, corridor_rig, corridor_site):
    with RecordingWriter(tmp_path / "rec", _rig(corridor_rig), corridor_site) as rec:
        assert not (tmp_path / "rec" / "truth.csv").exists()
        f = _frames(1)[0]
        rec.write(f)
        rec.write_truth(f.t_ns, 1.0, 2.0, 0.5)
    assert Recording(tmp_path / "rec").truth.lookup(f.t_ns) == pytest.approx((1.0, 2.0, 0.5))


def test_odometry_is_read_when_present(tmp_path, corridor_rig, corridor_site):
    folder = _make(tmp_path, corridor_rig, corridor_site)
    assert Recording(folder).odometry is None
    (folder / "odometry.csv").write_text("t_ns,dx,dy,dyaw_deg\n1000000,0.02,0.0,0.5\n"
                                         "2000000,0.021,-0.001,-90\n")
    odo = Recording(folder).odometry
    assert len(odo) == 2 and odo.t_ns.tolist() == [1_000_000, 2_000_000]
    assert odo.dx_m.tolist() == [0.02, 0.021] and odo.dy_m[1] == -0.001
    assert odo.dyaw_rad == pytest.approx(np.radians([0.5, -90.0]))


@pytest.mark.parametrize("text,key,words", [
    ("t_ns,dx,dy,dyaw\n1,0,0,0\n", "header", "expected `t_ns,dx,dy,dyaw_deg`"),
    ("t_ns,dx,dy,dyaw_deg\n1,0,0\n", "line 2", "4 fields"),
    ("t_ns,dx,dy,dyaw_deg\n1.5,0,0,0\n", "line 2: t_ns", "integer"),
    ("t_ns,dx,dy,dyaw_deg\n1,0,inf,0\n", "line 2: dy", "number"),
    ("t_ns,dx,dy,dyaw_deg\n5,0,0,0\n5,0,0,0\n", "line 3: t_ns", "increase"),
    ("t_ns,dx,dy,dyaw_deg\n123456789012345678901,0,0,0\n", "line 2: t_ns", "64-bit"),
])
def test_broken_odometry(tmp_path, corridor_rig, corridor_site, text, key, words):
    folder = _make(tmp_path, corridor_rig, corridor_site)
    (folder / "odometry.csv").write_text(text)
    with pytest.raises(ConfigError) as err:
        Recording(folder)
    assert "odometry.csv" in str(err.value) and key in str(err.value)
    assert words in str(err.value)


def test_logged_frames_replay_convert_and_repair(tmp_path, corridor_rig, corridor_site):
    from ceilkit.runtime.io.recording import LOG_DIR, read_frame_log, repair_recording

    rig = _rig(corridor_rig)
    frames = _frames(40)
    w = RecordingWriter(tmp_path / "rec", rig, corridor_site, keep_images=4)
    for f in frames:
        assert w.log(f) == f.index
    for _ in range(10):  # ten become PNGs (the first six read back from the log)
        assert w.convert_next()
    w.sync(durable=True)
    assert len(read_frame_log(tmp_path / "rec")) == 40
    # killed here: ten PNGs, thirty only in the log
    back = Recording(tmp_path / "rec")
    assert len(back) == 40 and back.logged == 30
    assert all(np.array_equal(back.frame(k).image, f.image) for k, f in enumerate(frames))
    assert repair_recording(tmp_path / "rec") == 30
    assert not (tmp_path / "rec" / LOG_DIR).exists()
    again = Recording(tmp_path / "rec")
    assert len(again) == 40 and again.logged == 0
    assert again.t_ns.tolist() == [f.t_ns for f in frames]


def test_a_closed_writer_leaves_no_log(tmp_path, corridor_rig, corridor_site):
    from ceilkit.runtime.io.recording import LOG_DIR

    with RecordingWriter(tmp_path / "rec", _rig(corridor_rig), corridor_site) as w:
        for f in _frames(35):
            w.log(f)
        while w.convert_next():
            pass
    assert not (tmp_path / "rec" / LOG_DIR).exists()
    assert len(Recording(tmp_path / "rec")) == 35


def test_existing_rig_and_site_are_not_overwritten(tmp_path, corridor_rig, corridor_site):
    (tmp_path / "rec").mkdir()
    (tmp_path / "rec" / "rig.yaml").write_text("mine")
    with pytest.raises(ConfigError, match="rig.yaml is already there"):
        RecordingWriter(tmp_path / "rec", corridor_rig, corridor_site)
    assert (tmp_path / "rec" / "rig.yaml").read_text() == "mine"
    with RecordingWriter(tmp_path / "rec", corridor_rig, corridor_site, force=True) as w:
        w.write(_frames(1)[0])
    assert Recording(tmp_path / "rec", rig=_rig(corridor_rig)).rig is not None


def test_device_of_names_the_file_system(tmp_path):
    from ceilkit.runtime.io.recording import device_of

    name = device_of(tmp_path)
    assert name.endswith(")") and " (/" in name


PUBLIC_BEFORE_THE_SPLIT = [
    "AppendFile", "CsvFile", "Disk", "FORCE_HINT", "FRAMES_HEADER", "FRAMES_PER_SEGMENT",
    "FullDisk", "GuardedRecorder", "LOG_DIR", "LoggedFrame", "ODOMETRY_HEADER", "OS_DISK",
    "Odometry", "OsDisk", "POSES_HEADER", "POSES_SIGMA_COLUMNS", "PoseTable", "PoseWriter",
    "RECORDING_FILES", "Recording", "RecordingWriter", "StoredFrames", "TRUTH_HEADER",
    "Truth", "check_frame_image", "clear_recording", "csv_line", "device_of", "frame_name",
    "guarded_log", "load_logged", "load_odometry", "load_poses", "load_truth",
    "output_error", "pose_row", "pose_sigmas", "read_frame_log", "refuse_existing",
    "repair_recording", "segment_name", "tum_line", "tum_seconds", "write_truth_tum"]
"""Every public name of io/recording.py when it was one 1131-line module."""


def test_every_name_is_still_importable_from_recording():
    """The module split by role (files, frame_log, tables, recording_reader,
    recording_writer) re-exports each name as the one object its role module defines."""
    import importlib

    from ceilkit.runtime.io import recording

    assert sorted(recording.__all__) == sorted(PUBLIC_BEFORE_THE_SPLIT)
    for name in PUBLIC_BEFORE_THE_SPLIT:
        obj = getattr(recording, name)
        home = getattr(obj, "__module__", None)
        if home is not None and home.startswith("ceilkit."):
            assert home != "ceilkit.runtime.io.recording", name   # defined once, by role
            assert getattr(importlib.import_module(home), name) is obj, name
