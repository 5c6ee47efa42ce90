"""Who may speak in a mesh run: one certificate per process identity, and
the zenoh configuration that makes zenoh enforce it (docs/security.md).

``issue(run_id, agents)`` creates a fresh certificate authority for one
run, issues one certificate and key per identity, in memory, and throws the
CA's key away (nobody can mint another identity for this run afterwards).
``up`` hands each of its processes its own identity alone (``bundle``) on
standard input (``--credentials -``), so no key of its runs is ever on
disk. ``make(out, run_id, agents)`` (``diskf-mesh credentials``, for
processes started by hand) writes them to disk:

    out/                          0700
      world/                      0700, one directory per identity
        ca.pem                    the run's CA certificate
        cert.pem                  this identity's certificate (CN = identity)
        key.pem                   its private key, 0600
        run.json                  run id, agent ids, the identity's name
      agent-<id>/ ...             one per agent of the scenario
      observer/ ...               may only listen (a program the user runs beside the mesh)
      router/ ...                 a zenoh router of the run (``diskf-mesh router``,
                                  docs/hosts.md): it forwards everything of the run

``world_routes=True`` (``diskf-mesh credentials --world-routes``; ``up
--hosts`` when a host has no router) grants the world a router's rights
as well: a host without a router has its agents connect to the world,
which then forwards their traffic (docs/hosts.md).

Every identity directory is self-contained: a process reads its own
directory only (``load``), and a host or container needs only its own.

``zenoh_settings(identity)`` is the zenoh configuration of that identity:
TLS links only (``transport/link/protocols = ["tls"]``, so neither a listen
endpoint, a connect endpoint nor a locator found by scouting can open plain
TCP), mutual authentication against the run's CA, and zenoh's access
control, default deny, with one subject per certificate common name. Every
process applies the same policy to what it receives (ingress) from each
peer, by the peer's certificate:

    world        put               diskf/<run>/world/**
                 liveliness token  diskf/<run>/alive/world/<nonce>, diskf/<run>/ticking/world
                 subscribe         diskf/<run>/agent/*/{report,duplicate,stopped};
                                   tokens diskf/<run>/*/agent/*/*, diskf/<run>/alive/world/*
                 answer queries    diskf/<run>/start/* (an agent's starting estimate)
    agent-<i>    put               diskf/<run>/agent/<i>/**
                 liveliness token  diskf/<run>/alive/agent/<i>/<nonce>, diskf/<run>/ready/agent/<i>/<nonce>
                 subscribe         the world's tick and stop, its own measurement
                                   diskf/<run>/world/meas/<i>, the messages addressed to
                                   it; tokens alive/**, ticking/world (no report: the
                                   reports reach the world and the observer only)
                 query             diskf/<run>/start/<i> (its own starting estimate)
    observer     subscribe         diskf/<run>/** (samples and tokens), nothing else
    router       everything        diskf/<run>/** both ways: it forwards the others' traffic,
                                   so a receiver behind it sees the router's certificate, not
                                   the sender's; each router applies the rules above to the
                                   processes connected to it (docs/hosts.md)
    world, with  everything        as a router, besides the world's own rules above: only in
    world_routes                   a run whose credentials say so (a host without a router)

A declaration refused at ingress never enters the receiver's routing
tables, so the receiver does not send that peer what it asked for. That
alone leaks: until a new peer's declarations have arrived, zenoh sends it
every put (measured: agent 2 subscribed to ``world/meas/*`` heard one of
agent 1's measurements in 8 connections). So what a process sends (egress)
is filtered by the receiver too: a put goes to an identity only on the keys
that identity may subscribe to (the "subscribe" column), every declaration
and token to every identity of the run.
"""
from __future__ import annotations

import base64
import datetime
import ipaddress
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from diskf_mesh.core.errors import InputError
from diskf_mesh.mesh.wire.keys import check_run_id

FORMAT = "diskf-credentials/1"
BUNDLE_FORMAT = "diskf-identities/1"  # identities handed over in memory (``bundle``)
PR_SET_DUMPABLE = 4
WORLD = "world"
OBSERVER = "observer"
ROUTER = "router"
CA_FILE, CERT_FILE, KEY_FILE, RUN_FILE = "ca.pem", "cert.pem", "key.pem", "run.json"
VALID_DAYS = 30
HOSTS = ("127.0.0.1", "localhost")  # subjectAltNames of every certificate, next to its identity


