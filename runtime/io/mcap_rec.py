"""MCAP recordings: a run (or a SPEC recording) as one ``.mcap`` file in ROS 2 message
encoding, so ``ros2 bag``, Foxglove and the ``mcap`` tools open it; read back as a
frame source for replay, converted to and from the SPEC folder (SPEC §2 stays the
default and the contract).

Channels (``ros2msg`` schemas, CDR messages, log time = the frame's capture ``t_ns``):

* ``/ceilkit/image/compressed``: ``sensor_msgs/msg/CompressedImage`` (PNG), each
  frame; the message's ``sequence`` is the frame's index;
* ``/ceilkit/pose``: ``geometry_msgs/msg/PoseWithCovarianceStamped`` in ``map``, each
  published pose;
* ``/ceilkit/detections``: ``std_msgs/msg/String``, each frame's outcome and the
  estimator's diagnostics as JSON;
* ``/ceilkit/wheel_odometry``: ``nav_msgs/msg/Odometry``, wheel odometry integrated in
  ``odom`` (the row's increment in the twist fields);
* ``/ceilkit/truth``: ``geometry_msgs/msg/PoseStamped``, ground truth (``truth.csv``);
* ``/diagnostics``: ``diagnostic_msgs/msg/DiagnosticArray``, the localizer's state;
* ``/tf``: ``tf2_msgs/msg/TFMessage``, each published pose with x and y as ``map →
  base_link`` (``map → odom`` and ``odom → base_link`` when wheel odometry is recorded),
  as the ROS 2 node publishes it (:mod:`~ceilkit.runtime.io.ros2_views`);
* ``/tf_static``: ``base_link → camera_optical_frame`` from the rig's mount, once,
  before the first image;
* ``/ceilkit/camera_info``: ``sensor_msgs/msg/CameraInfo`` from the rig's camera, with
  each image (same stamp and ``frame_id``), so Foxglove's image and 3D panels place the
  images without any layout work.

``rig.yaml`` and ``site.yaml`` (and a camera file beside them) are attachments, written
first. Crash safety: the file is written unchunked and flushed after every message,
so a SIGKILL loses nothing the loop had written (the data is in the page cache); a
file without its summary and footer (a killed run) is read record by record up to
its last whole record (:class:`McapRecording`). A frame's image is written before
its pose is published (the live loop records it first), so every frame that was
finished replays.

Example::

    convert_recording("run1", "run1.mcap")       # a SPEC folder to MCAP, and back:
    convert_recording("run1.mcap", "run1-again")
"""

from __future__ import annotations

import contextlib
import logging
import math
import shutil
import tempfile
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

import numpy as np

from ceilkit.runtime.config.inputs import require_regular_file
from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError, OutputError
from ceilkit.runtime.estimators.base import Estimate, PoseEstimate
from ceilkit.runtime.io import ros2_msgs as msgs
from ceilkit.runtime.io.images import decode_image
from ceilkit.runtime.io.outputs import (
    FolderLock,
    check_overlaps,
    claim_outputs,
    recording_inputs,
)
from ceilkit.runtime.io.provenance import version_line
from ceilkit.runtime.io.recording import (
    ODOMETRY_HEADER,
    CsvFile,
    GuardedRecorder,
    Odometry,
    Recording,
    RecordingWriter,
    StoredFrames,
    Truth,
    check_frame_image,
    guarded_log,
    refuse_existing,
)
from ceilkit.runtime.io.recording_writer import encode_png
from ceilkit.runtime.io.ros2_views import OdometryPose
from ceilkit.runtime.io.sources import Frame

log = logging.getLogger("ceilkit.mcap")

