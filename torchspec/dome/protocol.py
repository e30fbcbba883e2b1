"""The dome's serial protocol, version 1: pure functions that encode and parse its lines.

Both ends use them: :class:`~torchspec.dome.client.DomeClient` on the host and
:class:`~torchspec.dome.emulator.DomeEmulator` in place of the firmware. ``docs/dome-protocol.md``
is the full specification, written for firmware authors; this module is its reference implementation.

A line is ASCII, at most :data:`MAX_LINE` bytes with its ``\\n``::

    request:  <seq> <COMMAND> [args...] *<CC>\\n         e.g. "7 MOVE 45.000 90.000 *3D\\n"
    reply:    <seq> ok [key=value...] *<CC>\\n           e.g. "7 ok *A8\\n"
              <seq> err <CODE> [message] *<CC>\\n

``seq`` is a decimal in 1..65535 chosen by the host and echoed by the reply (0 in the reply to a
request the device could not read), ``CC`` the CRC-8 of every byte before `` *`` as two
upper-case hex digits. Angles are degrees on the wire and radians in the Python API.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

from ..errors import TorchspecError

__all__ = [
    "COMMANDS",
    "ERROR_CODES",
    "MAX_LINE",
    "PROTOCOL_VERSION",
    "SEQ_MAX",
    "Command",
    "DomeIdentity",
    "DomeStatus",
    "FrameError",
    "Reply",
    "Request",
    "crc8",
    "encode_reply",
    "encode_request",
    "error_hint",
    "format_degrees",
    "format_fraction",
    "identity_values",
    "next_seq",
    "parse_degrees",
    "parse_fraction",
    "parse_identity",
    "parse_number",
    "parse_reply",
    "parse_request",
    "parse_status",
    "status_values",
]

PROTOCOL_VERSION = 1
"""The version ``ID`` reports as ``protocol=``; bumped for any change a version-1 host would misread."""

MAX_LINE = 160
"""The longest line, in bytes with its ``\\n``, either end may send."""

SEQ_MAX = 65535
"""Request sequence numbers run 1..SEQ_MAX and wrap to 1; 0 is reserved (see :class:`Reply`)."""


@dataclass(frozen=True)
class Command:
    """One command of the protocol: its argument syntax (for messages and docs), whether resending
    it is harmless (idempotent), and whether it starts a motion the host then polls to its end."""

    args: str
    idempotent: bool
    motion: bool
    summary: str


COMMANDS: dict[str, Command] = {
    "ID": Command("", True, False, "identify: model, firmware version, protocol version"),
    "STATUS": Command("", True, False, "position, motion, light and latched fault"),
    "HOME": Command("", True, True, "drive to theta = phi = 0, arm = 0; clears a latched fault"),
    "MOVE": Command("THETA PHI", True, True, "drive to (theta, phi), degrees: theta 0..90, phi 0..<360"),
    "ARM": Command("EXTENSION", True, True, "drive the arm to an extension in 0..1"),
    "LIGHT": Command("ON|OFF [INTENSITY]", True, False, "switch the light; optional intensity 0..1"),
    "JOG": Command("DTHETA DPHI", False, True, "drive by (dtheta, dphi) degrees from where it is: never resent"),
}
"""Every command a version-1 device understands, by name."""

ERROR_CODES: dict[str, str] = {
    "BADFRAME": "the request line was not a frame (no ' *CC' trailer, bad sequence number, not ASCII, too long)",
    "CHECKSUM": "the request's checksum did not match its bytes (corrupted on the wire)",
    "UNKNOWN": "no such command",
    "BADARG": "wrong number or syntax of arguments",
    "RANGE": "an argument is outside its range",
    "NOTHOMED": "a motion before the first HOME since power-up (the position is not known)",
    "FAULTED": "a fault is latched; HOME clears it",
    "MOTOR": "a motor stalled or over-currented during a motion; the motion stopped where it was",
    "INTERNAL": "the firmware failed (a bug)",
}
"""Every error code a version-1 device may send in ``err CODE message``, with its meaning. The
codes a latched fault can show in ``STATUS`` (``fault=``) are among them (``MOTOR``)."""

_HINTS = {
    "BADFRAME": "The request was corrupted on the wire; check the cable and the baud rate.",
    "CHECKSUM": "The request was corrupted on the wire; check the cable and the baud rate.",
    "UNKNOWN": "The firmware does not implement this command; compare its ID with docs/dome-protocol.md.",
    "BADARG": "The host sent a malformed command; this is a bug in the host software.",
    "RANGE": "Keep theta in [0, pi/2], phi finite, arm extension and intensity in [0, 1].",
    "NOTHOMED": "Home the dome first (torchspec acquire homes it before the first move).",
    "FAULTED": "Check the dome for an obstruction, then home it to clear the fault (acquire --resume homes it).",
    "MOTOR": "Check the dome for an obstruction, then home it to clear the fault (acquire --resume homes it).",
    "INTERNAL": "Power-cycle the dome and report the firmware bug.",
}


class FrameError(TorchspecError):
    """A line that is not a valid frame; ``code`` is ``BADFRAME`` or ``CHECKSUM``, the error code a
    device answers it with."""

    def __init__(self, message: str, code: str = "BADFRAME") -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Request:
    """A host-to-device line: ``seq`` in 1..65535, an upper-case command and its argument tokens."""

    seq: int
    command: str
    args: tuple[str, ...] = ()


@dataclass(frozen=True)
class Reply:
    """A device-to-host line: ``ok`` with ``values`` (``code`` None), or ``err`` with ``code`` and
    ``message``. ``seq`` echoes the request's, or is 0 when the request could not be read."""

    seq: int
    values: dict[str, str] = field(default_factory=dict)
    code: str | None = None
    message: str = ""

    @property
    def ok(self) -> bool:
        return self.code is None


