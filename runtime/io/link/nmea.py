"""NMEA 0183 proprietary sentences for a pose stream to a microcontroller.

Pure, byte-exact encoders and a decoder; the port handling is in
:mod:`ceilkit.runtime.io.link.transport`. Two sentences (``P`` = proprietary,
``CEI`` = the talker, then ``L`` pose or ``S`` status), ASCII, each at most
:data:`MAX_SENTENCE_LEN` = 82 characters including ``\\r\\n``, as NMEA 0183 asks::

    $PCEIL,<seq>,<t_ms>,<status>,<x>,<y>,<yaw_deg>,<quality>,<method>*hh\\r\\n
    $PCEIS,<seq>,<t_ms>,<state>,<reason>,<age_ms>*hh\\r\\n

Fields (see ``docs/serial.md`` for the full table):

* ``seq``: message counter, 0..65535, wrapping; shared by both sentences, so a gap
  means a message was dropped.
* ``t_ms``: for ``PCEIL`` the frame's capture time, for ``PCEIS`` the link's clock,
  both integer milliseconds modulo 2**32 (wraps like an Arduino's ``millis()``).
* ``status``: ``A`` a valid pose, ``V`` no pose for this frame (all pose fields empty).
* ``x``, ``y``: vehicle position in W (SPEC §1), metres, 3 decimals, |v| <= 99999.999;
  empty where the method cannot observe it (the corridor method has no x).
* ``yaw_deg``: heading in W, degrees counter-clockwise from +x, 2 decimals, in
  [-180.00, 180.00).
* ``quality``: confidence in [0, 1], 2 decimals.
* ``method``: the estimator's name, at most 14 characters of ``[A-Za-z0-9_.-]``.
* ``state``: ``V`` running but no valid pose, ``F`` the localizer is faulted.
* ``reason``: a short code (the last failure's reason), at most 24 characters.
* ``age_ms``: milliseconds since the last valid pose's capture, capped at 9999999,
  empty if there never was one.
* ``hh``: XOR of every character between ``$`` and ``*``, two upper-case hex digits.

Example::

    >>> encode_pose(PoseEstimate(t_ns=12_345_000_000, method="lights", x_m=1.5,
    ...             y_m=-0.25, yaw_rad=math.pi / 2, quality=0.9), seq=7)
    b'$PCEIL,7,12345,A,1.500,-0.250,90.00,0.90,lights*07\\r\\n'
"""

from __future__ import annotations

import functools
import math
import re
import struct
from dataclasses import dataclass

from ceilkit.runtime.errors import LinkError
from ceilkit.runtime.estimators.base import Estimate, PoseEstimate

MAX_SENTENCE_LEN = 82
SEQ_MODULO = 65536
TIME_MODULO = 2**32
MAX_ABS_POSITION_M = 99999.999
MAX_METHOD_LEN = 14
MAX_REASON_LEN = 24
MAX_AGE_MS = 9_999_999

POSE_TALKER = "PCEIL"
STATUS_TALKER = "PCEIS"

_SAFE = re.compile(r"[^A-Za-z0-9_.\-]")


def checksum(body: str) -> str:
    """XOR of the characters of ``body`` (what lies between ``$`` and ``*``), as 2 hex digits.

    >>> checksum("PCEIS,0,0,V,none,")
    '3C'
    """
    return _HEX[_xor(body.encode("ascii"))]


def _xor(data: bytes) -> int:
    # XOR of the bytes, 8 at a time as big integers (a sentence is a few such words)
    n = len(data)
    pad = data + bytes(-n % 8)
    c = 0
    for (word,) in _WORDS.iter_unpack(pad):
        c ^= word
    c ^= c >> 32
    c ^= c >> 16
    c ^= c >> 8
    return c & 0xFF


_WORDS = struct.Struct("<Q")
_HEX = tuple(f"{c:02X}" for c in range(256))


def _sentence(body: str) -> bytes:
    raw = body.encode("ascii")
    out = b"$%b*%b\r\n" % (raw, _HEX[_xor(raw)].encode("ascii"))
    if len(out) > MAX_SENTENCE_LEN:  # cannot happen with the clamps below; a guard, not a check
        raise LinkError(f"NMEA sentence of {len(out)} characters exceeds {MAX_SENTENCE_LEN}")
    return out


@functools.lru_cache(maxsize=256)
def safe_token(text: str, max_len: int) -> str:
    """``text`` with NMEA-reserved characters replaced by ``_``, cut to ``max_len``."""
    return _SAFE.sub("_", text)[:max_len]


def _fmt_fixed(value: float, decimals: int) -> str:
    s = f"{value:.{decimals}f}"
    if s[0] == "-" and not s.strip("-0."):  # no "-0.000"
        s = s[1:]
    return s


def _fmt_position(v_m: float | None) -> str:
    if v_m is None:
        return ""
    return _fmt_fixed(v_m, 3)


def _fmt_yaw_deg(yaw_rad: float) -> str:
    deg = math.degrees(yaw_rad)
    deg = (deg + 180.0) % 360.0 - 180.0
    s = _fmt_fixed(deg, 2)
    if s == "180.00":  # rounding up to the open end of [-180, 180)
        s = "-180.00"
    return s


def _position_ok(v_m: float | None) -> bool:
    return v_m is None or (math.isfinite(v_m) and abs(v_m) <= MAX_ABS_POSITION_M)


def pose_is_sendable(est: Estimate) -> bool:
    """True when ``est`` is a pose every field of which fits the sentence.

    A pose with a non-finite yaw, a non-finite position, a position beyond
    +-99999.999 m or neither coordinate observed is sent as ``V`` (no pose),
    never clamped into a wrong number.
    """
    if not isinstance(est, PoseEstimate):
        return False
    if est.x_m is None and est.y_m is None:
        return False
    return (math.isfinite(est.yaw_rad) and _position_ok(est.x_m) and _position_ok(est.y_m))