def agent_identity(agent_id: int) -> str:
    return f"agent-{int(agent_id)}"


def identities(agents, observer: bool = True, router: bool = True) -> list:
    """Every identity of a run: the world, one per agent, the observer, the router."""
    return [WORLD, *(agent_identity(i) for i in agents), *([OBSERVER] if observer else []),
            *([ROUTER] if router else [])]


# --------------------------------------------------------------------------
# making them
# --------------------------------------------------------------------------
def _private_dir(path: Path) -> Path:
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    path.chmod(0o700)
    return path


def _write(path: Path, data: bytes, mode: int) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, mode)


def issue(run_id: str, agents, observer: bool = True, router: bool = True, world_routes: bool = False) -> dict:
    """A fresh CA and one certificate + key per identity of run ``run_id``,
    in memory: {identity name: ``Identity``}. The CA's key is not kept
    (nobody can mint another identity of the run afterwards)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    check_run_id(run_id)
    agents = tuple(sorted({int(i) for i in agents}))
    name = lambda cn: x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])  # noqa: E731
    now = datetime.datetime.now(datetime.timezone.utc)
    start, end = now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=VALID_DAYS)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = name(f"diskf run {run_id} CA")
    ca = (x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
          .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                       content_commitment=False, key_encipherment=False, data_encipherment=False,
                                       key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
          .sign(ca_key, hashes.SHA256()))
    ca_pem = ca.public_bytes(serialization.Encoding.PEM)
    out = {}
    for who in identities(agents, observer, router):
        key = ec.generate_private_key(ec.SECP256R1())
        sans = [x509.DNSName(who)] + [x509.IPAddress(ipaddress.ip_address(h)) if h[0].isdigit() else x509.DNSName(h)
                                      for h in HOSTS]
        cert = (x509.CertificateBuilder().subject_name(name(who)).issuer_name(ca_name).public_key(key.public_key())
                .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.SubjectAlternativeName(sans), critical=False)
                .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                      ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
                .sign(ca_key, hashes.SHA256()))
        out[who] = Identity(who, run_id, agents, observer, None, router, world_routes, ca_pem,
                            cert.public_bytes(serialization.Encoding.PEM),
                            key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                              serialization.NoEncryption()))
    return out  # ca_key goes out of scope here: the CA signs nothing more


def make(out, run_id: str, agents, observer: bool = True, router: bool = True, world_routes: bool = False) -> Path:
    """``issue``, written to ``out`` (created 0700; an identity directory
    already there is replaced) as in the module docstring. Returns ``out``."""
    check_run_id(run_id)
    out = Path(out)
    try:
        _private_dir(out)
    except OSError as e:
        raise InputError("out", f"cannot create {out}: {e.strerror or e}") from None
    for who, ident in issue(run_id, agents, observer, router, world_routes).items():
        d = _private_dir(out / who)
        _write(d / KEY_FILE, ident.key_pem, 0o600)
        _write(d / CERT_FILE, ident.cert_pem, 0o644)
        _write(d / CA_FILE, ident.ca_pem, 0o644)
        _write(d / RUN_FILE, (json.dumps(ident.description()) + "\n").encode(), 0o644)
    return out


# --------------------------------------------------------------------------
# using them
# --------------------------------------------------------------------------
@dataclass(frozen=True)
class Identity:
    """One identity of a run: its certificate, its private key, the run's CA
    certificate (PEM bytes, held in memory) and what the run says of it."""

    name: str
    run_id: str
    agents: tuple
    observer: bool
    dir: Path | None = None  # where it was read from (None: handed over in memory)
    router: bool = False
    world_routes: bool = False
    ca_pem: bytes = field(default=b"", repr=False)
    cert_pem: bytes = field(default=b"", repr=False)
    key_pem: bytes = field(default=b"", repr=False)

    def description(self) -> dict:
        """The identity's ``run.json``."""
        return {"format": FORMAT, "run_id": self.run_id, "agents": list(self.agents), "observer": self.observer,
                "router": self.router, "world_routes": self.world_routes, "identity": self.name}


