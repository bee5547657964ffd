"""Chunked program transfer (program_begin / program_chunk / program_end): the server's bookkeeping, the
client's splitting, and a program larger than one chunk through a real socket server (fake daemon)."""
from __future__ import annotations

import io
import os
import shutil
import tempfile

import pytest

from hexacnc.commands.upload_client import send_program, split_chunks
from hexacnc.config import load_config
from hexacnc.daemon import protocol as P
from hexacnc.daemon.server import SocketServer
from hexacnc.daemon.upload import UploadError, Uploads

from test_protocol_fake import FakeDaemon

pytestmark = pytest.mark.serial        # starts processes or keeps time: runs alone (not beside other tests)


def test_uploads_accept_chunks_in_order_and_refuse_the_rest_without_losing_anything():
    up = Uploads(max_program_bytes=100, max_open_bytes=150)
    assert up.begin(1, "p", 10)["next_seq"] == 0
    assert up.chunk(1, 0, "G1 X1\n")["received_bytes"] == 6
    with pytest.raises(UploadError) as ei:
        up.chunk(1, 2, "M2\n")                      # out of order: refused, nothing changes
    assert ei.value.code == "bad_value" and "expected 1" in ei.value.message
    with pytest.raises(UploadError):
        up.chunk(1, 1, "G1 X1\x00")                 # NUL
    with pytest.raises(UploadError) as ei:
        up.end(1)                                   # incomplete
    assert "6 of 10" in ei.value.message
    with pytest.raises(UploadError) as ei:
        up.chunk(1, 1, "G1 X2 Y3\n")                # over the declared size
    assert ei.value.code == "too_large"
    up.chunk(1, 1, "M2\n\n")
    assert up.end(1) == ("G1 X1\nM2\n\n", "p")
    with pytest.raises(UploadError):
        up.end(1)                                   # closed
    with pytest.raises(UploadError) as ei:
        up.begin(2, "big", 101)
    assert ei.value.code == "too_large"
    up.begin(2, "a", 100)
    with pytest.raises(UploadError):
        up.begin(3, "b", 60)                        # all open uploads together
    up.drop(2)
    up.begin(3, "b", 60)


@pytest.mark.parametrize("chunk", [7, 64, 1000])
def test_split_chunks_reassembles_and_never_cuts_a_character(chunk):
    text = "".join(f"G1 X{i} (ünïcödé ✓)\n" for i in range(200)) + "M2"
    data = text.encode("utf-8")
    parts = split_chunks(data, chunk)
    assert b"".join(parts) == data
    assert all(0 < len(p) <= chunk for p in parts)
    for p in parts:
        p.decode("utf-8")                           # raises if a character was cut


@pytest.fixture
def served():
    d = tempfile.mkdtemp(prefix="hxu", dir="/tmp")
    fake = FakeDaemon()
    srv = SocketServer(fake, load_config(None), os.path.join(d, "s.sock"))
    srv.start()
    yield srv, fake
    srv.close()
    fake.close()
    shutil.rmtree(d, ignore_errors=True)


def test_a_program_larger_than_a_chunk_arrives_whole(served):
    srv, fake = served
    text = "".join(f"G1 X{i % 50}\n" for i in range(5000))
    err = io.StringIO()
    with P.Client.unix(srv.socket_path) as cl:
        r = send_program(cl, text, "big.ngc", chunk_bytes=4096, err=err)
    assert r["ok"] and r["name"] == "big.ngc"
    assert r["blocks"] == 5000                      # every line arrived, in order
    assert "upload" in err.getvalue() and "100.0 %" in err.getvalue()


def test_chunk_errors_and_a_second_client(served):
    srv, _ = served
    with P.Client.unix(srv.socket_path) as cl, P.Client.unix(srv.socket_path) as other:
        cl.call("program_begin", name="x", bytes=12)
        with pytest.raises(P.DaemonError) as ei:
            cl.call("program_chunk", seq=1, text="G1 X1\n")
        assert ei.value.code == P.BAD_VALUE
        with pytest.raises(P.DaemonError) as ei:
            other.call("program_chunk", seq=0, text="G1 X1\n")
        assert ei.value.code == P.NOT_CONTROLLER
        cl.call("program_chunk", seq=0, text="G1 X1\n")
        with pytest.raises(P.DaemonError) as ei:
            cl.call("program_end")
        assert ei.value.code == P.BAD_VALUE
        cl.call("program_chunk", seq=1, text="G1 X2\n")
        assert cl.call("program_end")["blocks"] == 2
