"""Frame images read from files, damage reported as a value (issue 40).

A frame file that is cut short or cannot be decoded must never reach an estimator as an
image: OpenCV's ``imread`` returns a partly grey image for a truncated JPEG, and the only
sign is libjpeg's unattributed ``Premature end of JPEG file`` on stderr. So the file's
structure is checked before it is decoded (a JPEG must start with the start-of-image
marker ``FF D8`` and end with the end-of-image marker ``FF D9``; a PNG must start with
its signature and end with its ``IEND`` chunk), and a file that fails, or that the
decoder refuses, is *damage*: a one-line reason naming the file, which the sources turn
into a damaged :class:`~ceilkit.runtime.io.sources.Frame` and the pipeline into a
``bad_frame`` :class:`~ceilkit.runtime.estimators.base.Failure`.

Example::

    image, damage = read_image("frames/000003.jpg")
    if damage:      # "frames/000003.jpg: truncated JPEG (no end-of-image marker FF D9)"
        ...
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

JPEG_SOI = b"\xff\xd8"
JPEG_EOI = b"\xff\xd9"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"
"""The whole ``IEND`` chunk (length 0, type, CRC): the last 12 bytes of a PNG."""


def structure_damage(data: bytes) -> str:
    """Why ``data`` is not a whole JPEG or PNG file, or ``""`` (other formats: ``""``,
    the decoder decides). Trailing zero bytes after a JPEG's end marker (a camera's
    padding) are allowed."""
    if not data:
        return "empty file"
    if data.startswith(JPEG_SOI):
        if not data.rstrip(b"\x00").endswith(JPEG_EOI):
            return "truncated JPEG (no end-of-image marker FF D9)"
    elif data.startswith(PNG_SIGNATURE):
        if not data.endswith(PNG_IEND):
            return "truncated PNG (no IEND chunk at its end)"
    return ""


def decode_image(data: bytes, name: str | Path) -> tuple[np.ndarray | None, str]:
    """``(image, "")`` for the whole image file ``data``, as stored (grey or BGR,
    ``cv2.IMREAD_UNCHANGED``), or ``(None, reason)`` naming ``name`` when it is damaged
    or cannot be decoded."""
    why = structure_damage(data)
    if not why:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is not None and image.size:
            return image, ""
        why = "cannot decode the image (corrupt or not an image file)"
    return None, f"{name}: {why}"


def read_image(path: str | Path) -> tuple[np.ndarray | None, str]:
    """:func:`decode_image` of the file ``path``; a file that cannot be read is damage
    too (``(None, "PATH: cannot read: ...")``)."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        return None, f"{path}: cannot read: {exc.strerror or exc}"
    return decode_image(data, path)
