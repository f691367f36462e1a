"""Reading a SPEC recording folder (:class:`Recording`, also a frame source), its PNGs
and the frames a killed run left in the write-ahead log; the folder's layout
(:data:`RECORDING_FILES`, :func:`frame_name`) and the check of a frame's image.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ceilkit.runtime.config.rig import Rig
from ceilkit.runtime.config.site import Site
from ceilkit.runtime.errors import ConfigError
from ceilkit.runtime.io.frame_log import LOG_DIR, load_logged, read_frame_log
from ceilkit.runtime.io.images import read_image
from ceilkit.runtime.io.sources import Frame, SourceBase
from ceilkit.runtime.io.tables import (
    FRAMES_HEADER,
    int_field,
    load_odometry,
    load_truth,
    read_rows,
    stamp_column,
)

log = logging.getLogger("ceilkit.recording")

RECORDING_FILES = ("frames.csv", "frames", LOG_DIR, "rig.yaml", "site.yaml", "truth.csv",
                   "odometry.csv")
"""What a recording folder may hold; a folder holding any of them is not written over
unless told (``force``)."""


def frame_name(index: int) -> str:
    return f"{index:06d}.png"


def check_frame_image(image: np.ndarray, path: str | Path, rig: Rig) -> None:
    """Raise a ConfigError naming ``path`` unless ``image`` is what SPEC §2 allows and
    the rig's camera expects: 8-bit grey ``(H, W)`` or BGR ``(H, W, 3)``, ``W x H`` the
    camera's ``image_width x image_height``."""
    if image.dtype != np.uint8:
        raise ConfigError(path, None, f"expected an 8-bit image, found {image.dtype} "
                          "(convert to 8-bit grey or BGR)")
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3))):
        what = f"{image.shape[2]} channels" if image.ndim == 3 else f"{image.ndim} dimensions"
        raise ConfigError(path, None, f"expected grey or BGR, found {what}")
    h, w = image.shape[:2]
    cam = rig.camera
    if (w, h) != (cam.width, cam.height):
        raise ConfigError(path, None, f"the image is {w}x{h} but the camera "
                          f"({rig.camera_file or rig.source or 'the rig'}) is "
                          f"{cam.width}x{cam.height}: a frame must come from the calibrated "
                          "camera at its calibrated size")


class StoredFrames(SourceBase):
    """A recording's frames read in order (``read``) by index (``frame(k)``): the
    shared half of :class:`Recording` and the MCAP recording."""

    _i = 0

    def __len__(self) -> int:
        raise NotImplementedError

    def frame(self, k: int) -> Frame:
        raise NotImplementedError

    def read(self) -> Frame | None:
        if self._i >= len(self):
            return None
        f = self.frame(self._i)
        self._i += 1
        return f


class Recording(StoredFrames):
    """A SPEC recording opened for reading; also a frame source.

    The whole folder is checked when opened: ``frames.csv`` header and rows, every
    frame file present, stamps increasing, ``rig.yaml`` and ``site.yaml`` valid
    (unless ``rig``/``site`` override them), ``truth.csv`` and ``odometry.csv`` when
    present (``truth``, ``odometry``: ``None`` when absent). Frames still in the
    write-ahead log of a killed run (``frames.wal/``) are frames too (``logged``
    counts them; :func:`repair_recording` makes them PNGs). A ``truth.csv`` none of
    whose stamps is a frame's is warned about (errors against it cannot be measured).
    """

    live = False  # stored stamps: the live loop stamps frames with its own clock
    dropped = 0

    def __init__(self, folder: str | Path, rig: Rig | str | Path | None = None,
                 site: Site | str | Path | None = None):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise ConfigError(self.folder, None, "not a recording folder (not found)")
        fpath = self.folder / "frames.csv"
        rows = read_rows(fpath, FRAMES_HEADER)
        index = [int_field(fpath, n, "index", r[0]) for n, r in enumerate(rows, start=2)]
        seen: dict[int, int] = {}
        for n, i in enumerate(index, start=2):
            if not 0 <= i < 2**63:
                raise ConfigError(fpath, f"line {n}: index", f"expected an integer >= 0, "
                                  f"found {i}")
            if i in seen:
                raise ConfigError(fpath, f"line {n}: index",
                                  f"index {i} already listed on line {seen[i]}")
            seen[i] = n
        t_ns = stamp_column(fpath, [r[1:] for r in rows]).tolist()
        for n, i in enumerate(index, start=2):
            if not (self.folder / "frames" / frame_name(int(i))).exists():
                raise ConfigError(fpath, f"line {n}",
                                  f"frame file frames/{frame_name(int(i))} is missing")
        self._logged = {e.index: e for e in read_frame_log(self.folder) if e.index not in seen}
        for e in sorted(self._logged.values(), key=lambda e: e.index):
            index.append(e.index)
            t_ns.append(e.t_ns)
        self.index = np.array(index, dtype=np.int64)
        self.t_ns = np.array(t_ns, dtype=np.int64)
        if self.t_ns.size > 1 and np.any(np.diff(self.t_ns) <= 0):
            bad = int(np.argmax(np.diff(self.t_ns) <= 0)) + 1
            where = f"line {bad + 2}" if bad < len(rows) else f"{LOG_DIR} frame {index[bad]}"
            raise ConfigError(fpath, f"{where}: t_ns", "stamps must increase")
        self.rig = rig if isinstance(rig, Rig) else Rig.load(
            rig if rig is not None else self.folder / "rig.yaml")
        self.site = site if isinstance(site, Site) else Site.load(
            site if site is not None else self.folder / "site.yaml")
        tpath = self.folder / "truth.csv"
        self.truth = load_truth(tpath) if tpath.exists() else None
        if self.truth is not None and self.t_ns.size and self.truth.t_ns.size \
                and not np.isin(self.t_ns, self.truth.t_ns).any():
            log.warning("%s: none of its %d stamps is a frame's stamp in frames.csv: "
                        "errors against truth cannot be measured", tpath,
                        self.truth.t_ns.size)
        opath = self.folder / "odometry.csv"
        self.odometry = load_odometry(opath) if opath.exists() else None
        self._i = 0

    @property
    def logged(self) -> int:
        """Frames read from the write-ahead log (a killed run's last frames)."""
        return len(self._logged)

    def __len__(self) -> int:
        return int(self.index.size)

    def frame(self, k: int) -> Frame:
        """The k-th frame listed in ``frames.csv`` (then in the write-ahead log); a frame
        file that is no whole image (cut short) is a damaged frame naming it
        (:meth:`Frame.damaged <ceilkit.runtime.io.sources.Frame.damaged>`)."""
        i = int(self.index[k])
        entry = self._logged.get(i)
        if entry is not None:
            image, path = load_logged(entry), entry.path
        else:
            path = self.folder / "frames" / frame_name(i)
            image, damage = read_image(path)
            if image is None:  # a damaged file is a bad_frame failure, not a stop
                return Frame.damaged(damage, int(self.t_ns[k]), i)
        check_frame_image(image, path, self.rig)
        return Frame(image, int(self.t_ns[k]), i)
