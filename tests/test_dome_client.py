"""The client against the emulator, through a real pseudo-terminal: every command, every injected
fault recovered or stopped with the right error, exclusive access."""

import math
import os
import threading
import time

import pytest

from torchspec.dome import (
    PROTOCOL_VERSION,
    DomeClient,
    DomeDisconnected,
    DomeEmulator,
    DomeError,
    DomeFault,
    DomeProtocolError,
    DomeTimeout,
)

TIMEOUT = 0.2
RETRIES = 3
ANGLE = 1e-3 * math.pi / 180  # the wire's resolution: 0.001 degree


@pytest.fixture
def emulator():
    with DomeEmulator(speed=20.0, arm_speed=20.0) as dome:
        yield dome


@pytest.fixture
def client(emulator):
    with DomeClient(emulator.port, timeout=TIMEOUT, retries=RETRIES, backoff=0.01, move_timeout=5.0) as dome:
        yield dome


def names_port_and_command(error, port, command):
    text = str(error)
    assert port in text and command in text, f"the message must name {port} and {command}: {text}"
    assert error.port == port and error.command.startswith(command), (error.port, error.command)


def test_identify_reports_the_protocol_version(client):
    identity = client.identify()
    assert identity.protocol == PROTOCOL_VERSION == 1, identity
    assert identity.model == "TSDOME-EMU" and identity.firmware == "1.0.0", identity


def test_every_command(client, emulator):
    client.home()
    client.move(math.radians(40), math.radians(250))
    status = client.status()
    assert not status.moving and status.fault is None, status
    assert abs(status.theta - math.radians(40)) < ANGLE and abs(status.phi - math.radians(250)) < ANGLE, status
    client.move(0.3, -0.5)  # phi wraps into [0, 2 pi)
    status = client.status()
    assert abs(status.phi - (2 * math.pi - 0.5)) < ANGLE, f"phi {status.phi}"
    client.arm(0.75)
    assert client.status().arm == 0.75 and abs(client.status().theta - 0.3) < ANGLE
    client.light(True, 0.4)
    status = client.status()
    assert status.light and status.intensity == 0.4, status
    client.light(False)
    client.light(True)  # keeps the intensity
    status = client.status()
    assert status.light and status.intensity == 0.4, status
    client.jog(0.1, -0.2)
    status = client.status()
    assert abs(status.theta - 0.4) < 2 * ANGLE and abs(status.phi - (2 * math.pi - 0.7)) < 2 * ANGLE, status
    client.home()
    status = client.status()
    assert (status.theta, status.phi, status.arm) == (0.0, 0.0, 0.0), status
    assert emulator.motions == 6, f"{emulator.motions} motions"
    assert emulator.executed["LIGHT"] == 3 and emulator.executed["STATUS"] >= 6, emulator.executed


def test_a_move_takes_time_and_returns_at_rest():
    speed = 2.0  # rad/s: 0.6 rad take 0.3 s
    with DomeEmulator(speed=speed) as dome, DomeClient(dome.port, timeout=TIMEOUT) as client:
        start = time.monotonic()
        client.move(0.6, 0.0)
        took = time.monotonic() - start
        status = client.status()
    assert 0.3 <= took < 1.0, f"the move took {took:.3f} s; expected about 0.3 s"
    assert not status.moving and abs(status.theta - 0.6) < ANGLE, status


def test_a_move_longer_than_move_timeout_raises():
    with DomeEmulator(speed=0.5) as dome, DomeClient(dome.port, timeout=TIMEOUT, move_timeout=0.2) as client:
        with pytest.raises(DomeTimeout, match="move_timeout=0.2") as caught:
            client.move(1.0, 0.0)
        assert client.status().moving, "the dome moves on; the client only stopped waiting"
    names_port_and_command(caught.value, dome.port, "MOVE")


@pytest.mark.parametrize("kind", ["drop", "garble", "corrupt"])
@pytest.mark.parametrize("count", [1, RETRIES])
def test_lost_and_garbled_replies_are_recovered_and_the_move_runs_once(client, emulator, kind, count):
    emulator.inject(kind, count=count, command="MOVE")
    client.move(0.5, 1.0)
    assert emulator.received["MOVE"] == count + 1, f"{emulator.received['MOVE']} MOVE requests arrived"
    assert emulator.motions == 1, f"the resent MOVE ran {emulator.motions} times"
    status = client.status()
    assert abs(status.theta - 0.5) < ANGLE and abs(status.phi - 1.0) < ANGLE, status


