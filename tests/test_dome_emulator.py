"""The emulator as firmware would be tested: raw protocol lines on its pty, its motion model, its
fault injection, and the ``torchspec dome-emulator`` command."""

import math
import os
import select
import subprocess
import sys
import time
import tty

import pytest

from torchspec.cli import main
from torchspec.dome import DomeClient, DomeEmulator
from torchspec.dome.emulator import FAULTS, parse_fault
from torchspec.dome.protocol import MAX_LINE, Reply, Request, crc8, encode_request, parse_reply, parse_status


class Raw:
    """A host that writes raw lines to the emulator's pty and reads its replies."""

    def __init__(self, port):
        self.fd = os.open(port, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        self.buffer = b""

    def send(self, line: bytes) -> None:
        os.write(self.fd, line)

    def reply(self, timeout: float = 1.0) -> bytes | None:
        deadline = time.monotonic() + timeout
        while b"\n" not in self.buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.fd], [], [], left)[0]:
                return None
            self.buffer += os.read(self.fd, 1024)
        line, _, self.buffer = self.buffer.partition(b"\n")
        return line + b"\n"

    def ask(self, seq: int, command: str, *args: str) -> Reply:
        self.send(encode_request(Request(seq, command, args)))
        line = self.reply()
        assert line is not None, f"no reply to {command}"
        return parse_reply(line)

    def close(self):
        os.close(self.fd)


@pytest.fixture
def emulator():
    with DomeEmulator(speed=20.0, arm_speed=20.0) as dome:
        yield dome


@pytest.fixture
def raw(emulator):
    host = Raw(emulator.port)
    yield host
    host.close()


def test_start_stop_and_the_port(emulator):
    port = emulator.port
    assert port.startswith("/dev/pts/") and os.path.exists(port), port
    assert emulator.serving
    emulator.stop()
    emulator.stop()  # idempotent
    assert not emulator.serving and not os.path.exists(port), f"{port} must be gone after stop()"
    with pytest.raises(RuntimeError, match="must be started"):
        _ = DomeEmulator().port


def test_replies_echo_the_sequence_number(raw):
    reply = raw.ask(4242, "ID")
    assert reply.seq == 4242 and reply.ok and reply.values["protocol"] == "1", reply
    assert raw.ask(7, "STATUS").values["fault"] == "-"


@pytest.mark.parametrize(
    ("line", "code"),
    [
        (b"1 ID *00\n", "CHECKSUM"),
        (b"hello\n", "BADFRAME"),
        (b"1 ID\n", "BADFRAME"),
        (b"1 " + b"A" * MAX_LINE, "BADFRAME"),  # no newline in sight
    ],
)
def test_unreadable_requests_get_seq_0_and_are_not_acted_on(raw, emulator, line, code):
    raw.send(line)
    reply = parse_reply(raw.reply())
    assert reply.seq == 0 and reply.code == code, reply
    assert sum(emulator.executed.values()) == 0, emulator.executed


def test_an_over_long_line_is_answered_once(raw, emulator):
    raw.send(b"1 " + b"A" * (3 * MAX_LINE) + b" *00\n")
    assert parse_reply(raw.reply()).code == "BADFRAME"
    assert raw.reply(timeout=0.1) is None, "the rest of the line must be skipped, not answered"
    assert raw.ask(2, "ID").ok


def test_blank_lines_are_ignored(raw):
    raw.send(b"\r\n\n")
    assert raw.reply(timeout=0.1) is None
    assert raw.ask(1, "ID").ok


@pytest.mark.parametrize(
    ("command", "args", "code"),
    [
        ("FLY", (), "UNKNOWN"),
        ("MOVE", ("10.000",), "BADARG"),
        ("MOVE", ("1e1", "0"), "BADARG"),
        ("MOVE", ("95.000", "0.000"), "RANGE"),
        ("MOVE", ("10.000", "360.000"), "RANGE"),
        ("ARM", ("1.5000",), "RANGE"),
        ("LIGHT", ("DIM",), "BADARG"),
        ("LIGHT", ("ON", "2.0"), "RANGE"),
        ("JOG", ("-5.000", "0.000"), "RANGE"),  # theta would go below 0
    ],
)
def test_bad_commands_get_their_error_code(raw, emulator, command, args, code):
    reply = raw.ask(9, command, *args)
    assert reply.seq == 9 and reply.code == code and reply.message, reply
    assert emulator.motions == 0


def test_a_resent_request_is_answered_from_the_cache_without_acting(raw, emulator):
    line = encode_request(Request(31, "JOG", ("10.000", "20.000")))
    raw.send(line)
    first = raw.reply()
    raw.send(line)
    second = raw.reply()
    assert first == second == b"31 ok *" + f"{crc8(b'31 ok'):02X}".encode() + b"\n", (first, second)
    assert emulator.motions == 1 and emulator.received["JOG"] == 2, (emulator.motions, emulator.received)
    # The same seq with other bytes is a new request (a new session that reused the number).
    assert raw.ask(31, "JOG", "10.000", "0.000").ok
    assert emulator.motions == 2


