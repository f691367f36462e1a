"""Recordings, truth and pose files in the layouts of SPEC §2.

A recording is a folder::

    frames/000000.png ...          # 8-bit grey or BGR, as captured
    frames.csv                     # header `index,t_ns`, one row per frame
    rig.yaml, site.yaml            # as used when recording
    truth.csv                      # optional: `t_ns,x,y,yaw_deg`
    odometry.csv                   # optional: `t_ns,dx,dy,dyaw_deg`, increments in V
    frames.wal/000000.raw ...      # while recording live: the write-ahead frame log

Writing live is in two steps (:meth:`RecordingWriter.log`, then
:meth:`RecordingWriter.convert_next` on another thread): the raw frame is appended to
the write-ahead log ``frames.wal/`` with one ``writev`` (once it returns the bytes are
in the kernel's page cache, which outlives the process), before its pose is sent;
the PNG is encoded later, written atomically (by rename) before its ``frames.csv``
row, and a log segment is deleted once all its frames are PNGs (after an fsync when
``fsync_every_s`` is set). So a run killed at any instant leaves every frame whose
pose went out either as a PNG or in the log; :class:`Recording` reads both, and
:func:`repair_recording` turns the log into PNGs. :meth:`RecordingWriter.write` does
both steps at once (no log).

Every row of a CSV file is one ``write`` of the whole line, rolled back (truncated)
when it fails, so no file is ever cut mid-row. Files are written through a
:class:`Disk` (the operating system, or a fake such as :class:`FullDisk`). A file
that cannot be written is an :class:`~ceilkit.runtime.errors.OutputError` naming it
(its ``errno`` attribute says why: ``ENOSPC`` for a full disk).

The code is split by role; this module is where every name is imported from:
:mod:`~ceilkit.runtime.io.files` (the :class:`Disk`, whole-record files, output
errors), :mod:`~ceilkit.runtime.io.frame_log` (the write-ahead log),
:mod:`~ceilkit.runtime.io.tables` (``truth.csv``, ``odometry.csv``, ``poses.csv``,
TUM), :mod:`~ceilkit.runtime.io.recording_reader` (:class:`Recording`) and
:mod:`~ceilkit.runtime.io.recording_writer` (:class:`RecordingWriter`, repair, the
recorders' policy).
"""

from __future__ import annotations

from ceilkit.runtime.io.files import (
    FORCE_HINT,
    OS_DISK,
    AppendFile,
    CsvFile,
    Disk,
    FullDisk,
    OsDisk,
    csv_line,
    device_of,
    output_error,
    refuse_existing,
)
from ceilkit.runtime.io.frame_log import (
    FRAMES_PER_SEGMENT,
    LOG_DIR,
    LoggedFrame,
    load_logged,
    read_frame_log,
    segment_name,
)
from ceilkit.runtime.io.recording_reader import (
    RECORDING_FILES,
    Recording,
    StoredFrames,
    check_frame_image,
    frame_name,
)
from ceilkit.runtime.io.recording_writer import (
    GuardedRecorder,
    RecordingWriter,
    clear_recording,
    guarded_log,
    repair_recording,
)
from ceilkit.runtime.io.tables import (
    FRAMES_HEADER,
    ODOMETRY_HEADER,
    POSES_HEADER,
    POSES_SIGMA_COLUMNS,
    TRUTH_HEADER,
    Odometry,
    PoseTable,
    PoseWriter,
    Truth,
    load_odometry,
    load_poses,
    load_truth,
    pose_row,
    pose_sigmas,
    tum_line,
    tum_seconds,
    write_truth_tum,
)

__all__ = ["AppendFile", "CsvFile", "Disk", "FORCE_HINT", "FRAMES_HEADER",
           "FRAMES_PER_SEGMENT", "FullDisk", "GuardedRecorder", "LOG_DIR", "LoggedFrame",
           "ODOMETRY_HEADER", "OS_DISK", "Odometry", "OsDisk", "POSES_HEADER",
           "POSES_SIGMA_COLUMNS", "PoseTable", "PoseWriter", "RECORDING_FILES", "Recording",
           "RecordingWriter", "StoredFrames", "TRUTH_HEADER", "Truth", "check_frame_image",
           "clear_recording", "csv_line", "device_of", "frame_name", "guarded_log",
           "load_logged", "load_odometry", "load_poses", "load_truth", "output_error",
           "pose_row", "pose_sigmas", "read_frame_log", "refuse_existing",
           "repair_recording", "segment_name", "tum_line", "tum_seconds", "write_truth_tum"]