def crc8(data: bytes) -> int:
    """CRC-8 with polynomial 0x07 (x^8 + x^2 + x + 1), initial value 0, no reflection, no final XOR
    (the catalogue's "CRC-8", check value ``crc8(b"123456789") == 0xF4``).

    Example:
        >>> f"{crc8(b'1 ID'):02X}"
        'C1'
    """
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


_SEQ = re.compile(r"0|[1-9][0-9]{0,4}")
_COMMAND = re.compile(r"[A-Z][A-Z0-9_]*")
_TOKEN = re.compile(r"[!-)+-~]+")  # printable, no space, no '*'
_KEY = re.compile(r"[a-z][a-z0-9_]*")
_MESSAGE = re.compile(r"[ -)+-~]*")  # printable with spaces, no '*'
_NUMBER = re.compile(r"-?[0-9]{1,6}(\.[0-9]{1,6})?")


def _frame(body: str) -> bytes:
    data = body.encode("ascii")
    line = data + b" *" + f"{crc8(data):02X}".encode("ascii") + b"\n"
    if len(line) > MAX_LINE:
        raise TorchspecError(f"a frame must be at most {MAX_LINE} bytes; got {len(line)} for {body!r}. Shorten it.")
    return line


def _unframe(line: bytes) -> tuple[int, list[str]]:
    """The sequence number and the remaining space-separated words of a checked frame."""
    if len(line) > MAX_LINE:
        raise FrameError(f"a frame must be at most {MAX_LINE} bytes; got {len(line)}")
    if not line.endswith(b"\n"):
        raise FrameError(f"a frame must end with a newline; got {line[-20:]!r}")
    data = line[:-2] if line.endswith(b"\r\n") else line[:-1]
    if any(not 0x20 <= byte <= 0x7E for byte in data):
        raise FrameError(f"a frame must be printable ASCII; got {line!r}")
    body, star, check = data.partition(b" *")
    if not star or b"*" in body or re.fullmatch(rb"[0-9A-F]{2}", check) is None:
        raise FrameError(f"a frame must end with ' *' and two upper-case hex digits; got {line!r}")
    expected = crc8(body)
    if int(check, 16) != expected:
        raise FrameError(
            f"a frame's checksum must be {expected:02X} for its bytes; got {check.decode()} in {line!r}", "CHECKSUM"
        )
    words = body.decode("ascii").split(" ")
    if _SEQ.fullmatch(words[0]) is None or int(words[0]) > SEQ_MAX:
        raise FrameError(f"a frame must start with a sequence number in 0..{SEQ_MAX}; got {words[0]!r} in {line!r}")
    return int(words[0]), words[1:]


