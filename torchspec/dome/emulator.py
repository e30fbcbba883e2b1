"""A virtual dome speaking the protocol on a pseudo-terminal, for tests and for developing without
the hardware.

:class:`DomeEmulator` opens a pty pair (``os.openpty``) and answers on the master side in a
background thread, so a client opens ``.port`` (the slave's path) like any serial device. Motions
take real time (``speed`` in rad/s); faults are injected on request: a reply dropped or garbled,
the device stalling, the port vanishing, a motor fault. ``torchspec dome-emulator`` serves one
from the command line.

Example:
    >>> with DomeEmulator(speed=10.0) as dome, DomeClient(dome.port) as client:  # doctest: +SKIP
    ...     dome.inject("drop")           # the next reply is lost: the client resends
    ...     client.move(0.5, 1.0)
    ...     dome.motions
    1
"""

from __future__ import annotations

import collections
import math
import os
import select
import threading
import time
import tty
from dataclasses import dataclass

from ..errors import TorchspecError
from .protocol import (
    COMMANDS,
    MAX_LINE,
    PROTOCOL_VERSION,
    DomeIdentity,
    DomeStatus,
    FrameError,
    Reply,
    Request,
    encode_reply,
    format_degrees,
    identity_values,
    parse_degrees,
    parse_fraction,
    parse_request,
    status_values,
)

__all__ = ["FAULTS", "DomeEmulator", "parse_fault", "serve"]

FAULTS = {
    "drop": "act on the request but send no reply (a reply lost on the wire)",
    "garble": "act on the request and send its reply with one byte corrupted",
    "corrupt": "the request arrives corrupted: answer `0 err CHECKSUM` without acting on it",
    "stall": "freeze for `seconds` before acting on the request (requests meanwhile queue up)",
    "disconnect": "close the port instead of answering: the device vanished",
    "motor": "the next motion stops halfway with a MOTOR fault (only motion commands trigger it)",
}
"""The faults :meth:`DomeEmulator.inject` accepts, and what each does."""

_TAU = 2 * math.pi


@dataclass
class _Fault:
    kind: str
    count: int
    command: str | None
    seconds: float


@dataclass
class _Motion:
    start: tuple[float, float, float]  # theta, phi, arm where it began
    delta: tuple[float, float, float]  # signed travel; phi's along the shorter arc
    began: float  # time.monotonic()
    duration: float
    fails_at: float | None  # the fraction of the motion where a motor fault stops it


