"""A damaged frame is a failure, not a pose (issue 40, item 2): a truncated JPEG or PNG
in a recording or an image folder is a ``bad_frame`` failure naming the file, never
handed to an estimator, counted in the summary and written as a failed row."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from ceilkit.runtime.estimators.base import Failure, PoseEstimate
from ceilkit.runtime.io.capture import ImageFolderSource
from ceilkit.runtime.io.images import decode_image, structure_damage
from ceilkit.runtime.io.recording import Recording, load_poses
from ceilkit.runtime.io.sources import Frame
from ceilkit.runtime.pipeline import ListSink, Pipeline
from ceilkit.runtime.replay import replay
from ceilkit.runtime.session import SessionConfig, run_session
from helpers import FIXTURES

REC = FIXTURES / "corridor_rec"
BAD = 2  # the damaged frame's index


def _image() -> np.ndarray:
    return cv2.imread(str(REC / "frames" / "000000.png"), cv2.IMREAD_UNCHANGED)


def _encoded(ext: str) -> bytes:
    return cv2.imencode(ext, _image())[1].tobytes()


CUTS = {  # name -> (the file's bytes, the reason's words; "" for a whole image)
    "jpeg whole": (_encoded(".jpg"), ""),
    "jpeg padded with zeros": (_encoded(".jpg") + b"\x00" * 16, ""),
    "png whole": (_encoded(".png"), ""),
    "jpeg cut in half": (_encoded(".jpg")[:2000], "truncated JPEG"),
    "jpeg without its end marker": (_encoded(".jpg")[:-2], "truncated JPEG"),
    "png cut in half": (_encoded(".png")[:3000], "truncated PNG"),
    "png without IEND": (_encoded(".png")[:-12], "truncated PNG"),
    "empty file": (b"", "empty file"),
    "not an image": (b"hello, world", "cannot decode"),
}


@pytest.mark.parametrize("name", sorted(CUTS))
def test_a_file_is_whole_or_its_damage_is_named(name):
    data, words = CUTS[name]
    image, damage = decode_image(data, "f/000002.jpg")
    if not words:
        assert damage == "" and structure_damage(data) == "" and image.shape[:2] == (480, 640)
    else:
        assert image is None and damage.startswith("f/000002.jpg: ") and words in damage


def _damage(path, kind: str) -> None:
    """Replace ``path`` by the ``kind`` (jpeg, png) encoding of its image, cut short."""
    data = _encoded(".jpg" if kind == "jpeg" else ".png")
    path.write_bytes(data[: len(data) // 2])


@pytest.mark.parametrize("kind", ["png", "jpeg"])
def test_a_damaged_recording_frame_is_a_failed_row(tmp_path, kind, log_lines):
    rec = shutil.copytree(REC, tmp_path / "rec")
    bad = rec / "frames" / f"{BAD:06d}.png"
    _damage(bad, kind)
    frame = Recording(rec).frame(BAD)
    assert frame.image.size == 0 and str(bad) in frame.damage
    res = replay(rec, tmp_path / "o", method="corridor", track=False)
    assert res.telemetry.frames == 8 and res.telemetry.failures["bad_frame"] == 1
    assert any("bad_frame 1" in line for line in res.lines())
    poses = load_poses(tmp_path / "o" / "poses.csv")
    assert poses.t_ns.size == 8 and np.isnan(poses.x_m[BAD]) and np.isnan(poses.y_m[BAD])
    assert [ln for ln in log_lines if str(bad) in ln] == [
        f"frame {BAD}: {frame.damage}: no pose from it (bad_frame)"]


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_a_damaged_image_in_a_folder_is_a_failed_row(tmp_path, suffix, log_lines):
    folder = tmp_path / "images"
    folder.mkdir()
    for k in range(4):
        (folder / f"{k:02d}{suffix}").write_bytes(
            cv2.imencode(suffix, cv2.imread(str(REC / "frames" / f"{k:06d}.png")))[1])
    bad = folder / f"01{suffix}"
    _damage(bad, "jpeg" if suffix == ".jpg" else "png")
    with ImageFolderSource(folder) as src:
        frames = list(src)
    assert [bool(f.damage) for f in frames] == [False, True, False, False]
    res = run_session(SessionConfig(device=str(folder), rig=REC / "rig.yaml",
                                    site=REC / "site.yaml", method="corridor",
                                    out=tmp_path / "o"))
    tel = res.telemetry
    assert tel.frames == 4 and tel.failures["bad_frame"] == 1
    assert load_poses(tmp_path / "o" / "poses.csv").t_ns.size == 4
    assert any(str(bad) in ln and "bad_frame" in ln for ln in log_lines)


class _Counting:
    """A fake estimator that counts the images it was given."""

    name = "fake"

    def __init__(self) -> None:
        self.seen = 0

    def estimate(self, image, t_ns, prior=None):
        self.seen += 1
        return PoseEstimate(t_ns, self.name, 0.0, 0.0, 0.0, 0.9)


def test_the_estimator_never_sees_a_damaged_frame():
    est, sink = _Counting(), ListSink()
    pipe = Pipeline(est, [sink])
    out = pipe.process(Frame.damaged("f/1.jpg: truncated JPEG", 5, 1), capture_ns=5)
    assert isinstance(out, Failure) and out.reason == "bad_frame"
    assert out.detail == "f/1.jpg: truncated JPEG" and out.method == "fake"
    assert est.seen == 0 and sink.items == [(out, False)]
    assert pipe.telemetry.failures == {"bad_frame": 1}