def encode_request(request: Request) -> bytes:
    """The line for ``request``, checksum and newline included.

    Example:
        >>> encode_request(Request(7, "MOVE", ("45.000", "90.000")))
        b'7 MOVE 45.000 90.000 *3D\\n'
    """
    if not 1 <= request.seq <= SEQ_MAX:
        raise TorchspecError(f"a request's seq must be in 1..{SEQ_MAX}; got {request.seq}.")
    if _COMMAND.fullmatch(request.command) is None:
        raise TorchspecError(f"a command must be upper-case letters, digits and '_'; got {request.command!r}.")
    for arg in request.args:
        if _TOKEN.fullmatch(arg) is None:
            raise TorchspecError(f"an argument must be printable ASCII without spaces or '*'; got {arg!r}.")
    return _frame(" ".join((str(request.seq), request.command, *request.args)))


def parse_request(line: bytes) -> Request:
    """The request a line carries; :class:`FrameError` (code ``BADFRAME`` or ``CHECKSUM``) if the
    line is not exactly what :func:`encode_request` writes (a ``\\r`` before the ``\\n`` is allowed).

    Example:
        >>> parse_request(b"7 MOVE 45.000 90.000 *3D\\n")
        Request(seq=7, command='MOVE', args=('45.000', '90.000'))
    """
    seq, words = _unframe(line)
    if seq == 0:
        raise FrameError(f"a request's sequence number must be in 1..{SEQ_MAX}; got 0 in {line!r}")
    if not words or _COMMAND.fullmatch(words[0]) is None:
        raise FrameError(f"a request must name an upper-case command after its sequence number; got {line!r}")
    if any(_TOKEN.fullmatch(word) is None for word in words[1:]):
        raise FrameError(f"a request's arguments must be separated by single spaces; got {line!r}")
    return Request(seq, words[0], tuple(words[1:]))


def encode_reply(reply: Reply) -> bytes:
    """The line for ``reply``, checksum and newline included.

    Example:
        >>> encode_reply(Reply(7))
        b'7 ok *A8\\n'
        >>> encode_reply(Reply(8, code="RANGE", message="theta must be in 0..90"))
        b'8 err RANGE theta must be in 0..90 *CD\\n'
    """
    if not 0 <= reply.seq <= SEQ_MAX:
        raise TorchspecError(f"a reply's seq must be in 0..{SEQ_MAX}; got {reply.seq}.")
    if reply.ok:
        for key, value in reply.values.items():
            if _KEY.fullmatch(key) is None or _TOKEN.fullmatch(value) is None or "=" in value:
                raise TorchspecError(f"a reply value must be key=value (key [a-z][a-z0-9_]*); got {key!r}={value!r}.")
        return _frame(" ".join([str(reply.seq), "ok", *(f"{key}={value}" for key, value in reply.values.items())]))
    if _COMMAND.fullmatch(reply.code) is None:
        raise TorchspecError(f"an error code must be upper-case letters, digits and '_'; got {reply.code!r}.")
    if _MESSAGE.fullmatch(reply.message) is None:
        raise TorchspecError(f"an error message must be printable ASCII without '*'; got {reply.message!r}.")
    return _frame(f"{reply.seq} err {reply.code}" + (f" {reply.message}" if reply.message else ""))


def parse_reply(line: bytes) -> Reply:
    """The reply a line carries; :class:`FrameError` if it is not exactly what :func:`encode_reply`
    writes (a ``\\r`` before the ``\\n`` is allowed).

    Example:
        >>> parse_reply(b"8 err RANGE theta must be in 0..90 *CD\\n").code
        'RANGE'
    """
    seq, words = _unframe(line)
    if words[:1] == ["ok"]:
        values = {}
        for word in words[1:]:
            key, equals, value = word.partition("=")
            if not equals or _KEY.fullmatch(key) is None or _TOKEN.fullmatch(value) is None or "=" in value:
                raise FrameError(f"an ok reply must carry key=value words; got {word!r} in {line!r}")
            if key in values:
                raise FrameError(f"an ok reply must name each key once; got {key!r} twice in {line!r}")
            values[key] = value
        return Reply(seq, values)
    if words[:1] == ["err"] and len(words) >= 2 and _COMMAND.fullmatch(words[1]) is not None:
        return Reply(seq, code=words[1], message=" ".join(words[2:]))
    raise FrameError(f"a reply must be '<seq> ok ...' or '<seq> err CODE ...'; got {line!r}")


def next_seq(seq: int) -> int:
    """The sequence number after ``seq``: 1..SEQ_MAX, wrapping to 1 (0 is never a request's)."""
    return seq % SEQ_MAX + 1


