"""What a process holds in memory: the private keys and certificates an
attacker who has compromised it (or who may read its memory: root, or its
user if it did not close itself, ``credentials.keep_private``) finds there.

``pems(pid)`` scans every readable writable mapping of ``/proc/PID/mem``
for PEM blocks (as written, or inside a JSON string with escaped newlines);
``identity_of(pid, name, run_id, agents)`` rebuilds the identity ``name``
from them, as a compromised process would use it.
"""
from __future__ import annotations

import re

from cryptography import x509
from cryptography.hazmat.primitives import serialization

from diskf_mesh.mesh.security import credentials

_PEM = re.compile(rb"-----BEGIN (PRIVATE KEY|CERTIFICATE)-----((?:\\n|\n|[A-Za-z0-9+/=]){40,8000}?)"
                  rb"-----END \1-----")
_DER = serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo


def _regions(pid: int):
    with open(f"/proc/{pid}/maps") as f:
        for line in f:
            addr, perms, *rest = line.split()
            path = rest[3] if len(rest) > 3 else ""
            if perms.startswith("rw") and not path.startswith("/dev/"):
                lo, hi = (int(a, 16) for a in addr.split("-"))
                yield lo, hi


def pems(pid: int) -> dict:
    """{"PRIVATE KEY": {pem, ...}, "CERTIFICATE": {pem, ...}} found in the
    memory of process ``pid`` (each normalised to plain PEM)."""
    found = {"PRIVATE KEY": set(), "CERTIFICATE": set()}
    with open(f"/proc/{pid}/mem", "rb", buffering=0) as mem:
        for lo, hi in _regions(pid):
            try:
                mem.seek(lo)
                data = mem.read(hi - lo)
            except (OSError, OverflowError, ValueError):
                continue
            for m in _PEM.finditer(data):
                body = m.group(2).replace(b"\\n", b"\n").strip()
                kind = m.group(1).decode()
                found[kind].add(b"-----BEGIN %s-----\n%s\n-----END %s-----\n" % (m.group(1), body, m.group(1)))
    return found


def usable_keys(found: dict) -> list:
    """The private keys of ``found`` that load, as DER public keys."""
    out = set()
    for pem in found["PRIVATE KEY"]:
        try:
            out.add(serialization.load_pem_private_key(pem, None).public_key().public_bytes(*_DER))
        except ValueError:
            continue
    return sorted(out)


def certificates(found: dict) -> dict:
    """{common name: certificate} of the certificates of ``found`` that load."""
    out = {}
    for pem in found["CERTIFICATE"]:
        try:
            cert = x509.load_pem_x509_certificate(pem)
        except ValueError:
            continue
        cn = cert.subject.get_attributes_for_oid(x509.oid.NameOID.COMMON_NAME)
        if cn:
            out[cn[0].value] = cert
    return out


def public_key(cert) -> bytes:
    return cert.public_key().public_bytes(*_DER)


def identity_of(pid: int, name: str, run_id: str, agents) -> credentials.Identity:
    """Identity ``name`` of run ``run_id`` as found in process ``pid``'s
    memory (its key, its certificate, the CA's), for a zenoh session."""
    found = pems(pid)
    certs = certificates(found)
    cert = certs[name]
    ca = next(c for c in certs.values() if c.subject == c.issuer == cert.issuer)
    key = next(k for k in found["PRIVATE KEY"] if _loads(k) == public_key(cert))
    pem = lambda c: c.public_bytes(serialization.Encoding.PEM)  # noqa: E731
    return credentials.Identity(name, run_id, tuple(agents), True, None, False, False, pem(ca), pem(cert), key)


def _loads(key_pem: bytes) -> bytes | None:
    try:
        return serialization.load_pem_private_key(key_pem, None).public_key().public_bytes(*_DER)
    except ValueError:
        return None