def _identity(doc, name: str, where: str, ca=b"", cert=b"", key=b"", d: Path | None = None) -> Identity:
    """An ``Identity`` from a ``run.json`` document ``doc`` (checked)."""
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError("credentials", f"{where} is not a {FORMAT} file")
    if doc.get("identity") != name:
        raise InputError("credentials", f"{where} holds the credentials of {doc.get('identity')!r}, not {name!r}")
    try:
        agents = tuple(int(i) for i in doc["agents"])
        check_run_id(doc["run_id"])
    except (KeyError, TypeError, ValueError, InputError):
        raise InputError("credentials", f"{where}: bad run id or agent list") from None
    return Identity(name, doc["run_id"], agents, bool(doc.get("observer", False)), d, bool(doc.get("router", False)),
                    bool(doc.get("world_routes", False)), ca, cert, key)


def _check_run(ident: Identity, run_id: str | None, where) -> Identity:
    if run_id is not None and ident.run_id != run_id:
        raise InputError("credentials", f"{where} is for run {ident.run_id!r}, not {run_id!r} "
                                        f"(give --run-id {ident.run_id})")
    return ident


def load(directory, identity: str, run_id: str | None = None) -> Identity:
    """Identity ``identity`` from ``directory`` (a run's credentials
    directory, or that identity's own directory), read into memory.
    ``InputError`` if the files are missing, the key is readable by others,
    or they belong to another identity or run."""
    base = Path(directory)
    d = base if (base / RUN_FILE).is_file() else base / identity
    try:
        doc = json.loads((d / RUN_FILE).read_text())
        mode = (d / KEY_FILE).stat().st_mode & 0o777
        pems = [(d / f).read_bytes() for f in (CA_FILE, CERT_FILE, KEY_FILE)]
    except (OSError, ValueError) as e:
        raise InputError("credentials", f"no credentials for {identity} in {base}: "
                                        f"{getattr(e, 'strerror', None) or e}") from None
    ident = _check_run(_identity(doc, identity, str(d / RUN_FILE), *pems, d=d), run_id, base)
    if mode & 0o077:
        raise InputError("credentials", f"{d / KEY_FILE} is readable by others (mode {mode:o}); it must be 0600")
    return ident


# --------------------------------------------------------------------------
# handing them over in memory (``up``: each child its own, on its standard input)
# --------------------------------------------------------------------------
def bundle(idents) -> bytes:
    """The identities ``idents`` as one document (``BUNDLE_FORMAT``), for
    ``--credentials -`` (read from standard input)."""
    return json.dumps({"format": BUNDLE_FORMAT, "identities": [
        {**i.description(), "ca": i.ca_pem.decode(), "cert": i.cert_pem.decode(), "key": i.key_pem.decode()}
        for i in idents]}).encode()


def unbundle(data: bytes, where: str = "standard input") -> dict:
    """{name: ``Identity``} of a ``bundle`` document; ``InputError`` if it is not one."""
    try:
        doc = json.loads(data)
        items = doc["identities"] if isinstance(doc, dict) and doc.get("format") == BUNDLE_FORMAT else None
        if not isinstance(items, list):
            raise ValueError
        out = {}
        for item in items:
            pems = [item[f].encode() for f in ("ca", "cert", "key")]
            out[item["identity"]] = _identity(item, item["identity"], where, *pems)
    except (ValueError, TypeError, KeyError, AttributeError):
        raise InputError("credentials", f"{where} holds no {BUNDLE_FORMAT} document") from None
    return out


def pick(held: dict, identity: str, run_id: str | None = None, where: str = "standard input") -> Identity:
    """``identity`` of the identities ``held`` (``unbundle``), for run ``run_id``."""
    if identity not in held:
        raise InputError("credentials", f"no credentials for {identity} on {where} "
                                        f"(it holds {', '.join(sorted(held)) or 'none'})")
    return _check_run(held[identity], run_id, where)


