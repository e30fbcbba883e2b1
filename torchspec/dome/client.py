"""The host's side of the dome protocol: a pyserial client that moves the light and switches it.

Every call sends one request and waits for its reply with a deadline. A reply that does not come,
or comes garbled, is asked for again with the same sequence number after a growing pause, but only
for idempotent commands (the device answers a resent request from its cache without acting twice);
anything else stops with a :class:`DomeError` naming the port, the command and what was received.
Motions (``home``, ``move``, ``arm``) return once the dome reports it stopped, polling ``STATUS``
for up to ``move_timeout`` seconds. See ``docs/dome-protocol.md``.
"""

from __future__ import annotations

import errno
import math
import os
import termios
import threading
import time
from typing import NoReturn

import serial

from ..errors import TorchspecError
from .protocol import (
    COMMANDS,
    MAX_LINE,
    PROTOCOL_VERSION,
    SEQ_MAX,
    DomeIdentity,
    DomeStatus,
    FrameError,
    Reply,
    Request,
    encode_request,
    error_hint,
    format_degrees,
    format_fraction,
    next_seq,
    parse_identity,
    parse_reply,
    parse_status,
)

__all__ = [
    "DomeClient",
    "DomeDisconnected",
    "DomeError",
    "DomeFault",
    "DomeIdentity",
    "DomeProtocolError",
    "DomeStatus",
    "DomeTimeout",
]

_READ_SLICE = 0.05
"""Longest single wait on the port, in seconds: reads loop on slices until their own deadline."""

_POLL = 0.02
"""Pause between ``STATUS`` polls while the dome moves, in seconds."""

_SHOWN = 80
"""Bytes of a received line quoted in an error message."""

_PORT_ERRORS = (serial.SerialException, OSError, termios.error)
"""What a vanished port raises: pyserial's error, an OSError (EIO), or termios.error (tcflush, tcdrain)."""


class DomeError(OSError):
    """The base of every dome error. Its message names the port and the command; ``port``,
    ``command`` (the request as sent, without its sequence number) and ``received`` (the last
    bytes read, or None) are attributes too."""

    def __init__(
        self, message: str, *, port: str | None = None, command: str | None = None, received: bytes | None = None
    ) -> None:
        super().__init__(message)
        self.port = port
        self.command = command
        self.received = received

    def __str__(self) -> str:
        return self.args[0]


class DomeTimeout(DomeError):
    """No complete reply within the timeout, after the allowed retries (or a motion that did not
    end within ``move_timeout``)."""


class DomeProtocolError(DomeError):
    """A reply that is not a valid frame (garbled, bad checksum) or does not carry what the
    command needs, after the allowed retries; or a device speaking another protocol version."""


class DomeFault(DomeError):
    """The device refused or failed the command: ``err CODE message``, or a fault latched during a
    motion (``STATUS`` reports ``fault=CODE``). ``code`` and ``message`` are the device's."""

    def __init__(
        self,
        message: str,
        *,
        code: str,
        device_message: str = "",
        port: str | None = None,
        command: str | None = None,
        received: bytes | None = None,
    ) -> None:
        super().__init__(message, port=port, command=command, received=received)
        self.code = code
        self.message = device_message


class DomeDisconnected(DomeError):
    """The port vanished: the device was unplugged or powered off, or its emulator stopped."""