def test_motion_takes_time_and_is_coordinated():
    speed = 2.0
    with DomeEmulator(speed=speed, arm_speed=1.0) as dome:
        raw = Raw(dome.port)
        try:
            start = time.monotonic()
            assert raw.ask(1, "MOVE", "22.918", "0.000").ok  # 0.4 rad: 0.2 s
            during = parse_status(raw.ask(2, "STATUS"))
            assert during.moving and 0 <= during.theta < 0.4, f"right after MOVE: {during}"
            seq = 3
            while parse_status(raw.ask(seq, "STATUS")).moving:  # a new seq each time: the same is a resend
                seq += 1
                time.sleep(0.01)
            took = time.monotonic() - start
            assert 0.2 <= took < 1.0, f"a 0.4 rad move at {speed} rad/s took {took:.3f} s"
            assert raw.ask(seq + 1, "ARM", "0.3000").ok  # 0.3 s at 1 per second
            time.sleep(0.4)
            status = dome.status()
            assert not status.moving and status.arm == pytest.approx(0.3) and status.theta == pytest.approx(0.4, 1e-4)
            # HOME drives every axis: theta needs 0.2 s, the arm 0.3 s, and both arrive together.
            assert raw.ask(seq + 2, "HOME").ok
            status = dome.status()
            assert status.moving, status
            done_theta, done_arm = 1 - status.theta / 0.4, 1 - status.arm / 0.3
            assert abs(done_theta - done_arm) < 1e-3, f"theta {done_theta:.4f} and arm {done_arm:.4f} of the way"
        finally:
            raw.close()


def test_phi_takes_the_shorter_way_round():
    with DomeEmulator(speed=1.0) as dome:
        raw = Raw(dome.port)
        try:
            assert raw.ask(1, "MOVE", "10.000", "350.000").ok  # 10 deg the short way: 0.17 s, not 6 s
            time.sleep(0.05)
            phi = dome.status().phi
            assert phi >= math.radians(349.999), f"phi went the long way: {math.degrees(phi):.1f} deg"
        finally:
            raw.close()


def test_a_new_motion_replaces_the_one_under_way(raw, emulator):
    assert raw.ask(1, "MOVE", "80.000", "0.000").ok
    assert raw.ask(2, "MOVE", "5.000", "0.000").ok
    time.sleep(0.1)
    status = emulator.status()
    assert not status.moving and status.theta == pytest.approx(math.radians(5)), status


def test_an_unhomed_dome_refuses_motion_until_home():
    with DomeEmulator(speed=20.0, homed=False) as dome:
        raw = Raw(dome.port)
        try:
            assert raw.ask(1, "MOVE", "10.000", "0.000").code == "NOTHOMED"
            assert raw.ask(2, "STATUS").ok and raw.ask(3, "LIGHT", "ON").ok
            assert raw.ask(4, "HOME").ok and raw.ask(5, "MOVE", "10.000", "0.000").ok
        finally:
            raw.close()


def test_injected_faults_follow_their_command_and_count(raw, emulator):
    emulator.inject("drop", count=2, command="LIGHT")
    assert raw.ask(1, "ID").ok, "a fault for LIGHT must not touch ID"
    raw.send(encode_request(Request(2, "LIGHT", ("ON",))))
    assert raw.reply(timeout=0.1) is None
    raw.send(encode_request(Request(2, "LIGHT", ("ON",))))
    assert raw.reply(timeout=0.1) is None
    assert raw.ask(2, "LIGHT", "ON").ok and emulator.executed["LIGHT"] == 1
    assert emulator.pending_faults == []
    emulator.inject("garble")
    raw.send(encode_request(Request(3, "STATUS")))
    garbled = raw.reply()
    with pytest.raises(ValueError, match="checksum"):
        parse_reply(garbled)
    emulator.inject("motor")
    assert raw.ask(4, "STATUS").ok and emulator.pending_faults == [("motor", 1, None)], "only a motion uses it"


def test_inject_checks_its_arguments(emulator):
    with pytest.raises(ValueError, match="must be one of drop"):
        emulator.inject("explode")
    with pytest.raises(ValueError, match="count must be"):
        emulator.inject("drop", count=0)
    with pytest.raises(ValueError, match="command must be one of"):
        emulator.inject("drop", command="FLY")
    with pytest.raises(ValueError, match="must be a motion"):
        emulator.inject("motor", command="STATUS")
    with pytest.raises(ValueError, match="speed must be"):
        DomeEmulator(speed=0)


def test_parse_fault():
    assert parse_fault("drop") == ("drop", 1, None)
    assert parse_fault("drop:3") == ("drop", 3, None)
    assert parse_fault("garble:2:move") == ("garble", 2, "MOVE")
    for bad in ("boom", "drop:x", "drop:1:MOVE:2"):
        with pytest.raises(ValueError, match="--fault"):
            parse_fault(bad)
    assert set(FAULTS) == {"drop", "garble", "corrupt", "stall", "disconnect", "motor"}


def _spawn(*args):
    return subprocess.Popen(
        [sys.executable, "-m", "torchspec", "dome-emulator", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_the_command_prints_its_port_and_serves():
    process = _spawn("--speed", "3000", "--fault", "drop:1:ID", "garble:1:STATUS", "--fault", "corrupt:1:MOVE")
    try:
        port = process.stdout.readline().strip()
        assert port.startswith("/dev/"), f"first line {port!r}; stderr: {process.stderr.read() if not port else ''}"
        with DomeClient(port, timeout=0.3, backoff=0.01) as client:
            assert client.identify().protocol == 1  # after one lost reply: the fault flag took effect
            client.move(0.5, 0.5)
            assert abs(client.status().theta - 0.5) < 1e-4
    finally:
        process.terminate()
        _, err = process.communicate(timeout=10)
    assert process.returncode == 0, f"exit status {process.returncode}: {err}"
    assert "Ctrl-C to stop" in err, err


def test_the_command_refuses_a_bad_fault_flag(capsys):
    assert main(["dome-emulator", "--fault", "explode:2"]) == 2
    out, err = capsys.readouterr()
    assert out == "", f"no port must be printed: {out!r}"
    assert "--fault must be KIND[:COUNT[:COMMAND]]" in err, err