class DomeEmulator:
    """A dome on a pseudo-terminal.

    Args:
        speed: angular speed of theta and phi, radians per second (motions are coordinated: both
            axes and the arm arrive together, at the slowest one's pace).
        arm_speed: arm extension per second.
        stall_seconds: how long a ``stall`` fault freezes the device unless ``inject`` says.
        homed: whether the position is known at power-up; if False, motions other than HOME
            answer ``err NOTHOMED`` until the first HOME, as real firmware must.
        model, firmware, protocol: what ``ID`` reports.
    """

    def __init__(
        self,
        *,
        speed: float = math.radians(30),
        arm_speed: float = 0.25,
        stall_seconds: float = 1.0,
        homed: bool = True,
        model: str = "TSDOME-EMU",
        firmware: str = "1.0.0",
        protocol: int = PROTOCOL_VERSION,
    ) -> None:
        for name, value in (("speed", speed), ("arm_speed", arm_speed)):
            if not (math.isfinite(value) and value > 0):
                raise TorchspecError(f"{name} must be a positive finite number per second; got {value}.")
        self.speed = speed
        self.arm_speed = arm_speed
        self.stall_seconds = stall_seconds
        self.identity = DomeIdentity(model, firmware, protocol)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self._port: str | None = None
        self._faults: list[_Fault] = []
        self._last: tuple[Request, bytes] | None = None  # the last request acted on, and its reply
        self._position = (0.0, 0.0, 0.0)
        self._motion: _Motion | None = None
        self._homed = homed
        self._fault: str | None = None
        self._light = False
        self._intensity = 1.0
        self._motions = 0
        self._executed: collections.Counter[str] = collections.Counter()
        self._received: collections.Counter[str] = collections.Counter()
        self.disconnected = False

    # Life cycle.

    @property
    def port(self) -> str:
        """The slave pty's path, e.g. ``/dev/pts/3``: what a client opens."""
        if self._port is None:
            raise RuntimeError("the emulator must be started before its port exists; call start() or use `with`.")
        return self._port

    def start(self) -> DomeEmulator:
        """Open the pty pair and serve in a background thread."""
        if self._thread is not None:
            raise RuntimeError(f"the emulator on {self._port} is already started.")
        self._master, self._slave = os.openpty()
        # Raw, so nothing echoes back or turns \n into \r\n before a client configures the port;
        # the emulator keeps the slave open so that a client closing it does not hang up the master.
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self._port = os.ttyname(self._slave)
        self._thread = threading.Thread(target=self._serve, name=f"dome-emulator {self._port}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the pty pair (idempotent): a connected client sees the port vanish."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)
        self._close()

    def __enter__(self) -> DomeEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def serving(self) -> bool:
        """Whether the background thread still answers (False after stop() or a disconnect)."""
        return self._thread is not None and self._thread.is_alive()

    # What tests look at.

    def inject(self, kind: str, count: int = 1, command: str | None = None, *, seconds: float | None = None) -> None:
        """Make the next ``count`` requests (of ``command`` only, if given) suffer ``kind``, one of
        :data:`FAULTS`. A resent request suffers it too (``drop`` with ``count=3`` loses three
        replies); ``motor`` is used up only by a motion that is acted on. ``seconds`` is a stall's
        length (default ``stall_seconds``)."""
        if kind not in FAULTS:
            raise TorchspecError(f"a fault must be one of {', '.join(FAULTS)}; got {kind!r}.")
        if not (isinstance(count, int) and count >= 1):
            raise TorchspecError(f"a fault's count must be an integer >= 1; got {count!r}.")
        if command is not None and command not in COMMANDS:
            raise TorchspecError(f"a fault's command must be one of {', '.join(COMMANDS)}; got {command!r}.")
        if kind == "motor" and command is not None and not COMMANDS[command].motion:
            raise TorchspecError(f"a motor fault's command must be a motion (HOME, MOVE, ARM, JOG); got {command!r}.")
        seconds = self.stall_seconds if seconds is None else seconds
        if not (math.isfinite(seconds) and seconds >= 0):
            raise TorchspecError(f"a stall's seconds must be >= 0; got {seconds}.")
        with self._lock:
            self._faults.append(_Fault(kind, count, command, seconds))

    @property
    def pending_faults(self) -> list[tuple[str, int, str | None]]:
        """Injected faults not used up yet: (kind, count left, command)."""
        with self._lock:
            return [(fault.kind, fault.count, fault.command) for fault in self._faults]

    @property
    def motions(self) -> int:
        """How many motion commands were acted on (a resent duplicate is not acted on again)."""
        with self._lock:
            return self._motions

    @property
    def received(self) -> collections.Counter[str]:
        """How many requests of each command arrived readable, resent duplicates included."""
        with self._lock:
            return collections.Counter(self._received)

    @property
    def executed(self) -> collections.Counter[str]:
        """How many times each command was acted on (duplicates and refused commands excluded)."""
        with self._lock:
            return collections.Counter(self._executed)

    def status(self) -> DomeStatus:
        """The state now, as ``STATUS`` would report it (radians)."""
        with self._lock:
            return self._status(time.monotonic())

    # Serving.

    def _serve(self) -> None:
        buffer = b""
        skipping = False  # inside an over-long line, already answered: drop up to its newline
        try:
            while not self._stop.is_set():
                ready, _, _ = select.select([self._master], [], [], 0.05)
                if not ready:
                    continue
                try:
                    buffer += os.read(self._master, 4096)
                except BlockingIOError:
                    continue
                except OSError:  # the pty went away under us
                    return
                while b"\n" in buffer:
                    line, _, buffer = buffer.partition(b"\n")
                    if skipping:
                        skipping = False
                    elif not self._handle(line + b"\n"):
                        return
                if len(buffer) >= MAX_LINE:  # no newline in sight: answer once, then skip to the next line
                    if not skipping:
                        message = f"line longer than {MAX_LINE} bytes"
                        self._send(encode_reply(Reply(0, code="BADFRAME", message=message)))
                    buffer, skipping = b"", True
        finally:
            if self.disconnected:
                self._close()

    def _handle(self, line: bytes) -> bool:
        """Answer one line; False when the emulator must stop serving (a disconnect)."""
        if not line.strip():
            return True  # a terminal's bare Enter
        try:
            request = parse_request(line)
        except FrameError as error:
            # The sequence number of an unreadable request cannot be trusted: answer with 0.
            self._send(encode_reply(Reply(0, code=error.code, message=_message(str(error)))))
            return True
        with self._lock:
            self._received[request.command] += 1
            duplicate = self._last is not None and self._last[0] == request
            fault = self._take_fault(request, acting=not duplicate)
        if fault is not None and fault.kind == "corrupt":
            self._send(encode_reply(Reply(0, code="CHECKSUM", message="request corrupted on the wire (injected)")))
            return True
        if fault is not None and fault.kind == "disconnect":
            self.disconnected = True
            self._close()
            return False
        if fault is not None and fault.kind == "stall" and self._stop.wait(fault.seconds):
            return False
        with self._lock:
            if duplicate:
                reply = self._last[1]
            else:
                reply = encode_reply(self._execute(request, motor=fault is not None and fault.kind == "motor"))
                self._last = (request, reply)
        if fault is not None and fault.kind == "drop":
            return True
        if fault is not None and fault.kind == "garble":
            reply = _garble(reply)
        self._send(reply)
        return True

    def _take_fault(self, request: Request, *, acting: bool) -> _Fault | None:
        for fault in self._faults:
            if fault.command not in (None, request.command):
                continue
            spec = COMMANDS.get(request.command)
            if fault.kind == "motor" and not (acting and spec is not None and spec.motion):
                continue
            fault.count -= 1
            if fault.count == 0:
                self._faults.remove(fault)
            return fault
        return None

    def _send(self, data: bytes) -> None:
        try:
            os.write(self._master, data)
        except (BlockingIOError, OSError):
            pass  # nobody reads the port and its buffer is full: the bytes are lost, as on a real line

    def _close(self) -> None:
        for name in ("_master", "_slave"):
            fd = getattr(self, name)
            setattr(self, name, None)
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass

    # The device.

    def _execute(self, request: Request, *, motor: bool) -> Reply:
        seq = request.seq
        spec = COMMANDS.get(request.command)
        if spec is None:
            return Reply(
                seq, code="UNKNOWN", message=f"{request.command} is not a command of protocol {PROTOCOL_VERSION}"
            )
        expected = len(spec.args.split()) if request.command != "LIGHT" else None
        if expected is not None and len(request.args) != expected:
            return Reply(
                seq, code="BADARG", message=f"{request.command} takes {expected} arguments {spec.args}".rstrip()
            )
        now = time.monotonic()
        self._settle(now)
        try:
            reply = getattr(self, f"_do_{request.command.lower()}")(seq, request.args, now, motor)
        except ValueError as error:
            return Reply(seq, code="BADARG", message=_message(str(error)))
        if reply.ok:
            self._executed[request.command] += 1
            self._motions += spec.motion
        return reply

    def _do_id(self, seq, args, now, motor) -> Reply:
        return Reply(seq, identity_values(self.identity))

    def _do_status(self, seq, args, now, motor) -> Reply:
        return Reply(seq, status_values(self._status(now)))

    def _do_home(self, seq, args, now, motor) -> Reply:
        self._fault = None
        self._homed = True
        return self._start(seq, (0.0, 0.0, 0.0), now, motor)

    def _do_move(self, seq, args, now, motor) -> Reply:
        theta, phi = parse_degrees(args[0]), parse_degrees(args[1])
        if not 0 <= theta <= math.pi / 2 + 1e-12 or not 0 <= phi < _TAU:
            return Reply(
                seq, code="RANGE", message=f"theta must be in 0..90 and phi in 0..<360; got {args[0]} {args[1]}"
            )
        return self._refuse(seq) or self._start(seq, (theta, phi, self._position[2]), now, motor)

    def _do_jog(self, seq, args, now, motor) -> Reply:
        theta, phi, arm = self._position
        theta += parse_degrees(args[0])
        if not 0 <= theta <= math.pi / 2 + 1e-12:
            return Reply(seq, code="RANGE", message=f"theta would leave 0..90: {format_degrees(theta)}")
        return self._refuse(seq) or self._start(seq, (theta, (phi + parse_degrees(args[1])) % _TAU, arm), now, motor)

    def _do_arm(self, seq, args, now, motor) -> Reply:
        extension = parse_fraction(args[0])
        if not 0 <= extension <= 1:
            return Reply(seq, code="RANGE", message=f"extension must be in 0..1; got {args[0]}")
        return self._refuse(seq) or self._start(seq, (*self._position[:2], extension), now, motor)

    def _do_light(self, seq, args, now, motor) -> Reply:
        if not 1 <= len(args) <= 2 or args[0] not in ("ON", "OFF"):
            return Reply(seq, code="BADARG", message="LIGHT takes ON|OFF [INTENSITY]")
        if len(args) == 2:
            intensity = parse_fraction(args[1])
            if not 0 <= intensity <= 1:
                return Reply(seq, code="RANGE", message=f"intensity must be in 0..1; got {args[1]}")
            self._intensity = intensity
        self._light = args[0] == "ON"
        return Reply(seq)

    def _refuse(self, seq: int) -> Reply | None:
        if self._fault is not None:
            return Reply(seq, code="FAULTED", message=f"fault {self._fault} latched; HOME clears it")
        if not self._homed:
            return Reply(seq, code="NOTHOMED", message="position unknown since power-up; HOME first")
        return None

    def _start(self, seq: int, target: tuple[float, float, float], now: float, motor: bool) -> Reply:
        """Begin a motion to ``target`` (replacing one under way): the reply is sent at once."""
        start = self._position
        dphi = math.remainder(target[1] - start[1], _TAU)
        delta = (target[0] - start[0], dphi, target[2] - start[2])
        duration = max(abs(delta[0]) / self.speed, abs(delta[1]) / self.speed, abs(delta[2]) / self.arm_speed)
        self._motion = _Motion(start, delta, now, duration, 0.5 if motor else None)
        self._settle(now)
        return Reply(seq)

    def _settle(self, now: float) -> None:
        """Bring the position up to ``now``: the motion under way ends, or stops on its motor fault."""
        motion = self._motion
        if motion is None:
            return
        fraction = 1.0 if motion.duration == 0 else min(1.0, (now - motion.began) / motion.duration)
        if motion.fails_at is not None and fraction >= motion.fails_at:
            fraction = motion.fails_at
            self._fault = "MOTOR"
            self._motion = None
        elif fraction >= 1.0:
            self._motion = None
        theta, phi, arm = (s + d * fraction for s, d in zip(motion.start, motion.delta, strict=True))
        self._position = (theta, phi % _TAU, arm)

    def _status(self, now: float) -> DomeStatus:
        self._settle(now)
        theta, phi, arm = self._position
        return DomeStatus(theta, phi, arm, self._motion is not None, self._light, self._intensity, self._fault)


