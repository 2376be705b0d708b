"""Byte-level tests of the ATI Net F/T RDT protocol and the netftapi2.xml calibration page."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dentibot.errors import ConfigError, ProtocolError
from dentibot.io.interfaces import WRENCH_SATURATED
from dentibot.io.netft_protocol import (
    MAX_RECORDS_PER_DATAGRAM,
    Command,
    NetFTCalibration,
    RdtRecord,
    SequenceTracker,
    counts_to_si,
    decode_datagram,
    decode_request,
    describe_status,
    encode_record,
    encode_records,
    encode_request,
    http_get_request,
    http_response,
    parse_calibration_xml,
    parse_http_request_line,
    parse_http_response,
    rdt_status_from_wrench,
    render_calibration_xml,
    si_to_counts,
    wrench_status_from_rdt,
)

u32 = st.integers(0, 2**32 - 1)
i32 = st.integers(-(2**31), 2**31 - 1)
records = st.builds(RdtRecord, u32, u32, u32, st.tuples(i32, i32, i32, i32, i32, i32))


# --------------------------------------------------------------------------- requests
@pytest.mark.parametrize(("command", "count", "wire"), [
    (Command.STOP, 0, "1234 0000 00000000"),
    (Command.START_REALTIME, 0, "1234 0002 00000000"),
    (Command.START_BUFFERED, 1000, "1234 0003 000003e8"),
    (Command.SET_BIAS, 0, "1234 0042 00000000"),
])
def test_requests_are_the_documented_eight_bytes(command, count, wire):
    data = encode_request(command, count)
    assert data == bytes.fromhex(wire)
    req = decode_request(data)
    assert (req.command, req.sample_count) == (command, count)


def test_bad_requests_are_typed_errors():
    with pytest.raises(ProtocolError, match="8"):
        decode_request(bytes.fromhex("1234 0002 0000"))
    with pytest.raises(ProtocolError, match="header 0x4321"):
        decode_request(bytes.fromhex("4321 0002 00000000"))
    with pytest.raises(ProtocolError, match="0x0007"):
        decode_request(bytes.fromhex("1234 0007 00000000"))
    with pytest.raises(ConfigError):
        encode_request(0x0007)
    with pytest.raises(ConfigError):
        encode_request(Command.START_REALTIME, 2**32)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=20))
def test_request_parser_never_crashes(data):
    try:
        req = decode_request(data)
    except ProtocolError:
        return
    assert encode_request(req.command, req.sample_count) == data


# --------------------------------------------------------------------------- records
def _be32(v: int) -> bytes:
    return (v % 2**32).to_bytes(4, "big")


def test_record_layout_big_endian_sequence_status_then_six_signed_counts():
    # built by hand from the ATI record layout, not with the module's struct
    wire = (_be32(7) + _be32(0x01020304) + _be32(0)
            + b"".join(_be32(c) for c in (1, -1, 1_000_000, -2_000_000, 2**31 - 1, -(2**31))))
    assert len(wire) == 36
    (rec,) = decode_datagram(wire)
    assert rec == RdtRecord(7, 0x01020304, 0, (1, -1, 1_000_000, -2_000_000, 2**31 - 1, -(2**31)))
    assert encode_record(rec) == wire


def test_buffered_datagram_carries_records_back_to_back():
    recs = [RdtRecord(i + 1, 100 + 14 * i, 0, (i, -i, 2 * i, 0, 0, -3 * i)) for i in range(3)]
    data = encode_records(recs)
    assert len(data) == 3 * 36
    assert decode_datagram(data) == recs


@pytest.mark.parametrize("size", [0, 1, 35, 37, 71, 8, (MAX_RECORDS_PER_DATAGRAM + 1) * 36])
def test_wrong_lengths_are_protocol_errors(size):
    with pytest.raises(ProtocolError) as e:
        decode_datagram(b"\x00" * size)
    assert e.value.device == "netft" and str(size) in str(e.value)


def test_a_truncated_record_rejects_the_whole_datagram():
    data = encode_records([RdtRecord(1, 1, 0, (1,) * 6), RdtRecord(2, 2, 0, (2,) * 6)])
    with pytest.raises(ProtocolError):
        decode_datagram(data[:-5])


def test_encoding_out_of_range_fields_is_a_config_error():
    with pytest.raises(ConfigError):
        encode_record(RdtRecord(-1, 0, 0, (0,) * 6))
    with pytest.raises(ConfigError):
        encode_record(RdtRecord(1, 0, 0, (2**31, 0, 0, 0, 0, 0)))


@settings(max_examples=200, deadline=None)
@given(st.lists(records, min_size=1, max_size=MAX_RECORDS_PER_DATAGRAM))
def test_records_round_trip(recs):
    assert decode_datagram(encode_records(recs)) == recs


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=40 * 36 + 50))
def test_datagram_parser_never_crashes_on_garbage(data):
    try:
        recs = decode_datagram(data)
    except ProtocolError:
        assert len(data) == 0 or len(data) % 36 or len(data) > 40 * 36
        return
    assert len(recs) * 36 == len(data)
    assert encode_records(recs) == data


# --------------------------------------------------------------------------- units, status
def test_counts_convert_with_counts_per_unit():
    f, t = counts_to_si((1_234_567, -500_000, 0, 250, -1, 1_000_000), 1_000_000, 1_000_000)
    assert f == pytest.approx((1.234567, -0.5, 0.0))
    assert t == pytest.approx((0.000250, -0.000001, 1.0))
    assert si_to_counts((1.234567, -0.5, 0.0), (0.00025, -1e-6, 1.0), 1e6, 1e6) == (
        1_234_567, -500_000, 0, 250, -1, 1_000_000)
    # saturating the i32 wire range instead of wrapping
    assert si_to_counts((1e9, -1e9, 0), (0, 0, 0), 1e6, 1e6)[:2] == (2**31 - 1, -(2**31))


def test_status_words_name_their_bits():
    assert "healthy" in describe_status(0)
    text = describe_status(0x80020000)
    assert "0x80020000" in text and "error summary" in text and "saturation" in text
    assert "bit 0" in describe_status(0x1)
    assert rdt_status_from_wrench(WRENCH_SATURATED) == 0x80020000
    assert rdt_status_from_wrench(0) == 0
    assert wrench_status_from_rdt(0x80020000) == WRENCH_SATURATED
    assert wrench_status_from_rdt(0x80000004) == 0


# --------------------------------------------------------------------------- sequences
def test_sequence_tracker_counts_gaps_duplicates_reordering_and_wrap():
    tr = SequenceTracker()
    assert tr.accept(1, 10) == 0
    assert tr.accept(2, 24) == 0
    assert tr.accept(5, 66) == 2          # 3 and 4 lost
    assert tr.accept(4, 52) == -1         # late: older
    assert tr.accept(5, 66) == -1         # duplicate
    tr.reset()
    assert tr.accept(2**32 - 1, 1000) == 2**32 - 2   # first seen; all before it never came
    assert tr.accept(0, 1014) == 0        # wraps to 0 as the next number
    assert tr.accept(1, 1028) == 0


def test_a_new_request_restarts_rdt_sequence_and_is_not_out_of_order():
    tr = SequenceTracker()
    for k in range(1, 101):
        assert tr.accept(k, 14 * k) == 0
    assert tr.accept(1, 14 * 200) == 0    # ft_sequence moved on: a new stream
    assert tr.restarts == 1
    assert tr.accept(3, 14 * 202) == 1


@settings(max_examples=200, deadline=None)
@given(st.lists(st.booleans(), min_size=1, max_size=300))
def test_lost_plus_received_covers_every_sequence_number(keep):
    tr = SequenceTracker()
    seqs = [k + 1 for k, kept in enumerate(keep) if kept]
    lost = received = 0
    for s in seqs:
        n = tr.accept(s, 7 * s)
        assert n >= 0
        lost += n
        received += 1
    if seqs:
        assert lost + received == seqs[-1]


# --------------------------------------------------------------------------- calibration page
# trimmed shape of a live box's document, as quoted by public clients (root <netft>)
LIVE_LIKE = b"""<?xml version="1.0"?><netft>
<runstat>0x00000000</runstat><runrate>7000</runrate>
<cfgnam>empty</cfgnam><cfgcalsel>0</cfgcalsel>
<scfgfu>N</scfgfu><scfgtu>Nm</scfgtu>
<cfgcpf>1000000</cfgcpf><cfgcpt>1000000</cfgcpt>
<cfgmr>20;20;60;1;1;1</cfgmr>
<comrdte>Enabled</comrdte><comrdtrate>500</comrdtrate><comrdtbsiz>1</comrdtbsiz>
</netft>"""


def test_parses_a_live_like_document():
    cal = parse_calibration_xml(LIVE_LIKE)
    assert cal.counts_per_force == 1_000_000 and cal.counts_per_torque == 1_000_000
    assert (cal.force_unit, cal.torque_unit) == ("N", "Nm")
    assert cal.rdt_rate_hz == 500 and cal.buffer_size == 1
    assert cal.counts_per_newton == 1_000_000 and cal.counts_per_newton_metre == 1_000_000


def test_non_si_units_are_converted_to_n_and_nm():
    doc = (b"<netft><cfgcpf>1000</cfgcpf><cfgcpt>1000</cfgcpt><scfgfu>lbf</scfgfu>"
           b"<scfgtu>N-mm</scfgtu></netft>")
    cal = parse_calibration_xml(doc)
    # 1000 counts per lbf, 1 lbf = 4.4482216152605 N (exact definition)
    assert cal.counts_per_newton == pytest.approx(1000 / 4.4482216152605)
    # 1000 counts per N*mm = 1e6 counts per N*m
    assert cal.counts_per_newton_metre == pytest.approx(1e6)


@pytest.mark.parametrize(("doc", "match"), [
    (b"<netft><cfgcpf>1000000", "XML"),
    (b"not xml at all", "XML"),
    (b"<netft><cfgcpt>1000000</cfgcpt></netft>", "cfgcpf"),
    (b"<netft><cfgcpf>0</cfgcpf><cfgcpt>1</cfgcpt></netft>", "positive"),
    (b"<netft><cfgcpf>abc</cfgcpf><cfgcpt>1</cfgcpt></netft>", "not a number"),
    (b"<netft><cfgcpf>1</cfgcpf><cfgcpt>nan</cfgcpt></netft>", "positive"),
    (b"<netft><cfgcpf>1</cfgcpf><cfgcpt>1</cfgcpt><scfgfu>furlong</scfgfu></netft>", "furlong"),
    (b"<netft><cfgcpf>1</cfgcpf><cfgcpt>1</cfgcpt><scfgtu>parsec</scfgtu></netft>", "parsec"),
])
def test_bad_calibration_documents_are_protocol_errors(doc, match):
    with pytest.raises(ProtocolError, match=match):
        parse_calibration_xml(doc)


def test_render_and_parse_round_trip():
    cal = NetFTCalibration(250_000, 4_000_000, "N", "Nm", 1000, 10)
    assert parse_calibration_xml(render_calibration_xml(cal)) == cal


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.binary(max_size=200),
                 st.text(max_size=60).map(
                     lambda s: f"<netft><cfgcpf>{s}</cfgcpf><cfgcpt>1</cfgcpt></netft>")))
def test_calibration_parser_never_crashes(doc):
    try:
        cal = parse_calibration_xml(doc)
    except ProtocolError:
        return
    assert cal.counts_per_force > 0 and cal.counts_per_torque > 0


# --------------------------------------------------------------------------- minimal HTTP
def test_http_helpers():
    req = http_get_request("192.168.1.1")
    assert req.startswith(b"GET /netftapi2.xml HTTP/1.0\r\n") and req.endswith(b"\r\n\r\n")
    assert parse_http_request_line(req.split(b"\r\n")[0]) == ("GET", "/netftapi2.xml")
    status, body = parse_http_response(http_response(200, b"<netft/>"))
    assert (status, body) == (200, b"<netft/>")
    assert parse_http_response(http_response(404))[0] == 404
    for bad in (b"", b"HTTP/1.0 200 OK\r\n", b"SMTP 200\r\n\r\n", b"HTTP/1.1 abc\r\n\r\n"):
        with pytest.raises(ProtocolError):
            parse_http_response(bad)
    for bad in (b"GET", b"GET netftapi2.xml HTTP/1.0", b"GET / FTP/1.0", b"\xff / HTTP/1.0"):
        with pytest.raises(ProtocolError):
            parse_http_request_line(bad)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=120))
def test_http_parsers_never_crash(data):
    for fn in (parse_http_response, parse_http_request_line):
        try:
            fn(data)
        except ProtocolError:
            pass


def test_struct_formats_match_the_documented_sizes():
    assert struct.calcsize(">HHI") == 8 and struct.calcsize(">III6i") == 36
