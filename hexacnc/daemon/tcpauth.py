"""TCP authentication: the token, its file, constant-time checks, pre-auth limits, rate limiting.

* The token comes from ``[daemon] token_file`` - a regular file owned by the daemon's user (or
  root) that neither group nor others may read or write - or from the legacy ``[daemon]
  tcp_token``.  Either way it must hold at least 128 bits (:func:`token_weakness`): the daemon
  refuses to start otherwise, with the reason (never the value).
* ``hello`` tokens are compared in constant time (:func:`token_matches`).
* Before authentication a connection may send at most :data:`PREAUTH_MAX_BYTES` and must
  authenticate within :data:`AUTH_TIMEOUT_S`; unauthenticated connections live in their own pool
  (``[daemon] max_unauthenticated``, the oldest is closed for a newcomer) and never take a client
  slot.
* Failed attempts are rate-limited per peer address (:class:`FailureLimiter`): after the n-th
  failure in a row the address waits 0.1 s * 2**(n-1) (at most 30 s) before its next token is
  even compared - at most 10 guesses per second, fewer the longer it goes on.
"""
from __future__ import annotations

import hashlib
import hmac
import math
import os
import stat
import string
import time
from collections import OrderedDict

from ..errors import HexacncError

#: least token strength accepted (bits)
MIN_TOKEN_BITS = 128
#: bytes a TCP connection may send before it has authenticated
PREAUTH_MAX_BYTES = 1024
#: a TCP connection must authenticate within this time (s)
AUTH_TIMEOUT_S = 2.0
#: shortest interval between two token comparisons for one address (s): <= 10 guesses/s
MIN_INTERVAL_S = 0.1
#: longest back-off (s)
MAX_DELAY_S = 30.0
#: addresses remembered by the limiter (oldest forgotten first)
MAX_ADDRESSES = 4096
#: an address quiet this long after its back-off is forgotten (s)
FORGET_S = 600.0
#: largest token file read (bytes)
MAX_TOKEN_FILE_BYTES = 4096

_HEX = frozenset(string.hexdigits)
_B32 = frozenset(string.ascii_uppercase + "234567=")
_ALNUM = frozenset(string.ascii_letters + string.digits)
_B64 = frozenset(string.ascii_letters + string.digits + "+/-_=")
_PRINT = frozenset(chr(c) for c in range(0x21, 0x7F))
#: (alphabet, bits per character), smallest first
_CLASSES = ((frozenset(string.digits), math.log2(10)), (_HEX, 4.0),
            (frozenset(string.ascii_lowercase), math.log2(26)), (frozenset(string.ascii_uppercase), math.log2(26)),
            (_B32, 5.0), (frozenset(string.ascii_lowercase + string.digits), math.log2(36)),
            (frozenset(string.ascii_uppercase + string.digits), math.log2(36)), (_ALNUM, math.log2(62)),
            (_B64, 6.0), (_PRINT, math.log2(94)))


def token_bits(token: str) -> float:
    """An upper bound of the token's strength: length x bits per character of the smallest usual
    alphabet (digits, hex, one-case letters, base32, one-case alphanumeric, alphanumeric, base64,
    printable ASCII) holding all its characters.  A word-like token is still weaker than this
    bound: the rule refuses what cannot hold 128 bits, it cannot prove randomness."""
    chars = set(token)
    for alphabet, bits in _CLASSES:
        if chars <= alphabet:
            return len(token) * bits
    return len(token.encode("utf-8", "surrogatepass")) * 8.0


def token_weakness(token: str) -> str:
    """"" for an acceptable token, else why it is refused (without the value)."""
    if not token:
        return "the token is empty"
    if token != token.strip():
        return "the token has leading or trailing white space"
    bits = token_bits(token)
    if bits < MIN_TOKEN_BITS:
        return (f"the token is too weak: {len(token)} characters hold at most {bits:.0f} bits, at least "
                f"{MIN_TOKEN_BITS} are required (e.g. python3 -c 'import secrets; print(secrets.token_hex(32))')")
    if len(set(token)) < 8:
        return f"the token is too repetitive ({len(set(token))} distinct characters): use a random one"
    return ""


def load_token_file(path: str) -> str:
    """The token in ``path``; raises HexacncError if the file could leak it or the token is weak."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        raise HexacncError(f"[daemon] token_file {path}: cannot open: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise HexacncError(f"[daemon] token_file {path}: not a regular file")
        if st.st_uid not in (os.geteuid(), 0):
            raise HexacncError(f"[daemon] token_file {path}: owned by uid {st.st_uid}, not by the daemon's "
                               f"user (uid {os.geteuid()}) or root")
        if st.st_mode & 0o077:
            raise HexacncError(f"[daemon] token_file {path}: mode {stat.S_IMODE(st.st_mode):04o} lets "
                               f"{'others' if st.st_mode & 0o007 else 'its group'} read or change the token; "
                               f"chmod 600 {path}")
        data = os.read(fd, MAX_TOKEN_FILE_BYTES + 1)
    finally:
        os.close(fd)
    if len(data) > MAX_TOKEN_FILE_BYTES:
        raise HexacncError(f"[daemon] token_file {path}: larger than {MAX_TOKEN_FILE_BYTES} bytes")
    try:
        token = data.decode("utf-8").strip()
    except UnicodeDecodeError:
        raise HexacncError(f"[daemon] token_file {path}: not UTF-8 text") from None
    weak = token_weakness(token)
    if weak:
        raise HexacncError(f"[daemon] token_file {path}: {weak}")
    return token


def _digest(token: str) -> bytes:
    return hashlib.sha256(token.encode("utf-8", "surrogatepass")).digest()


def token_matches(given: object, secret_digest: bytes) -> bool:
    """Constant-time comparison of a ``hello`` token with the secret's SHA-256 (lengths do not leak)."""
    if not isinstance(given, str) or len(given) > MAX_TOKEN_FILE_BYTES:
        return False
    return hmac.compare_digest(_digest(given), secret_digest)