def encode_pose(est: Estimate, seq: int, t_ms: int | None = None) -> bytes:
    """One ``$PCEIL`` sentence for an estimate (a pose, or ``V`` for a failure).

    Args:
        est: a :class:`PoseEstimate` (status ``A``) or :class:`Failure` (status ``V``,
            pose fields empty). A pose that does not fit (see :func:`pose_is_sendable`)
            is sent as ``V``.
        seq: message counter; taken modulo 65536.
        t_ms: capture time in ms; defaults to ``est.t_ns // 1_000_000``; taken modulo 2**32.

    Returns:
        ASCII bytes ending in ``\\r\\n``, at most 82 of them.
    """
    t = est.t_ns // 1_000_000 if t_ms is None else int(t_ms)
    head = f"{POSE_TALKER},{int(seq) % SEQ_MODULO},{t % TIME_MODULO}"
    method = safe_token(est.method, MAX_METHOD_LEN)
    if isinstance(est, PoseEstimate) and pose_is_sendable(est):
        q = est.quality if math.isfinite(est.quality) else 0.0
        q = min(1.0, max(0.0, q))
        fields = ["A", _fmt_position(est.x_m), _fmt_position(est.y_m),
                  _fmt_yaw_deg(est.yaw_rad), _fmt_fixed(q, 2), method]
    else:
        fields = ["V", "", "", "", "", method]
    return _sentence(head + "," + ",".join(fields))


def encode_status(seq: int, t_ms: int, *, faulted: bool = False, reason: str = "",
                  age_ms: int | None = None) -> bytes:
    """One ``$PCEIS`` sentence: the link is alive but there is no valid pose.

    Args:
        seq: message counter; taken modulo 65536.
        t_ms: the link's clock in ms; taken modulo 2**32.
        faulted: ``F`` when the localizer is faulted, else ``V`` (running, no pose).
        reason: a short code, sanitized and cut to 24 characters.
        age_ms: ms since the last valid pose's capture (capped at 9999999), or ``None``.

    >>> encode_status(3, 1000, reason="too_few_lines", age_ms=2500)
    b'$PCEIS,3,1000,V,too_few_lines,2500*7E\\r\\n'
    """
    age = "" if age_ms is None else str(min(MAX_AGE_MS, max(0, int(age_ms))))
    body = (f"{STATUS_TALKER},{int(seq) % SEQ_MODULO},{int(t_ms) % TIME_MODULO},"
            f"{'F' if faulted else 'V'},{safe_token(reason, MAX_REASON_LEN)},{age}")
    return _sentence(body)


# ---------------------------------------------------------------------------- decoding


@dataclass(frozen=True)
class NmeaPose:
    """A decoded ``$PCEIL``: ``x_m``/``y_m``/``yaw_deg``/``quality`` are ``None`` when empty."""

    seq: int
    t_ms: int
    valid: bool
    x_m: float | None
    y_m: float | None
    yaw_deg: float | None
    quality: float | None
    method: str


@dataclass(frozen=True)
class NmeaStatus:
    """A decoded ``$PCEIS``."""

    seq: int
    t_ms: int
    faulted: bool
    reason: str
    age_ms: int | None


def _opt_float(s: str) -> float | None:
    return float(s) if s else None


def decode(sentence: bytes | str) -> NmeaPose | NmeaStatus:
    """Parse and validate one sentence (with or without the trailing ``\\r\\n``).

    Raises:
        LinkError: framing, length, checksum, talker or a field is wrong; the
            message says which.
    """
    text = sentence.decode("ascii") if isinstance(sentence, bytes | bytearray) else sentence
    full_len = len(text) + (0 if text.endswith("\r\n") else 2)
    text = text.rstrip("\r\n")
    if full_len > MAX_SENTENCE_LEN:
        raise LinkError(f"NMEA sentence of {full_len} characters exceeds {MAX_SENTENCE_LEN}")
    if not text.startswith("$") or len(text) < 4 or text[-3] != "*":
        raise LinkError(f"not an NMEA sentence with a checksum: {text!r}")
    body, given = text[1:-3], text[-2:]
    if checksum(body) != given:
        raise LinkError(f"NMEA checksum mismatch: computed {checksum(body)}, found {given}")
    parts = body.split(",")
    try:
        if parts[0] == POSE_TALKER and len(parts) == 9:
            _, seq, t_ms, status, x, y, yaw, q, method = parts
            if status not in ("A", "V"):
                raise ValueError(f"status {status!r}")
            return NmeaPose(int(seq), int(t_ms), status == "A", _opt_float(x), _opt_float(y),
                            _opt_float(yaw), _opt_float(q), method)
        if parts[0] == STATUS_TALKER and len(parts) == 6:
            _, seq, t_ms, state, reason, age = parts
            if state not in ("V", "F"):
                raise ValueError(f"state {state!r}")
            return NmeaStatus(int(seq), int(t_ms), state == "F", reason,
                              int(age) if age else None)
    except ValueError as exc:
        raise LinkError(f"bad field in {parts[0]} sentence: {exc}") from None
    raise LinkError(f"unknown sentence {parts[0]!r} with {len(parts) - 1} fields")


def split_sentences(buffer: bytes) -> tuple[list[bytes], bytes]:
    """Complete ``\\n``-terminated lines in ``buffer`` and the incomplete rest.

    Used to read back what a controller sends: each line is returned without
    ``\\r\\n``; the rest is kept (bounded by the caller) until more bytes arrive.
    """
    *lines, rest = buffer.split(b"\n")
    return [ln.rstrip(b"\r") for ln in lines if ln.strip()], rest