SUFFIX = ".mcap"
IMAGE_TOPIC = "/ceilkit/image/compressed"
POSE_TOPIC = "/ceilkit/pose"
DETECTIONS_TOPIC = "/ceilkit/detections"
WHEEL_ODOMETRY_TOPIC = "/ceilkit/wheel_odometry"
TRUTH_TOPIC = "/ceilkit/truth"
DIAGNOSTICS_TOPIC = "/diagnostics"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
CAMERA_INFO_TOPIC = "/ceilkit/camera_info"
CHANNELS: Mapping[str, str] = {
    IMAGE_TOPIC: "sensor_msgs/msg/CompressedImage",
    POSE_TOPIC: "geometry_msgs/msg/PoseWithCovarianceStamped",
    DETECTIONS_TOPIC: "std_msgs/msg/String",
    WHEEL_ODOMETRY_TOPIC: "nav_msgs/msg/Odometry",
    TRUTH_TOPIC: "geometry_msgs/msg/PoseStamped",
    DIAGNOSTICS_TOPIC: "diagnostic_msgs/msg/DiagnosticArray",
    TF_TOPIC: "tf2_msgs/msg/TFMessage",
    TF_STATIC_TOPIC: "tf2_msgs/msg/TFMessage",
    CAMERA_INFO_TOPIC: "sensor_msgs/msg/CameraInfo",
}
"""Topic -> ROS 2 message type of every channel."""
PROFILE = "ros2"
CAMERA_FRAME = msgs.CAMERA_FRAME
"""``frame_id`` of the images and of ``camera_info``."""


def _import_mcap():
    try:
        from mcap.writer import Writer
        from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic
    except ImportError:
        raise ConfigError(None, "record", "MCAP needs the mcap extra: pip install "
                          "'ceilkit[mcap]'") from None
    return Writer, serialize_dynamic, generate_dynamic


def is_mcap(path: str | Path) -> bool:
    """Whether ``path`` names an MCAP file (by its suffix)."""
    return str(path).lower().endswith(SUFFIX)


def replay_folder(recording: str | Path) -> Path:
    """Where a replay writes by default: ``RECORDING/replay/`` (SPEC §3), and for
    ``run.mcap`` the folder ``run.replay/`` beside it."""
    p = Path(recording)
    return p.with_suffix(".replay") if is_mcap(p) else p / "replay"


def open_recording(path: str | Path, rig: Rig | str | Path | None = None,
                   site: Site | str | Path | None = None) -> Recording | McapRecording:
    """A SPEC recording folder or an ``.mcap`` file, opened for reading."""
    if is_mcap(path):
        return McapRecording(path, rig=rig, site=site)
    return Recording(path, rig=rig, site=site)


def _image_format(image: np.ndarray) -> str:
    """image_transport's ``format`` of a PNG of ``image``."""
    return ("mono8" if image.ndim == 2 else "bgr8") + "; png compressed"


