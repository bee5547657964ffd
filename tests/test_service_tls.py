"""Optional TLS on the TCP socket (127.0.0.1 here): the token only inside TLS, the daemon's
certificate checked by the client, a plaintext or unverifying client refused (and logged), the
pre-auth rules unchanged; configuration refusals."""
from __future__ import annotations

import logging
import os
import secrets
import shutil
import socket
import subprocess
import tempfile

import msgpack
import pytest

from hexacnc.config import load_config
from hexacnc.daemon import protocol as P
from hexacnc.daemon.server import SocketServer
from hexacnc.errors import ConfigError, HexacncError

from test_protocol_fake import FakeDaemon
from test_service_socket import _free_port, cfg_with

pytestmark = pytest.mark.e2e
TOKEN = secrets.token_hex(32)


@pytest.fixture(scope="module")
def pki():
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: cannot make a test certificate")
    d = tempfile.mkdtemp(prefix="hxtls", dir="/tmp")
    cert, key = os.path.join(d, "cert.pem"), os.path.join(d, "key.pem")
    r = subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", key, "-out", cert,
                        "-days", "1", "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1"],
                       capture_output=True, text=True, timeout=120)
    if r.returncode != 0:
        pytest.skip(f"openssl cannot make a test certificate: {r.stderr[-200:]}")
    os.chmod(key, 0o600)
    other_cert = os.path.join(d, "other.pem")
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", os.path.join(d, "o.key"),
                    "-out", other_cert, "-days", "1", "-subj", "/CN=127.0.0.1"], capture_output=True, timeout=120)
    yield {"dir": d, "cert": cert, "key": key, "other": other_cert}
    shutil.rmtree(d, ignore_errors=True)


def test_tls_client_with_the_certificate_works_others_are_refused(pki, caplog):
    cfg = cfg_with(load_config(None), tls_cert=pki["cert"], tls_key=pki["key"])
    d = FakeDaemon()
    port = _free_port()
    caplog.set_level(logging.INFO, logger="hexacnc.daemon.access")
    with SocketServer(d, cfg, os.path.join(pki["dir"], "s.sock"), tcp_port=port, tcp_token=TOKEN) as srv:
        with P.Client.tcp(port, TOKEN, tls_ca=pki["cert"]) as c:
            assert c.call("status")["access"] == "controller"
            c.call("program", text="G1 X1\n", name="tls.ngc")
            assert c.call("wait", timeout_s=10)["state"] == "idle"
        # plaintext hello (the token in clear) gets no answer and a logged refusal
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        s.sendall(msgpack.packb({"id": 1, "op": "hello", "token": "0" * 64}))
        s.settimeout(5)
        try:
            data = s.recv(4096)
        except ConnectionResetError:
            data = b""
        s.close()
        assert b"unauthorized" not in data and srv.stats["auth_failed"] == 0
        assert any("op connect: receive failed" in r.getMessage() for r in caplog.records)
        # a client that does not trust this certificate does not send its token
        with pytest.raises(P.ConnectionLost, match="certificate verify failed"):
            P.Client.tcp(port, TOKEN, tls_ca=pki["other"])
        assert srv.stats["auth_failed"] == 0
        # wrong tokens inside TLS are limited as without it
        with pytest.raises(P.DaemonError, match="wrong token"):
            P.Client.tcp(port, secrets.token_hex(32), tls_ca=pki["cert"])
        assert srv.stats["auth_failed"] == 1
        with P.Client.unix(srv.socket_path) as c:        # the local controller is unaffected
            assert c.call("status")["ok"]
    d.close()


def test_tls_configuration_is_checked(pki):
    base = open(os.path.join(os.path.dirname(__file__), "..", "config", "default.toml")).read()
    p = os.path.join(pki["dir"], "m.toml")
    for extra, msg in (('tcp_host = "0.0.0.0"\n', r"\[daemon\] tcp_host: .* not a loopback address: .* needs TLS"),
                       ('tcp_host = "localhost"\n', r"\[daemon\] tcp_host: .* not an IP address"),
                       (f'tls_cert = "{pki["cert"]}"\n', r"\[daemon\] tls_key: tls_cert and tls_key go together")):
        with open(p, "w") as f:
            f.write(base.replace("[daemon]\n", "[daemon]\n" + extra))
        with pytest.raises(ConfigError, match=msg):
            load_config(p)
    with open(p, "w") as f:
        f.write(base.replace("[daemon]\n", f'[daemon]\ntcp_host = "0.0.0.0"\ntls_cert = "{pki["cert"]}"\n'
                                           f'tls_key = "{pki["key"]}"\n'))
    assert load_config(p).daemon.tcp_host == "0.0.0.0"          # allowed with TLS (not bound here)
    os.chmod(pki["key"], 0o640)
    fake = FakeDaemon()
    try:
        with pytest.raises(HexacncError, match=r"tls_key .* mode 0640"):
            SocketServer(fake, cfg_with(load_config(None), tls_cert=pki["cert"], tls_key=pki["key"]),
                         os.path.join(pki["dir"], "t.sock"), tcp_port=_free_port(), tcp_token=TOKEN)
    finally:
        os.chmod(pki["key"], 0o600)
        fake.close()