def _garble(line: bytes) -> bytes:
    """``line`` with the byte in the middle of its body replaced (its CRC no longer matches)."""
    index = len(line) // 2
    return line[:index] + (b"?" if line[index : index + 1] != b"?" else b"!") + line[index + 1 :]


def _message(text: str) -> str:
    """``text`` fit for an ``err`` message: printable ASCII without '*', short enough for a line."""
    cleaned = "".join(c if " " <= c <= "~" and c != "*" else "?" for c in text)
    return cleaned[: MAX_LINE - 40]


def parse_fault(text: str) -> tuple[str, int, str | None]:
    """A CLI fault ``KIND[:COUNT[:COMMAND]]`` (e.g. ``drop:3``, ``garble:1:MOVE``) as inject's arguments."""
    parts = text.split(":")
    if not 1 <= len(parts) <= 3 or parts[0] not in FAULTS:
        raise TorchspecError(
            f"--fault must be KIND[:COUNT[:COMMAND]] with KIND one of {', '.join(FAULTS)}; got {text!r}."
        )
    if len(parts) >= 2 and not parts[1].isdigit():
        raise TorchspecError(f"--fault's COUNT must be a positive integer; got {parts[1]!r} in {text!r}.")
    count = int(parts[1]) if len(parts) >= 2 else 1
    command = parts[2].upper() if len(parts) == 3 else None
    return parts[0], count, command


def serve(
    *, speed: float, arm_speed: float, faults: list[str] = (), stall_seconds: float = 1.0, homed: bool = True
) -> int:
    """``torchspec dome-emulator``: print the port's path (alone on stdout's first line, for scripts),
    then serve until Ctrl-C or SIGTERM. ``speed`` in rad/s; ``faults`` as :func:`parse_fault` reads them."""
    import signal
    import sys

    emulator = DomeEmulator(speed=speed, arm_speed=arm_speed, stall_seconds=stall_seconds, homed=homed)
    injected = [parse_fault(text) for text in faults]  # every flag checked before the port opens
    for kind, count, command in injected:
        emulator.inject(kind, count, command)
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        with emulator:
            print(emulator.port, flush=True)
            print(
                f"dome emulator on {emulator.port} (protocol {emulator.identity.protocol}, "
                f"{math.degrees(speed):g} deg/s); Ctrl-C to stop",
                file=sys.stderr,
                flush=True,
            )
            while not stop.wait(0.2) and emulator.serving:
                pass
            if emulator.disconnected:
                print(f"dome emulator on {emulator.port}: disconnected (injected fault)", file=sys.stderr)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0