class McapWriter:
    """Writes an MCAP recording (see the module docstring); thread-safe.

    Args:
        path: the ``.mcap`` file (refused when it exists, unless ``force``).
        rig, site: attached as ``rig.yaml`` / ``site.yaml`` (``attachments`` instead:
            name -> bytes, files as they are, for a converted recording).
        truth_of: ground truth the source carries: each frame gets its truth message.

    Raises:
        ConfigError: ``path`` exists (without ``force``); the mcap extra is missing.
        OutputError: the file cannot be written.
    """

    def __init__(self, path: str | Path, rig: Rig | None = None, site: Site | None = None,
                 force: bool = False, truth_of: Truth | None = None,
                 attachments: Mapping[str, bytes] | None = None, header: str = ""):
        Writer, serialize, _ = _import_mcap()
        self.path = Path(path)
        if self.path.exists() and not force:
            raise refuse_existing(self.path, "a recording is")
        self._lock = threading.Lock()
        self._truth_of = truth_of
        self.count = 0
        self.messages = 0
        self._odo_pose = (0.0, 0.0, 0.0)
        self._rig = rig
        self._odom = OdometryPose()
        self._static_written = False
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh: IO[bytes] = open(self.path, "wb")
        except OSError as exc:
            raise OutputError(self.path, f"cannot create: {exc.strerror or exc}") from None
        self._writer = Writer(self._fh, use_chunking=False, use_summary_offsets=True)
        self._encoders: dict[str, Any] = {}
        self._channels: dict[str, int] = {}
        try:
            self._writer.start(profile=PROFILE, library="ceilkit")
            for topic, kind in CHANNELS.items():
                text = msgs.DEFINITIONS[kind]
                schema = self._writer.register_schema(kind, "ros2msg", text.encode())
                self._channels[topic] = self._writer.register_channel(topic, "cdr", schema)
                self._encoders[topic] = serialize(kind, text)[kind]
            self._writer.add_metadata("ceilkit", {"layout": "ceilkit-mcap", "version": "1",
                                                  "written_by": version_line()})
            files = dict(attachments or {})
            if not files and rig is not None and site is not None:
                files = _config_files(rig, site, header)
            for name, data in files.items():
                self._writer.add_attachment(0, 0, name, "application/yaml", data)
            self._fh.flush()
        except OSError as exc:
            self._fh.close()
            raise OutputError(self.path, f"cannot write: {exc.strerror or exc}") from None

    def _write(self, topic: str, t_ns: int, message: Mapping[str, Any],
               sequence: int = 0) -> None:
        data = self._encoders[topic](message)
        t = max(int(t_ns), 0)
        with self._lock:
            if self._fh.closed:
                return
            try:
                self._writer.add_message(self._channels[topic], t, data, t, sequence)
                self._fh.flush()  # in the page cache: a SIGKILL now loses nothing
            except OSError as exc:
                err = OutputError(self.path, f"cannot write: {exc.strerror or exc}")
                err.errno = exc.errno  # type: ignore[attr-defined]
                raise err from None
            self.messages += 1

    # -------------------------------------------------------------- what is recorded
    def write_png(self, index: int, t_ns: int, png: bytes, fmt: str) -> None:
        """A frame already PNG-encoded (``fmt``: ``mono8; png compressed`` or ``bgr8;
        ...``), after its ``camera_info`` (and, before the first, ``/tf_static``)."""
        self._write_camera(int(t_ns))
        self._write(IMAGE_TOPIC, t_ns, {"header": msgs.header(t_ns, CAMERA_FRAME),
                                        "format": fmt, "data": png}, int(index))
        self.count += 1
        pose = self._truth_of.lookup(int(t_ns)) if self._truth_of is not None else None
        if pose is not None:
            self.write_truth(int(t_ns), *pose)

    def write_frame(self, frame: Frame) -> None:
        """A frame, as PNG (then its truth, when the source has one).

        Raises:
            OutputError: not an image (``errno`` None) or the file cannot be written.
        """
        img = frame.image
        if not isinstance(img, np.ndarray) or img.dtype != np.uint8:
            img = None  # encode_png refuses it (errno None), as the folder's writer does
        png = encode_png(img, self.path)
        self.write_png(frame.index, frame.t_ns, png, _image_format(img))

    def _write_camera(self, t_ns: int) -> None:
        if self._rig is None:
            return
        if not self._static_written:
            self._static_written = True
            m = self._rig.mount
            self._write(TF_STATIC_TOPIC, t_ns, msgs.tf_msg(
                [msgs.camera_transform(m.R_vehicle_cam, m.t_vehicle_cam, t_ns)]))
        self._write(CAMERA_INFO_TOPIC, t_ns, msgs.camera_info_msg(self._rig.camera, t_ns))

    def write_pose(self, est: PoseEstimate) -> None:
        """The pose, and its ``/tf`` when it has x and y."""
        self._write(POSE_TOPIC, est.t_ns, msgs.pose_msg(est))
        odom = self._odom.at(int(est.t_ns))
        transforms = msgs.pose_transforms(est, int(est.t_ns), odom_base=odom,
                                          with_odom_base=odom is not None)
        if transforms:
            self._write(TF_TOPIC, est.t_ns, msgs.tf_msg(transforms))

    def write_detection(self, est: Estimate) -> None:
        self._write(DETECTIONS_TOPIC, est.t_ns, {"data": msgs.detection_json(est)})

    def write_diagnostics(self, t_ns: int, est: Estimate | None,
                          counts: Mapping[str, Any], fault: str | None = None) -> None:
        self._write(DIAGNOSTICS_TOPIC, t_ns, msgs.diagnostics_msg(t_ns, est, counts, fault))

    def write_truth(self, t_ns: int, x_m: float, y_m: float, yaw_rad: float) -> None:
        self._write(TRUTH_TOPIC, t_ns, msgs.pose_stamped_msg(t_ns, x_m, y_m, yaw_rad))

    def write_odometry(self, t_ns: int, dx_m: float, dy_m: float, dyaw_rad: float) -> None:
        """One wheel odometry increment (V, since the previous row), recorded as the
        integrated pose in ``odom`` with the increment itself in the twist (m, rad:
        the exact values of an ``odometry.csv`` row)."""
        with self._lock:
            x, y, yaw = self._odo_pose
            c, s = math.cos(yaw), math.sin(yaw)
            self._odo_pose = (x + c * dx_m - s * dy_m, y + s * dx_m + c * dy_m,
                              yaw + dyaw_rad)
            pose = self._odo_pose
        self._odom.set(int(t_ns), pose, external=False)
        m = msgs.wheel_odometry_msg(t_ns, *pose)
        m["twist"]["twist"]["linear"].update(x=float(dx_m), y=float(dy_m))
        m["twist"]["twist"]["angular"]["z"] = float(dyaw_rad)
        self._write(WHEEL_ODOMETRY_TOPIC, t_ns, m)

    # -------------------------------------------------------------- the live loop's API
    @property
    def pending(self) -> int:
        return 0  # nothing waits: every frame is in the file when write_frame returns

    def close(self) -> None:
        """Write the summary and the footer (a file a kill left without them reads too)."""
        with self._lock:
            if self._fh.closed:
                return
            try:
                self._writer.finish()
            except OSError as exc:
                raise OutputError(self.path, f"cannot write: {exc.strerror or exc}") \
                    from None
            finally:
                self._fh.close()

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _config_files(rig: Rig, site: Site, header: str = "") -> dict[str, bytes]:
    """``rig.yaml`` (camera inline) and ``site.yaml`` as their file bytes."""
    tmp = Path(tempfile.mkdtemp(prefix="ceilkit-mcap-"))
    try:
        rig.save(tmp / "rig.yaml", header)
        site.save(tmp / "site.yaml", header)
        return {p.name: p.read_bytes() for p in sorted(tmp.iterdir())}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