class DomeClient:
    """A light dome on a serial port, opened with exclusive access (a second client on the same
    port fails with :class:`DomeError`).

    Args:
        port: the serial device, e.g. ``/dev/ttyACM0`` or the path a :class:`DomeEmulator` prints.
        timeout: seconds to wait for each reply.
        retries: how many times an idempotent request is resent after no reply or a garbled one.
        backoff: seconds before the first resend; doubled for each further one.
        move_timeout: seconds a motion may take before :class:`DomeTimeout`.
        baudrate: the port's speed (irrelevant for USB CDC devices and the emulator).

    Example:
        >>> with DomeClient("/dev/ttyACM0") as dome:  # doctest: +SKIP
        ...     dome.home()
        ...     dome.move(math.radians(30), math.radians(90))
        ...     dome.light(True, 0.8)
    """

    def __init__(
        self,
        port: str,
        *,
        timeout: float = 2.0,
        retries: int = 3,
        backoff: float = 0.05,
        move_timeout: float = 60.0,
        baudrate: int = 115200,
    ) -> None:
        for name, value in (("timeout", timeout), ("move_timeout", move_timeout)):
            if not (math.isfinite(value) and value > 0):
                raise TorchspecError(f"{name} must be a positive number of seconds; got {value}.")
        if not (isinstance(retries, int) and retries >= 0):
            raise TorchspecError(f"retries must be an integer >= 0; got {retries!r}.")
        if not (math.isfinite(backoff) and backoff >= 0):
            raise TorchspecError(f"backoff must be a number of seconds >= 0; got {backoff}.")
        self.port = port
        self.timeout = timeout
        self.retries = retries
        self.backoff = backoff
        self.move_timeout = move_timeout
        self._lock = threading.Lock()
        # A random start keeps a new session's first request from matching the previous session's
        # last one, which the device would take for a resend and answer from its cache.
        self._seq = int.from_bytes(os.urandom(2), "big") % SEQ_MAX + 1
        self._pending = b""
        self._gone: str | None = None  # why the port vanished, once it has
        try:
            self._serial = serial.Serial(
                port, baudrate, timeout=min(timeout, _READ_SLICE), write_timeout=timeout, exclusive=True
            )
        except serial.SerialException as cause:
            if cause.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                raise DomeError(
                    f"dome port {port} must be free; got it locked by another program ({cause}). Close the other "
                    "DomeClient, acquisition or terminal using it.",
                    port=port,
                ) from cause
            raise DomeError(
                f"dome port {port} must be a serial device that opens; got {cause}. Check the cable and the name "
                "(ls /dev/serial/by-id/); for the emulator use the path it printed.",
                port=port,
            ) from cause
        except ValueError as cause:  # pyserial's check of the baud rate and the like
            raise TorchspecError(f"dome port {port} settings must be valid; got {cause}.") from cause

    def __enter__(self) -> DomeClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Release the port (idempotent)."""
        try:
            self._serial.close()
        except _PORT_ERRORS:
            pass  # a vanished port is closed already as far as the caller is concerned

    def __repr__(self) -> str:
        return f"DomeClient({self.port!r}, {'open' if self._serial.is_open else 'closed'})"

    # The agreed API.

    def identify(self) -> DomeIdentity:
        """The device's model, firmware and protocol version; :class:`DomeProtocolError` if the
        device speaks another protocol version than this client (:data:`PROTOCOL_VERSION`)."""
        reply, text = self._call("ID")
        identity = self._decode(parse_identity, reply, text)
        if identity.protocol != PROTOCOL_VERSION:
            raise DomeProtocolError(
                f"dome at {self.port}: ID must report protocol {PROTOCOL_VERSION}; got protocol {identity.protocol} "
                f"({identity.model} firmware {identity.firmware}). Use a torchspec that speaks it, or update the "
                "firmware.",
                port=self.port,
                command=text,
            )
        return identity

    def status(self) -> DomeStatus:
        """Position (radians), motion, light and latched fault, as the device reports them now."""
        reply, text = self._call("STATUS")
        return self._decode(parse_status, reply, text)

    def home(self) -> None:
        """Drive to the home position (theta = phi = 0, arm retracted) and clear a latched fault;
        returns once the dome is at rest there."""
        self._motion("HOME")

    def move(self, theta: float, phi: float) -> None:
        """Drive the light to ``theta`` (radians from the zenith, in [0, pi/2]) and ``phi``
        (radians of azimuth from +x towards +y, any finite value); returns once it stopped."""
        if not (math.isfinite(theta) and math.isfinite(phi)):
            raise TorchspecError(f"theta and phi must be finite radians; got theta={theta}, phi={phi}.")
        wire_theta = format_degrees(theta)
        if not 0 <= float(wire_theta) <= 90:
            raise TorchspecError(f"theta must be in [0, pi/2] radians; got {theta} ({wire_theta} degrees).")
        wire_phi = format_degrees(math.remainder(phi, 2 * math.pi) % (2 * math.pi))
        if wire_phi == "360.000":
            wire_phi = "0.000"
        self._motion("MOVE", wire_theta, wire_phi)

    def arm(self, extension: float) -> None:
        """Drive the arm to ``extension`` in [0, 1] (0 retracted); returns once it stopped."""
        self._motion("ARM", self._fraction("extension", extension))

    def light(self, on: bool, intensity: float | None = None) -> None:
        """Switch the light on or off; ``intensity`` in [0, 1] sets its level too (None keeps it)."""
        args = ("ON" if on else "OFF",) + (() if intensity is None else (self._fraction("intensity", intensity),))
        self._call("LIGHT", *args)

    # Beyond the agreed API.

    def jog(self, dtheta: float, dphi: float) -> None:
        """Drive by (``dtheta``, ``dphi``) radians from where the dome is. Not idempotent, so a lost
        or garbled reply is never resent: it raises, and :meth:`status` tells where the dome went."""
        if not (math.isfinite(dtheta) and math.isfinite(dphi)):
            raise TorchspecError(f"dtheta and dphi must be finite radians; got dtheta={dtheta}, dphi={dphi}.")
        self._motion("JOG", format_degrees(dtheta), format_degrees(dphi))

    # The exchange.

    @staticmethod
    def _fraction(name: str, value: float) -> str:
        text = format_fraction(value) if math.isfinite(value) else "nan"
        if not (math.isfinite(value) and 0 <= float(text) <= 1):
            raise TorchspecError(f"{name} must be in [0, 1]; got {value}.")
        return text

    def _motion(self, command: str, *args: str) -> None:
        _, text = self._call(command, *args)
        deadline = time.monotonic() + self.move_timeout
        while True:
            status = self.status()
            if status.fault is not None:
                raise DomeFault(
                    f"dome at {self.port}: {text} must end at rest without a fault; got fault {status.fault} at theta="
                    f"{math.degrees(status.theta):.3f} phi={math.degrees(status.phi):.3f} deg, arm={status.arm:.4f}. "
                    f"{error_hint(status.fault)}",
                    code=status.fault,
                    device_message="latched during the motion",
                    port=self.port,
                    command=text,
                )
            if not status.moving:
                return
            if time.monotonic() > deadline:
                raise DomeTimeout(
                    f"dome at {self.port}: {text} must finish within move_timeout={self.move_timeout} s; got still "
                    f"moving at theta={math.degrees(status.theta):.3f} phi={math.degrees(status.phi):.3f} deg. Raise "
                    "move_timeout for a slow dome, or check it for an obstruction.",
                    port=self.port,
                    command=text,
                )
            time.sleep(_POLL)

    def _decode(self, decode, reply: Reply, text: str):
        try:
            return decode(reply)
        except ValueError as cause:
            raise DomeProtocolError(
                f"dome at {self.port}: the reply to {text} must carry what the protocol says; got {cause}. Compare the "
                "firmware with docs/dome-protocol.md.",
                port=self.port,
                command=text,
            ) from cause

    def _call(self, command: str, *args: str) -> tuple[Reply, str]:
        """Send one request and return its ``ok`` reply and the request's text (for messages)."""
        text = " ".join((command, *args))
        idempotent = COMMANDS[command].idempotent
        with self._lock:
            if self._gone is not None:
                raise DomeDisconnected(
                    f"dome at {self.port}: {text} needs the port; got it gone earlier ({self._gone})."
                    " Reconnect the dome and open a new DomeClient.",
                    port=self.port,
                    command=text,
                )
            if not self._serial.is_open:
                raise DomeError(
                    f"dome at {self.port}: {text} needs an open client; got a closed one. Open a new DomeClient.",
                    port=self.port,
                    command=text,
                )
            self._seq = next_seq(self._seq)
            seq = self._seq
            line = encode_request(Request(seq, command, args))
            attempts = 1 + self.retries
            problem, received, withheld = "", None, False
            for attempt in range(attempts):
                if attempt:
                    time.sleep(self.backoff * 2 ** (attempt - 1))
                    self._flush(text)
                self._write(line, text)
                reply, problem, received = self._await(seq, text)
                if reply is not None and reply.seq == seq:
                    if reply.ok:
                        return reply, text
                    raise DomeFault(
                        f"dome at {self.port}: {text} (seq {seq}) must succeed; got err {reply.code} "
                        f"{reply.message!r}. {error_hint(reply.code)}",
                        code=reply.code,
                        device_message=reply.message,
                        port=self.port,
                        command=text,
                        received=received,
                    )
                # A device that could not read the request (seq 0: corrupted on the way) did not act
                # on it: resending is safe for any command. Otherwise only idempotent ones are resent.
                if reply is None and not idempotent:
                    withheld = True
                    break
            tried = f"{attempt + 1} attempt{'s' if attempt else ''}"
            shown = "nothing" if not received else repr(received[:_SHOWN])
            if withheld:
                why = f"; not resent: {command} is not idempotent and may have been acted on"
                fix = "Check status() before sending it again."
            elif problem == "timeout":
                why, fix = "", "The port stopped answering: check that the dome is powered and on this port."
            else:
                why, fix = "", "Check the cable and that both ends use the same baud rate."
            if problem == "timeout":
                raise DomeTimeout(
                    f"dome at {self.port}: {text} (seq {seq}) must be answered within {self.timeout} s; got no "
                    f"complete reply after {tried} (last received: {shown}){why}. {fix}",
                    port=self.port,
                    command=text,
                    received=received,
                )
            raise DomeProtocolError(
                f"dome at {self.port}: the reply to {text} (seq {seq}) must be a valid frame; got {shown} ({problem}) "
                f"after {tried}{why}. {fix}",
                port=self.port,
                command=text,
                received=received,
            )

    def _await(self, seq: int, text: str) -> tuple[Reply | None, str, bytes | None]:
        """The reply to ``seq`` (or a seq-0 rejection) read before the timeout, or None with why not
        ("timeout", a frame error, or the device's rejection) and the last bytes received."""
        deadline = time.monotonic() + self.timeout
        received = None
        while True:
            line = self._read_line(deadline, text)
            if line is None:
                return None, "timeout", received or (self._pending or None)
            received = line
            try:
                reply = parse_reply(line)
            except FrameError as cause:
                return None, str(cause), received
            if reply.seq == seq:
                return reply, "", received
            if reply.seq == 0 and not reply.ok:  # the device could not read what we sent
                return reply, f"the device could not read the request: {reply.code} {reply.message}", received
            # Any other sequence number is the late answer to an earlier request: skip it.

    def _read_line(self, deadline: float, text: str) -> bytes | None:
        """One line (with its newline) read before ``deadline``, or None; a line longer than the
        protocol allows is returned cut, to fail as a frame."""
        while b"\n" not in self._pending and len(self._pending) <= MAX_LINE:
            if time.monotonic() >= deadline:
                return None
            try:
                waiting = self._serial.in_waiting
                chunk = self._serial.read(max(1, min(waiting, 4096)))
            except _PORT_ERRORS as cause:
                self._vanished(cause, text)
            self._pending += chunk
        line, newline, rest = self._pending.partition(b"\n")
        self._pending = rest
        return line + newline

    def _write(self, line: bytes, text: str) -> None:
        try:
            self._serial.write(line)
            self._serial.flush()
        except serial.SerialTimeoutException as cause:
            raise DomeTimeout(
                f"dome at {self.port}: {text} must be written within {self.timeout} s; got the port blocked "
                f"({cause}). Check the flow control and that the dome reads its port.",
                port=self.port,
                command=text,
            ) from cause
        except _PORT_ERRORS as cause:
            self._vanished(cause, text)

    def _flush(self, text: str) -> None:
        """Drop stale input (a garbled line's rest, a late reply) before a resend."""
        self._pending = b""
        try:
            self._serial.reset_input_buffer()
        except _PORT_ERRORS as cause:
            self._vanished(cause, text)

    def _vanished(self, cause: BaseException, text: str) -> NoReturn:
        shown = OSError(*cause.args) if isinstance(cause, termios.error) and len(cause.args) == 2 else cause
        self._gone = str(shown)  # termios.error's own str is a bare tuple
        self.close()
        raise DomeDisconnected(
            f"dome at {self.port}: the port must stay connected during {text}; got {shown}. Reconnect the dome (or "
            "restart its emulator) and open a new DomeClient.",
            port=self.port,
            command=text,
        ) from cause
