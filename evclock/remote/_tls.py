"""TLS for ``tls://HOST:PORT``: protocol v3 unchanged, inside TLS 1.3 (stdlib :mod:`ssl`).

The server presents a certificate (``tls_cert``, ``tls_key``); a participant verifies it
against a CA file (``tls_ca``, with the host name or IP address of its URL) or a pinned
SHA-256 fingerprint of the server's certificate (``tls_fingerprint``), before it sends a
byte of the protocol. The token still authenticates the participant, by the same HMAC
handshake inside TLS: TLS keeps the traffic private and says which server this is; the
token says who may join.

A non-blocking TLS socket reads whole records: bytes of a record already decrypted wait in
the SSL object (``pending()``), where a poll of the raw socket cannot see them. Every read
here (:func:`recv`) therefore drains the SSL object, so nothing is ever left where a poll
would miss it.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import socket
import ssl

from evclock._errors import ClockLostError, InvalidArgumentError, JoinRefusedError

#: What a non-blocking send or receive raises when it must be tried again later (TLS: the
#: SSL object wants the socket readable or writable first).
WOULD_BLOCK = (BlockingIOError, InterruptedError, ssl.SSLWantReadError, ssl.SSLWantWriteError)
#: The first byte of every TLS connection (a handshake record): how a TLS server recognises
#: a plain client, and a plain server a TLS client.
TLS_RECORD_HANDSHAKE = 0x16


def recv(sock: socket.socket, size: int) -> bytes:
    """Up to ``size`` bytes from ``sock`` (more on TLS: whatever the SSL object had already
    decrypted, so that a poll of the socket afterwards misses nothing); raises as
    ``sock.recv`` does (:data:`WOULD_BLOCK` when nothing is there)."""
    data = sock.recv(size)
    if data and isinstance(sock, ssl.SSLSocket):
        left = sock.pending()
        if left:
            chunks = [data]
            while left:
                chunks.append(sock.recv(left))
                left = sock.pending()
            data = b"".join(chunks)
    return data


def pending(sock: socket.socket) -> bool:
    """Whether decrypted bytes wait in ``sock``'s SSL object (never on a plain socket)."""
    return isinstance(sock, ssl.SSLSocket) and sock.pending() > 0


def parse_fingerprint(raw: str) -> bytes:
    """The 32 bytes of a SHA-256 fingerprint written in hex (colons allowed, as
    ``openssl x509 -fingerprint -sha256`` prints it)."""
    digits = raw.replace(":", "").strip()
    try:
        value = bytes.fromhex(digits)
    except ValueError:
        value = b""
    if len(value) != 32:
        raise InvalidArgumentError(
            f"tls_fingerprint must be the SHA-256 fingerprint of the server's certificate, 64 "
            f"hex digits (colons allowed: `openssl x509 -in cert.pem -noout -fingerprint "
            f"-sha256` prints it), got {raw!r}"
        )
    return value


def certificate_fingerprint(der: bytes) -> str:
    """The SHA-256 fingerprint of a DER certificate, as colon-separated hex."""
    return hashlib.sha256(der).digest().hex(":").upper()


def _readable_file(path: str, what: str) -> str:
    if not isinstance(path, str | os.PathLike):
        raise InvalidArgumentError(f"{what} is a file path, got {path!r}")
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InvalidArgumentError(f"{what} {path!r} is not a readable file")
    return path


def server_context(cert: str, key: str) -> ssl.SSLContext:
    """A TLS 1.3 server context presenting ``cert`` (PEM, the chain) with its ``key``."""
    cert = _readable_file(cert, "tls_cert")
    key = _readable_file(key, "tls_key")
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_3
    context.num_tickets = 0  # no session resumption: no ticket records after the handshake
    try:
        context.load_cert_chain(cert, key)
    except (ssl.SSLError, OSError) as exc:
        raise InvalidArgumentError(
            f"cannot use the TLS certificate {cert!r} with the key {key!r}: {exc} (both PEM; "
            "the key must belong to the certificate)"
        ) from None
    return context


def client_context(ca: str | None, fingerprint: bytes | None) -> ssl.SSLContext:
    """A TLS 1.3 client context: verifies the chain and host name against ``ca``, or
    nothing here when only ``fingerprint`` is given (:func:`check_fingerprint` then does)."""
    if ca is None and fingerprint is None:
        raise InvalidArgumentError(
            "a tls:// clock address needs a way to verify the server: ?tls_ca=/path/ca.pem "
            "(the CA that signed its certificate) or ?tls_fingerprint=SHA256 (its "
            "certificate's fingerprint)"
        )
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.minimum_version = ssl.TLSVersion.TLSv1_3
    if ca is None:
        context.check_hostname = False
        context.verify_mode = ssl.CERT_NONE  # the pinned fingerprint is the check
    else:
        ca = _readable_file(ca, "tls_ca")
        try:
            context.load_verify_locations(cafile=ca)
        except (ssl.SSLError, OSError) as exc:
            raise InvalidArgumentError(f"cannot read the CA file {ca!r}: {exc}") from None
    return context


def wrap_client(
    sock: socket.socket,
    context: ssl.SSLContext,
    host: str,
    fingerprint: bytes | None,
    where: str,
) -> ssl.SSLSocket:
    """The TLS handshake of a participant on the connected ``sock`` (its timeout applies):
    the server's certificate verified before anything of the protocol is sent.

    :raises JoinRefusedError: the certificate is not the server's (wrong CA, host name or
        fingerprint).
    :raises ClockLostError: the handshake failed otherwise (not a TLS server, timeout).
    """
    try:
        tls = context.wrap_socket(sock, server_hostname=host)
    except ssl.SSLCertVerificationError as exc:
        raise JoinRefusedError(
            f"the clock server at {where} presented a certificate that does not verify "
            f"({exc.verify_message}): it is not the simulation you meant, or tls_ca names "
            "another CA; nothing was sent to it"
        ) from None
    except ssl.SSLError as exc:
        raise ClockLostError(
            f"the TLS handshake with the clock server at {where} failed ({exc.reason or exc}): "
            "is it serving tls://? A simulation served on tcp:// speaks plain TCP (join it "
            "with tcp://)"
        ) from None
    except OSError as exc:
        raise ClockLostError(
            f"the TLS handshake with the clock server at {where} failed: {exc}"
        ) from None
    if fingerprint is not None:
        der = tls.getpeercert(binary_form=True) or b""
        if not hmac.compare_digest(hashlib.sha256(der).digest(), fingerprint):
            tls.close()
            raise JoinRefusedError(
                f"the clock server at {where} presented a certificate with SHA-256 fingerprint "
                f"{certificate_fingerprint(der)}, not the pinned "
                f"{fingerprint.hex(':').upper()}: it is not the simulation you meant; nothing "
                "was sent to it"
            )
    return tls