class McapRecorder(GuardedRecorder):
    """The live loop's recorder for an ``.mcap`` (what
    :class:`~ceilkit.runtime.live.AsyncRecorder` is for a folder): :meth:`write`
    puts the frame's PNG into the file on the loop's thread, before its pose goes out.
    With ``guard`` a failing disk pauses the recording (one line) instead of raising."""

    def __init__(self, writer: McapWriter, guard: Any = None):
        self.writer = writer
        self.guard = guard
        self.skipped_images = 0

    def write(self, frame: Frame) -> None:
        """Put ``frame`` into the file (see :func:`~ceilkit.runtime.io.recording.guarded_log`)."""
        guarded_log(self, lambda: self.writer.write_frame(frame), frame.index)

    def close(self) -> None:
        self.writer.close()


class McapSink:
    """A pose sink recording each frame's outcome into an :class:`McapWriter`: the pose
    (when there is one), the detection and the localizer's diagnostics; a fault
    (``set_fault``) is recorded as an ERROR diagnostic."""

    def __init__(self, writer: McapWriter, guard: Any = None):
        self.writer = writer
        self.guard = guard
        self.frames = 0
        self.poses = 0
        self.fault: str | None = None
        self._last: Estimate | None = None
        self._t_ns = 0

    def _counts(self) -> dict[str, Any]:
        return {"frames": self.frames, "poses": self.poses}

    def send(self, est: Estimate, relocalized: bool, capture_ns: int) -> None:
        self.frames += 1
        self._last, self._t_ns = est, int(est.t_ns)
        try:
            if isinstance(est, PoseEstimate):
                self.poses += 1
                self.writer.write_pose(est)
            self.writer.write_detection(est)
            self.writer.write_diagnostics(est.t_ns, est, self._counts(), self.fault)
        except OutputError as exc:
            if self.guard is None:
                raise
            self.guard.failed(exc, self.frames, "mcap")

    def set_fault(self, reason: str | None) -> None:
        self.fault = reason
        with contextlib.suppress(OutputError):
            self.writer.write_diagnostics(self._t_ns, self._last, self._counts(), reason)


