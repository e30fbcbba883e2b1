import doctest
import math
import re
from pathlib import Path

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from torchspec.dome import protocol
from torchspec.dome.protocol import (
    COMMANDS,
    ERROR_CODES,
    MAX_LINE,
    SEQ_MAX,
    DomeIdentity,
    DomeStatus,
    FrameError,
    Reply,
    Request,
    crc8,
    encode_reply,
    encode_request,
    format_degrees,
    format_fraction,
    identity_values,
    next_seq,
    parse_identity,
    parse_number,
    parse_reply,
    parse_request,
    parse_status,
    status_values,
)

DOC = Path(__file__).resolve().parents[1] / "docs" / "dome-protocol.md"

tokens = st.text(alphabet=[chr(c) for c in range(0x21, 0x7F) if chr(c) != "*"], min_size=1, max_size=8)
requests = st.builds(
    Request,
    seq=st.integers(1, SEQ_MAX),
    command=st.sampled_from(sorted(COMMANDS)) | st.from_regex(r"[A-Z][A-Z0-9_]{0,7}", fullmatch=True),
    args=st.lists(tokens, max_size=4).map(tuple),
)
ok_replies = st.builds(
    Reply,
    seq=st.integers(0, SEQ_MAX),
    values=st.dictionaries(
        st.from_regex(r"[a-z][a-z0-9_]{0,7}", fullmatch=True), tokens.filter(lambda t: "=" not in t), max_size=5
    ),
)
err_replies = st.builds(
    Reply,
    seq=st.integers(0, SEQ_MAX),
    code=st.sampled_from(sorted(ERROR_CODES)),
    message=st.text(alphabet=[chr(c) for c in range(0x20, 0x7F) if chr(c) != "*"], max_size=40),
)


def test_crc8_is_the_catalogue_crc8():
    # The catalogue's check value of CRC-8 (poly 0x07, init 0, no reflection, no xorout).
    assert crc8(b"123456789") == 0xF4, f"got {crc8(b'123456789'):#04x}"
    assert crc8(b"") == 0


def test_module_examples():
    failures, tried = doctest.testmod(protocol)
    assert tried > 5 and failures == 0, f"{failures} of {tried} doctest examples failed"


@given(requests)
@example(Request(1, "ID"))
@example(Request(SEQ_MAX, "MOVE", ("90.000", "359.999")))
def test_request_round_trip(request):
    line = encode_request(request)
    assert line.endswith(b"\n") and len(line) <= MAX_LINE
    assert parse_request(line) == request
    assert parse_request(line[:-1] + b"\r\n") == request, "a CRLF line ending must be accepted"


@given(ok_replies | err_replies)
@example(Reply(0, code="CHECKSUM"))
def test_reply_round_trip(reply):
    line = encode_reply(reply)
    assert parse_reply(line) == reply


@settings(max_examples=300)
@given(requests | ok_replies | err_replies, st.data())
def test_any_single_byte_corruption_is_rejected(message, data):
    is_request = isinstance(message, Request)
    line = (encode_request if is_request else encode_reply)(message)
    index = data.draw(st.integers(0, len(line) - 1), label="index")
    byte = data.draw(st.integers(0, 255).filter(lambda b: b != line[index]), label="byte")
    corrupted = line[:index] + bytes([byte]) + line[index + 1 :]
    with pytest.raises(FrameError):
        (parse_request if is_request else parse_reply)(corrupted)


@pytest.mark.parametrize(
    ("line", "code"),
    [
        (b"7 MOVE 45.000 90.000 *3E\n", "CHECKSUM"),
        (b"7 MOVE 45.000 90.000 *3d\n", "BADFRAME"),  # lower-case hex
        (b"7 MOVE 45.000 90.000 *3D", "BADFRAME"),  # no newline: the line was cut
        (b"7 MOVE 45.000 90.000\n", "BADFRAME"),  # no checksum
        (b"hello\n", "BADFRAME"),
        (b"\xff\xfe\n", "BADFRAME"),
        (b"1 " + b"A" * MAX_LINE + b" *00\n", "BADFRAME"),
    ],
)
def test_malformed_lines_are_rejected_with_their_code(line, code):
    with pytest.raises(FrameError) as caught:
        parse_request(line)
    assert caught.value.code == code, f"{line!r}: got {caught.value.code}: {caught.value}"