def secret_digest(token: str) -> bytes:
    return _digest(token)


def resolve_token(dcfg, override: str | None = None) -> str:
    """The TCP token: ``override`` (tests), else ``token_file``, else the legacy ``tcp_token``;
    refused if weak.  The legacy key's config file must not be readable by others."""
    if override is not None and override != "":
        token, where = override, "tcp_token"
    elif getattr(dcfg, "token_file", ""):
        return load_token_file(dcfg.token_file)
    else:
        token, where = getattr(dcfg, "tcp_token", ""), "[daemon] tcp_token"
    weak = token_weakness(token)
    if weak:
        raise HexacncError(f"{where}: {weak}")
    return token


def config_file_leaks(path: str | None) -> str:
    """Why a config file holding ``tcp_token`` leaks it ("" when it does not, or is embedded)."""
    if not path or not os.path.isfile(path):
        return ""
    st = os.stat(path)
    if st.st_mode & 0o077:
        return (f"{path} holds [daemon] tcp_token but has mode {stat.S_IMODE(st.st_mode):04o}: other users "
                f"can read the token; chmod 600 it or move the token to [daemon] token_file")
    return ""


class FailureLimiter:
    """Per-address back-off after failed authentications (memory bounded)."""

    def __init__(self, min_interval_s: float = MIN_INTERVAL_S, max_delay_s: float = MAX_DELAY_S,
                 max_addresses: int = MAX_ADDRESSES):
        self.min_interval_s = min_interval_s
        self.max_delay_s = max_delay_s
        self.max_addresses = max_addresses
        self._s: OrderedDict[str, list] = OrderedDict()     # address -> [failures, next_allowed]

    def retry_after(self, address: str, now: float | None = None) -> float:
        """Seconds before ``address`` may try again (0: now)."""
        e = self._s.get(address)
        if e is None:
            return 0.0
        now = time.monotonic() if now is None else now
        if now - e[1] > FORGET_S:
            del self._s[address]
            return 0.0
        return max(0.0, e[1] - now)

    def failed(self, address: str, now: float | None = None) -> float:
        """Record a failure; returns the back-off (s) now imposed on ``address``."""
        now = time.monotonic() if now is None else now
        e = self._s.pop(address, None) or [0, now]
        e[0] += 1
        delay = min(self.max_delay_s, self.min_interval_s * 2.0 ** min(e[0] - 1, 30))
        e[1] = now + delay
        self._s[address] = e
        while len(self._s) > self.max_addresses:
            self._s.popitem(last=False)
        return delay

    def succeeded(self, address: str) -> None:
        self._s.pop(address, None)


class LogThrottle:
    """At most ``per_s`` log lines per second for one kind of event; the rest are counted and
    reported with the next line that passes."""

    def __init__(self, per_s: int = 20):
        self.per_s = per_s
        self._t = 0.0
        self._n = 0
        self.suppressed = 0

    def allow(self, now: float | None = None) -> tuple[bool, int]:
        """(log this one?, lines suppressed since the last one logged)."""
        now = time.monotonic() if now is None else now
        if now - self._t >= 1.0:
            self._t, self._n = now, 0
        self._n += 1
        if self._n > self.per_s:
            self.suppressed += 1
            return False, 0
        n, self.suppressed = self.suppressed, 0
        return True, n


__all__ = ["MIN_TOKEN_BITS", "PREAUTH_MAX_BYTES", "AUTH_TIMEOUT_S", "token_bits", "token_weakness",
           "load_token_file", "token_matches", "secret_digest", "resolve_token", "config_file_leaks",
           "FailureLimiter", "LogThrottle"]


def client_token(dcfg) -> str:
    """The token a client sends: ``[daemon] token_file`` when readable by this user, else ``tcp_token``."""
    path = getattr(dcfg, "token_file", "")
    if path:
        try:
            with open(path, encoding="utf-8") as f:
                return f.read(MAX_TOKEN_FILE_BYTES).strip()
        except OSError as exc:
            raise HexacncError(f"[daemon] token_file {path}: cannot read: {exc.strerror or exc} "
                               f"(pass --token or $HEXACNC_TOKEN)") from None
    return getattr(dcfg, "tcp_token", "")