# ----------------------------------------------------------------------------- reading
def read_mcap(path: str | Path) -> tuple[list[Any], dict[int, Any], dict[str, bytes],
                                          bool]:
    """Every whole message of an MCAP file, in file order, even without its summary and
    footer (a killed run): ``(messages, channels by id, attachments by name, complete)``,
    ``complete`` False when the file ends early (the last partial record is dropped).

    Raises:
        ConfigError: not an MCAP file (naming the path).
    """
    from mcap.exceptions import InvalidMagic, McapError
    from mcap.records import Attachment, Channel, DataEnd, Footer, Message
    from mcap.stream_reader import StreamReader

    path = Path(path)
    require_regular_file(path)   # a FIFO would block, a device never end
    messages: list[Any] = []
    channels: dict[int, Any] = {}
    attachments: dict[str, bytes] = {}
    complete = False
    try:
        with open(path, "rb") as fh:
            try:
                for rec in StreamReader(fh).records:
                    if isinstance(rec, Message):
                        messages.append(rec)
                    elif isinstance(rec, Channel):
                        channels[rec.id] = rec
                    elif isinstance(rec, Attachment):
                        attachments[rec.name] = bytes(rec.data)
                    elif isinstance(rec, DataEnd | Footer):
                        complete = True
                        break
            except InvalidMagic:
                raise ConfigError(path, None, "not an MCAP file (no MCAP magic at its "
                                  "start)") from None
            except (McapError, EOFError, ValueError, OSError):  # a record cut by a kill
                pass
    except FileNotFoundError:
        raise ConfigError(path, None, "file not found") from None
    except OSError as exc:
        raise ConfigError(path, None, f"cannot read: {exc}") from None
    return messages, channels, attachments, complete