def test_status_polls_are_retried_during_a_move(client, emulator):
    emulator.inject("drop", count=2, command="STATUS")
    emulator.inject("garble", count=1, command="STATUS")
    client.move(1.2, 0.0)
    assert emulator.pending_faults == [] and not client.status().moving


@pytest.mark.parametrize(
    ("kind", "error", "match"),
    [
        ("drop", DomeTimeout, "no complete reply after 4 attempts"),
        ("garble", DomeProtocolError, "must be a valid frame"),
        ("corrupt", DomeProtocolError, "could not read the request"),
    ],
)
def test_faults_outlasting_the_retries_raise(client, emulator, kind, error, match):
    emulator.inject(kind, count=RETRIES + 1, command="ARM")
    start = time.monotonic()
    with pytest.raises(error, match=match) as caught:
        client.arm(0.5)
    took = time.monotonic() - start
    names_port_and_command(caught.value, emulator.port, "ARM 0.5000")
    assert emulator.received["ARM"] == RETRIES + 1, f"{emulator.received['ARM']} attempts"
    assert took < (RETRIES + 1) * TIMEOUT + 0.5, f"gave up after {took:.2f} s"
    client.arm(0.5)  # the fault is used up: the same client goes on
    assert client.status().arm == 0.5


def test_a_stall_is_waited_out_and_the_late_replies_are_skipped(client, emulator):
    emulator.inject("stall", command="MOVE", seconds=2.5 * TIMEOUT)
    client.move(0.7, 0.2)
    assert emulator.received["MOVE"] >= 2, "the client must have resent the MOVE during the stall"
    assert emulator.motions == 1, f"{emulator.motions} motions"
    # The device answers the original and each queued resend: those late replies reach the move's
    # STATUS polls, which must skip them by their sequence number.
    for _ in range(3):
        assert abs(client.status().theta - 0.7) < ANGLE
    assert client.identify().protocol == PROTOCOL_VERSION


def test_a_stall_outlasting_the_retries_raises_a_timeout(client, emulator):
    emulator.inject("stall", command="STATUS", seconds=(RETRIES + 2) * TIMEOUT)
    with pytest.raises(DomeTimeout, match="stopped answering") as caught:
        client.status()
    names_port_and_command(caught.value, emulator.port, "STATUS")


def test_a_non_idempotent_command_is_never_resent(client, emulator):
    emulator.inject("drop", command="JOG")
    with pytest.raises(DomeTimeout, match="not idempotent") as caught:
        client.jog(0.1, 0.0)
    names_port_and_command(caught.value, emulator.port, "JOG")
    assert emulator.received["JOG"] == 1, f"JOG was sent {emulator.received['JOG']} times"
    emulator.inject("garble", command="JOG")
    with pytest.raises(DomeProtocolError, match="not idempotent"):
        client.jog(0.1, 0.0)
    assert emulator.received["JOG"] == 2 and emulator.executed["JOG"] == 2
    # A request the device could not read was not acted on: resending it is safe, even a JOG.
    emulator.inject("corrupt", command="JOG")
    client.jog(0.1, 0.0)
    assert emulator.received["JOG"] == 4 and emulator.executed["JOG"] == 3


def test_a_motor_fault_stops_with_the_device_code(client, emulator):
    emulator.inject("motor", command="MOVE")
    with pytest.raises(DomeFault, match="fault MOTOR") as caught:
        client.move(1.0, 0.0)
    assert caught.value.code == "MOTOR", caught.value.code
    names_port_and_command(caught.value, emulator.port, "MOVE")
    status = client.status()
    assert status.fault == "MOTOR" and not status.moving and 0 < status.theta < 1.0, status
    with pytest.raises(DomeFault, match="FAULTED") as refused:
        client.move(0.2, 0.0)
    assert refused.value.code == "FAULTED" and "HOME" in refused.value.message, refused.value
    client.light(True, 0.5)  # what does not move still works
    client.home()
    assert client.status().fault is None
    client.move(0.2, 0.0)


def test_device_errors_carry_code_and_message(client):
    with pytest.raises(DomeFault, match="RANGE") as caught:
        client._call("MOVE", "95.000", "0.000")
    assert caught.value.code == "RANGE" and "theta" in caught.value.message, caught.value
    names_port_and_command(caught.value, client.port, "MOVE 95.000 0.000")