@pytest.mark.parametrize(
    "body",
    [b"0 ID", b"07 ID", b"65536 ID", b"1  MOVE 1 2", b"1 MOVE 1 2 ", b"1 move", b"1"],
)
def test_requests_must_be_canonical(body):
    with pytest.raises(FrameError, match="must"):
        parse_request(body + f" *{crc8(body):02X}\n".encode())


@pytest.mark.parametrize("body", [b"5 fine", b"5 ok theta", b"5 ok a=1 a=2", b"5 err", b"5 err bad code"])
def test_replies_must_be_ok_or_err(body):
    with pytest.raises(FrameError, match="must"):
        parse_reply(body + f" *{crc8(body):02X}\n".encode())


@pytest.mark.parametrize(
    "make",
    [
        lambda: encode_request(Request(0, "ID")),
        lambda: encode_request(Request(1, "id")),
        lambda: encode_request(Request(1, "MOVE", ("1 2",))),
        lambda: encode_request(Request(1, "MOVE", ("*",))),
        lambda: encode_reply(Reply(1, code="RANGE", message="a * b")),
        lambda: encode_reply(Reply(1, {"Key": "1"})),
        lambda: encode_request(Request(1, "X", ("a" * MAX_LINE,))),
    ],
)
def test_encoders_refuse_what_cannot_be_framed(make):
    with pytest.raises(ValueError, match="must"):
        make()


def test_sequence_numbers_wrap_past_zero():
    assert next_seq(1) == 2 and next_seq(SEQ_MAX) == 1, f"{next_seq(SEQ_MAX)}"


def test_status_and_identity_values_round_trip():
    status = DomeStatus(math.radians(12.5), math.radians(300.0), 0.25, True, True, 0.75, "MOTOR")
    back = parse_status(Reply(3, status_values(status)))
    assert back == status, f"{back} != {status}"
    assert parse_status(Reply(3, {**status_values(status), "fault": "-"})).fault is None
    extra = parse_status(Reply(3, {**status_values(status), "temperature": "41.5"}))
    assert extra == status, "keys a newer firmware adds must be ignored"
    identity = DomeIdentity("TSDOME-1", "2.3.1", 1)
    assert parse_identity(Reply(4, identity_values(identity))) == identity


@pytest.mark.parametrize(
    ("values", "match"),
    [
        ({"phi": None}, "got no phi"),
        ({"moving": "yes"}, "moving must be 0 or 1"),
        ({"theta": "1e3"}, "no exponent"),
        ({"fault": "stall?"}, "fault must be"),
    ],
)
def test_bad_status_values_are_named(values, match):
    good = status_values(DomeStatus(0.1, 0.2, 0.0, False, False, 1.0, None))
    bad = {key: value for key, value in {**good, **values}.items() if value is not None}
    with pytest.raises(ValueError, match=match):
        parse_status(Reply(3, bad))


def test_wire_numbers():
    assert format_degrees(math.pi / 4) == "45.000" and format_degrees(-1e-9) == "0.000"
    assert format_fraction(0.5) == "0.5000" and format_fraction(-1e-9) == "0.0000"
    assert parse_number("-12.345") == -12.345
    for bad in ("nan", "inf", "1e3", "1.", ".5", "+1", ""):
        with pytest.raises(ValueError):
            parse_number(bad)


def test_every_error_code_and_command_is_documented():
    text = DOC.read_text(encoding="utf-8")
    for name in [*ERROR_CODES, *COMMANDS]:
        assert re.search(rf"\| `{name}`", text), f"docs/dome-protocol.md has no table row for {name}"
    assert f"version {protocol.PROTOCOL_VERSION}" in text


def test_the_docs_examples_carry_valid_checksums():
    # Firmware authors check their CRC against these lines: each must be a valid frame.
    lines = re.findall(r"^(?:>|<) (.* \*[0-9A-F]{2})$", DOC.read_text(encoding="utf-8"), flags=re.MULTILINE)
    assert len(lines) >= 10, f"found only {len(lines)} example lines"
    for line in lines:
        body, _, check = line.rpartition(" *")
        assert int(check, 16) == crc8(body.encode()), f"{line!r}: the CRC of {body!r} is {crc8(body.encode()):02X}"