class McapRecording(StoredFrames):
    """An MCAP recording opened for reading; a frame source, as
    :class:`~ceilkit.runtime.io.recording.Recording` is for a folder (same
    attributes: ``rig``, ``site``, ``truth``, ``odometry``, ``t_ns``, ``index``).

    Every whole record is read (:func:`read_mcap`): a file a killed run left replays
    every frame it holds. ``rig.yaml``/``site.yaml`` come from its attachments unless
    ``rig``/``site`` are given.

    Raises:
        ConfigError: not an MCAP file, no frames channel, stamps not increasing, a
            missing or bad rig or site (naming ``FILE:rig.yaml``).
    """

    live = False
    dropped = 0
    logged = 0

    def __init__(self, path: str | Path, rig: Rig | str | Path | None = None,
                 site: Site | str | Path | None = None):
        _, _, generate = _import_mcap()
        self.folder = self.path = Path(path)
        messages, channels, self.attachments, self.complete = read_mcap(self.path)
        topics = {cid: ch.topic for cid, ch in channels.items()}
        decode = {t: generate(k, msgs.DEFINITIONS[k])[k] for t, k in CHANNELS.items()}
        images, truth, odo = [], [], []
        self.poses: list[tuple[int, Any]] = []
        for m in messages:
            topic = topics.get(m.channel_id)
            if topic == IMAGE_TOPIC:
                msg = decode[topic](m.data)
                images.append((msgs.join_stamp(msg.header.stamp), int(m.sequence),
                               bytes(msg.data)))
            elif topic == TRUTH_TOPIC:
                msg = decode[topic](m.data)
                truth.append((msgs.join_stamp(msg.header.stamp), msg.pose.position.x,
                              msg.pose.position.y, msgs.quaternion_yaw(msg.pose.orientation)))
            elif topic == WHEEL_ODOMETRY_TOPIC:
                msg = decode[topic](m.data)
                tw = msg.twist.twist
                odo.append((msgs.join_stamp(msg.header.stamp), tw.linear.x, tw.linear.y,
                            tw.angular.z))
            elif topic == POSE_TOPIC:
                self.poses.append((int(m.log_time), decode[topic](m.data)))
        self._images = images
        self.index = np.array([i for _, i, _ in images], dtype=np.int64)
        self.t_ns = np.array([t for t, _, _ in images], dtype=np.int64)
        if self.t_ns.size > 1 and np.any(np.diff(self.t_ns) <= 0):
            bad = int(np.argmax(np.diff(self.t_ns) <= 0)) + 1
            raise ConfigError(self.path, f"{IMAGE_TOPIC}[{bad}]", "stamps must increase")
        self.rig = rig if isinstance(rig, Rig) else None
        self.site = site if isinstance(site, Site) else None
        self._load_configs(rig, site)
        self.truth = _truth(truth) if truth else None
        self.odometry = Odometry(*(np.array(c, dtype=np.int64 if k == 0 else float)
                                   for k, c in enumerate(zip(*odo, strict=True)))) \
            if odo else None
        self._i = 0

    def _load_configs(self, rig: Any, site: Any) -> None:
        need = [n for n, v in (("rig.yaml", rig), ("site.yaml", site)) if v is None]
        for name in need:
            if name not in self.attachments:
                raise ConfigError(self.path, name, "not attached: give --rig/--site")
        tmp = Path(tempfile.mkdtemp(prefix="ceilkit-mcap-"))
        try:
            for name, data in self.attachments.items():
                if "/" not in name and name not in (".", ".."):
                    (tmp / name).write_bytes(data)
            try:
                if self.rig is None:
                    self.rig = Rig.load(rig if rig is not None else tmp / "rig.yaml")
                if self.site is None:
                    self.site = Site.load(site if site is not None else tmp / "site.yaml")
            except ConfigError as exc:
                if exc.path is not None and Path(exc.path).parent == tmp:
                    raise ConfigError(f"{self.path}:{Path(exc.path).name}", exc.key,
                                      exc.detail) from None
                raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def __len__(self) -> int:
        return int(self.index.size)

    def png(self, k: int) -> bytes:
        """The k-th frame's PNG bytes, as recorded."""
        return self._images[k][2]

    def frame(self, k: int) -> Frame:
        where = f"{self.path}:{IMAGE_TOPIC}[{k}]"
        image, damage = decode_image(self._images[k][2], where)
        if image is None:  # a damaged image is a bad_frame failure, not a stop
            return Frame.damaged(damage, int(self.t_ns[k]), int(self.index[k]))
        check_frame_image(image, where, self.rig)
        return Frame(image, int(self.t_ns[k]), int(self.index[k]))



def _truth(rows: list[tuple[int, float, float, float]]) -> Truth:
    rows = sorted(rows, key=lambda r: r[0])
    t, x, y, yaw = zip(*rows, strict=True)
    return Truth(np.array(t, dtype=np.int64), np.array(x, float), np.array(y, float),
                 np.array(yaw, float))


# ---------------------------------------------------------------------------- convert
def _copy_truth(truth: Truth | None, writer: Any) -> None:
    """Every row of ``truth`` (if any) through ``writer.write_truth``."""
    if truth is None:
        return
    for k in range(truth.t_ns.size):
        writer.write_truth(int(truth.t_ns[k]), float(truth.x_m[k]), float(truth.y_m[k]),
                           float(truth.yaw_rad[k]))


def _whole(frame: Frame) -> Frame:
    """``frame``, unless it is damaged: a conversion copies frames, it cannot copy one
    that is no image (ConfigError: the damage, naming the file)."""
    if frame.damage:
        raise ConfigError(None, None, f"{frame.damage}: a damaged frame cannot be "
                          "converted")
    return frame