def test_a_vanished_port_raises_disconnected_quickly(client, emulator):
    emulator.inject("disconnect", command="STATUS")
    start = time.monotonic()
    with pytest.raises(DomeDisconnected, match="must stay connected") as caught:
        client.move(0.5, 0.5)  # vanishes while the client polls the move
    took = time.monotonic() - start
    assert took < 1.0, f"noticed after {took:.2f} s"
    assert isinstance(caught.value, OSError)
    names_port_and_command(caught.value, emulator.port, "STATUS")
    assert not os.path.exists(emulator.port), "the pty must be gone"
    with pytest.raises(DomeDisconnected, match="gone earlier"):
        client.identify()


def test_the_emulator_stopping_under_a_client(client, emulator):
    client.identify()
    emulator.stop()
    with pytest.raises(DomeDisconnected):
        client.status()


def test_exclusive_access(emulator):
    with DomeClient(emulator.port, timeout=TIMEOUT) as first:
        with pytest.raises(DomeError, match="must be free") as caught:
            DomeClient(emulator.port, timeout=TIMEOUT)
        assert emulator.port in str(caught.value)
        first.identify()
    with DomeClient(emulator.port, timeout=TIMEOUT) as second:  # released on close
        assert second.identify().protocol == PROTOCOL_VERSION


def test_a_missing_port_is_named():
    with pytest.raises(DomeError, match="/dev/nonexistent-dome") as caught:
        DomeClient("/dev/nonexistent-dome")
    assert not isinstance(caught.value, DomeDisconnected)


def test_another_protocol_version_is_refused():
    with DomeEmulator(protocol=2) as dome, DomeClient(dome.port, timeout=TIMEOUT) as client:
        with pytest.raises(DomeProtocolError, match="must report protocol 1; got protocol 2"):
            client.identify()


def test_garbage_from_the_device_is_a_protocol_error():
    # A device printing a banner (or at the wrong baud rate): lines that are never frames.
    master, slave = os.openpty()
    port = os.ttyname(slave)
    stop = threading.Event()

    def babble():
        while not stop.wait(0.01):
            try:
                os.read(master, 1024)
                os.write(master, b"Dome v0.9 ready\r\n")
            except OSError:
                return

    thread = threading.Thread(target=babble, daemon=True)
    thread.start()
    try:
        with DomeClient(port, timeout=TIMEOUT, retries=1, backoff=0.0) as client:
            with pytest.raises(DomeProtocolError, match="Dome v0.9 ready") as caught:
                client.status()
    finally:
        stop.set()
        thread.join()
        os.close(master)
        os.close(slave)
    names_port_and_command(caught.value, port, "STATUS")
    assert b"Dome v0.9" in caught.value.received


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda c: c.move(math.pi / 2 + 0.01, 0.0), "theta must be in"),
        (lambda c: c.move(-0.01, 0.0), "theta must be in"),
        (lambda c: c.move(0.1, math.nan), "finite"),
        (lambda c: c.arm(1.5), "extension must be in"),
        (lambda c: c.light(True, -0.1), "intensity must be in"),
        (lambda c: c.light(True, math.inf), "intensity must be in"),
    ],
)
def test_bad_arguments_are_refused_before_sending(client, emulator, call, match):
    with pytest.raises(ValueError, match=match):
        call(client)
    assert sum(emulator.received.values()) == 0, emulator.received


def test_boundaries_are_accepted(client):
    client.move(math.pi / 2, 2 * math.pi)
    status = client.status()
    assert abs(status.theta - math.pi / 2) < ANGLE and status.phi == 0.0, status


def test_bad_settings_and_a_closed_client(emulator):
    for settings in ({"timeout": 0}, {"retries": -1}, {"backoff": math.nan}, {"move_timeout": math.inf}):
        with pytest.raises(ValueError, match="must be"):
            DomeClient(emulator.port, **settings)
    client = DomeClient(emulator.port)
    client.close()
    client.close()
    with pytest.raises(DomeError, match="closed"):
        client.status()


def test_a_non_idempotent_command_unread_every_time_says_so(client, emulator):
    emulator.inject("corrupt", count=RETRIES + 1, command="JOG")
    with pytest.raises(DomeProtocolError, match="could not read the request") as caught:
        client.jog(0.1, 0.0)
    assert "may have been acted on" not in str(caught.value), str(caught.value)
    assert emulator.received["JOG"] == RETRIES + 1 and emulator.executed["JOG"] == 0, emulator.received