def error_hint(code: str) -> str:
    """What to do about a device error code (empty for a code this version does not know)."""
    return _HINTS.get(code, "")


# Values: angles are degrees with 3 decimals on the wire (0.001 deg = 17 microradians), fractions
# (arm extension, intensity) 4 decimals; fixed point keeps firmware free of float formatting.


def parse_number(text: str) -> float:
    """A wire number: optional '-', up to 6 digits, optional '.' and up to 6 decimals; no exponent,
    no inf or nan. Raises TorchspecError otherwise."""
    if _NUMBER.fullmatch(text) is None:
        raise TorchspecError(f"a number must look like -12.345 (no exponent); got {text!r}")
    return float(text)


def format_degrees(radians: float) -> str:
    """An angle in radians as wire degrees, e.g. ``format_degrees(math.pi / 4) == "45.000"``."""
    text = f"{math.degrees(radians):.3f}"
    return "0.000" if text == "-0.000" else text


def parse_degrees(text: str) -> float:
    """Wire degrees as radians."""
    return math.radians(parse_number(text))


def format_fraction(value: float) -> str:
    """A fraction in [0, 1] as a wire number, e.g. ``format_fraction(0.5) == "0.5000"``."""
    text = f"{value:.4f}"
    return "0.0000" if text == "-0.0000" else text


def parse_fraction(text: str) -> float:
    """A wire fraction (arm extension, intensity) as a float."""
    return parse_number(text)


@dataclass(frozen=True)
class DomeIdentity:
    """What ``ID`` reports: the model and firmware names and the protocol version it speaks."""

    model: str
    firmware: str
    protocol: int


@dataclass(frozen=True)
class DomeStatus:
    """What ``STATUS`` reports, in the Python API's units: theta (from the zenith) and phi (azimuth
    from +x towards +y) in radians, arm extension and light intensity in [0, 1], and the latched
    fault's code (None when there is none)."""

    theta: float
    phi: float
    arm: float
    moving: bool
    light: bool
    intensity: float
    fault: str | None


def identity_values(identity: DomeIdentity) -> dict[str, str]:
    """The ``ok`` values of an ``ID`` reply."""
    return {"model": identity.model, "firmware": identity.firmware, "protocol": str(identity.protocol)}


def parse_identity(reply: Reply) -> DomeIdentity:
    """The identity an ``ID`` reply carries; TorchspecError naming the missing or malformed key."""
    values = _required(reply, ("model", "firmware", "protocol"))
    if re.fullmatch(r"[0-9]{1,5}", values["protocol"]) is None:
        raise TorchspecError(f"protocol must be a decimal integer; got {values['protocol']!r}")
    return DomeIdentity(values["model"], values["firmware"], int(values["protocol"]))


def status_values(status: DomeStatus) -> dict[str, str]:
    """The ``ok`` values of a ``STATUS`` reply."""
    return {
        "theta": format_degrees(status.theta),
        "phi": format_degrees(status.phi),
        "arm": format_fraction(status.arm),
        "moving": str(int(status.moving)),
        "light": str(int(status.light)),
        "intensity": format_fraction(status.intensity),
        "fault": status.fault or "-",
    }


def parse_status(reply: Reply) -> DomeStatus:
    """The status a ``STATUS`` reply carries; TorchspecError naming the missing or malformed key. Keys
    this version does not know are ignored (a newer firmware may add some)."""
    values = _required(reply, ("theta", "phi", "arm", "moving", "light", "intensity", "fault"))
    for key in ("moving", "light"):
        if values[key] not in ("0", "1"):
            raise TorchspecError(f"{key} must be 0 or 1; got {values[key]!r}")
    fault = values["fault"]
    if fault != "-" and _COMMAND.fullmatch(fault) is None:
        raise TorchspecError(f"fault must be '-' or an error code; got {fault!r}")
    return DomeStatus(
        theta=parse_degrees(values["theta"]),
        phi=parse_degrees(values["phi"]),
        arm=parse_fraction(values["arm"]),
        moving=values["moving"] == "1",
        light=values["light"] == "1",
        intensity=parse_fraction(values["intensity"]),
        fault=None if fault == "-" else fault,
    )


def _required(reply: Reply, keys: tuple[str, ...]) -> dict[str, str]:
    missing = [key for key in keys if key not in reply.values]
    if missing:
        raise TorchspecError(f"the reply must carry {', '.join(keys)}; got no {', '.join(missing)}")
    return reply.values