def keep_private() -> None:
    """Make this process's memory and open files unreadable by other
    processes of its user (Linux: not dumpable, so ``/proc/PID/mem``,
    ``/proc/PID/fd`` and ptrace need CAP_SYS_PTRACE). Called by every
    process that holds a private key."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_DUMPABLE, 0, 0, 0, 0)
    except (OSError, AttributeError):
        pass


ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "liveliness_query", "declare_liveliness_subscriber")
LISTEN = ("declare_subscriber",)
WATCH = ("declare_liveliness_subscriber", "liveliness_query")
ANSWER = ("declare_queryable", "reply")


def access_control(run_id: str, agents, observer: bool = True, router: bool = False,
                   world_routes: bool = False) -> dict:
    """zenoh's ``access_control`` of a run (the table in the module docstring)."""
    r = f"diskf/{run_id}"
    rules, subjects, policies = [], [], []

    def rule(rid, messages, keys, flows=("ingress",)):
        rules.append({"id": rid, "permission": "allow", "flows": list(flows), "messages": list(messages),
                      "key_exprs": list(keys)})
        return rid

    def grant(who, listens, *rule_ids):
        """``who`` subscribes to ``listens`` and is sent puts on those keys only."""
        subjects.append({"id": who, "cert_common_names": [who]})
        policies.append({"id": who, "subjects": [who], "rules": [
            rule(f"{who}-listen", LISTEN, listens), rule(f"{who}-receive", ("put",), listens, flows=("egress",)),
            *rule_ids, "egress"]})

    rule("egress", [m for m in ALL_MESSAGES if m != "put"], [f"{r}/**"], flows=("egress",))
    routes = (rule("world-routes", ALL_MESSAGES, [f"{r}/**"]),) if world_routes else ()
    grant(WORLD, [f"{r}/**"] if world_routes else [f"{r}/agent/*/report", f"{r}/agent/*/duplicate",
                                                   f"{r}/agent/*/stopped"],
          rule("world-put", ("put",), [f"{r}/world/**"]),
          rule("world-tokens", ("liveliness_token",), [f"{r}/alive/world/*", f"{r}/ticking/world"]),
          rule("world-watch", WATCH, [f"{r}/*/agent/*/*", f"{r}/alive/world/*"]),
          rule("world-answer", ANSWER, [f"{r}/start/*"]), *routes)
    watch = rule("agent-watch", WATCH, [f"{r}/alive/**", f"{r}/ticking/world"])
    for i in agents:
        who = agent_identity(i)
        grant(who, [f"{r}/world/tick", f"{r}/world/stop", f"{r}/world/meas/{i}", f"{r}/agent/*/msg/$*_{i}_$*"],
              rule(f"{who}-put", ("put",), [f"{r}/agent/{i}/**"]),
              rule(f"{who}-tokens", ("liveliness_token",), [f"{r}/alive/agent/{i}/*", f"{r}/ready/agent/{i}/*"]),
              rule(f"{who}-ask", ("query",), [f"{r}/start/{i}"]),
              watch)
    if observer:
        grant(OBSERVER, [f"{r}/**"], rule("observer-watch", WATCH, [f"{r}/**"]))
    if router:
        grant(ROUTER, [f"{r}/**"], rule("router-all", ALL_MESSAGES, [f"{r}/**"]))
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def zenoh_settings(ident: Identity) -> list:
    """(config path, JSON5 value) pairs that make a zenoh session this
    identity: TLS only, mutual authentication, the run's access control.
    Endpoints and the mode stay with the command line's flags."""
    b64 = lambda pem: base64.b64encode(pem).decode()  # noqa: E731
    tls = {  # inline: zenoh reads no file, and no key is written anywhere for it
        "root_ca_certificate_base64": b64(ident.ca_pem),
        "listen_certificate_base64": b64(ident.cert_pem), "listen_private_key_base64": b64(ident.key_pem),
        "connect_certificate_base64": b64(ident.cert_pem), "connect_private_key_base64": b64(ident.key_pem),
        "enable_mtls": True,
        # a peer is who its certificate says (the access control checks that), wherever it
        # listens: an address found by scouting or gossip is not in any certificate
        "verify_name_on_connect": False,
    }
    return [
        ("transport/link/protocols", json.dumps(["tls"])),
        ("transport/link/tls", json.dumps(tls)),
        ("access_control", json.dumps(access_control(ident.run_id, ident.agents, ident.observer, ident.router,
                                                     ident.world_routes))),
    ]