def convert_recording(src: str | Path, dst: str | Path, force: bool = False) -> int:
    """A SPEC recording folder to an ``.mcap`` file, or an ``.mcap`` to a SPEC folder
    (by the suffixes); the number of frames converted. Frames are lossless PNGs both
    ways (the images are identical); rig, site, ``truth.csv`` and ``odometry.csv``
    travel too, so the copy replays to identical poses.

    ``dst`` is claimed first (:func:`_claim_convert`): never the source itself nor inside
    it, locked for the whole conversion (a second conversion or a recording into it is
    refused at once).

    Raises:
        ConfigError: a bad source; ``dst`` exists (without ``force``), is the source or
            lies inside it; both or neither are ``.mcap``.
        OutputError: ``dst`` cannot be written, or another run is writing it.
    """
    src, dst = Path(src), Path(dst)
    if is_mcap(src) == is_mcap(dst):
        raise ConfigError(None, "dst", f"convert a folder to .mcap or .mcap to a folder; "
                          f"found {src} -> {dst}")
    with contextlib.ExitStack() as stack:
        _claim_convert(src, dst, force, stack)
        return _convert(src, dst, force)


def _claim_convert(src: Path, dst: Path, force: bool, stack: contextlib.ExitStack) -> None:
    """Refuse a ``dst`` that is ``src`` or lies inside it (``ConfigError`` keyed ``dst``),
    then lock it until ``stack`` closes: an ``.mcap`` by the lock a recording into it
    takes (``.NAME.lock`` beside it; :class:`McapWriter` refuses it when it exists), a
    folder by its :class:`~ceilkit.runtime.io.outputs.FolderLock`
    (:class:`RecordingWriter` refuses a recording in it)."""
    if not src.exists():      # before any output folder (or its lock) is made
        raise ConfigError(src, None, "not a recording (not found)")
    inputs = [*recording_inputs(src), src]   # the whole recording folder, not only its parts
    if is_mcap(dst):
        check_overlaps(inputs, {"dst": [dst]})
        stack.enter_context(FolderLock(dst.parent, f".{dst.name}.lock", subject=dst))
    else:
        claim_outputs({}, folders={"dst": [dst]}, inputs=inputs, force=force, stack=stack)


def _convert(src: Path, dst: Path, force: bool) -> int:
    """:func:`convert_recording` once ``dst`` is claimed."""
    if is_mcap(dst):
        rec = Recording(src)
        files = {p.name: p.read_bytes() for p in sorted(src.glob("*.yaml"))}
        with McapWriter(dst, rig=rec.rig, force=force, attachments=files) as w:
            for k in range(len(rec)):
                f = _whole(rec.frame(k))
                w.write_png(int(rec.index[k]), f.t_ns, encode_png(f.image, src),
                            _image_format(f.image))
            _copy_truth(rec.truth, w)
            if rec.odometry is not None:
                od = rec.odometry
                for k in range(len(od)):
                    w.write_odometry(int(od.t_ns[k]), float(od.dx_m[k]), float(od.dy_m[k]),
                                     float(od.dyaw_rad[k]))
        return len(rec)
    mrec = McapRecording(src)
    with RecordingWriter(dst, mrec.rig, mrec.site, truth=mrec.truth is not None,
                         force=force) as w:
        for k in range(len(mrec)):
            f = _whole(mrec.frame(k))
            w.write(Frame(f.image, f.t_ns, k))
        _copy_truth(mrec.truth, w)
    if mrec.odometry is not None:
        od = mrec.odometry
        out = CsvFile(dst / "odometry.csv", ODOMETRY_HEADER)
        try:
            for k in range(len(od)):
                out.row([int(od.t_ns[k]), repr(float(od.dx_m[k])), repr(float(od.dy_m[k])),
                         repr(math.degrees(float(od.dyaw_rad[k])))])
        finally:
            out.close()
    return len(mrec)


def mcap_summary(path: str | Path) -> dict[str, Any]:
    """What an MCAP file holds: message counts per topic, attachments, and whether it
    ends with its summary and footer (``complete``; False after a kill)."""
    messages, channels, attachments, complete = read_mcap(path)
    counts: dict[str, int] = {}
    for m in messages:
        t = channels[m.channel_id].topic if m.channel_id in channels else "?"
        counts[t] = counts.get(t, 0) + 1
    return {"complete": complete, "messages": counts, "attachments": sorted(attachments)}


__all__ = ["CHANNELS", "McapRecorder", "McapRecording", "McapSink", "McapWriter",
           "convert_recording", "is_mcap", "mcap_summary", "open_recording", "read_mcap",
           "replay_folder"]
