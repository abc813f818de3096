"""Node identities (issue 27, Build 2): TLS 1.3 from the standard library's ``ssl``, or mso's own
handshake with an Ed25519 proof of identity, measured side by side.

Both sides of one connection run in this process over memory buffers (``ssl.MemoryBIO``; the
framing is sans-IO already), so the figures are CPU time and bytes on the wire, with no
network or scheduling in them:

- ``tls13``: TLS 1.3, both sides presenting an Ed25519 X.509 certificate signed by the
  operator's Ed25519 key (a CA certificate the nodes are given), verified by OpenSSL; frames
  are TLS records (AES-GCM or ChaCha20-Poly1305, as OpenSSL picks);
- ``mso+ed25519``: mso's handshake as it is (X25519 in the hello, key confirmation with the
  overlay key) plus, in the first frame each side sends, its certificate (its name and public
  key, signed by the operator: 32 + 64 bytes and the name) and its signature over both hellos
  with its node key; each side checks the other's certificate and signature. Frames are
  mso's (blake2b tag, or ChaCha20-Poly1305 with ``--encrypt``).

The Noise protocol has no well-kept Python package (``noiseprotocol`` was last released in
2020, ``dissononce`` in 2019), so it is not measured.

Usage: .venv/bin/python bench/identity.py [--handshakes 300] [--json FILE]
"""

from __future__ import annotations

import argparse
import datetime as dt
import ssl
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from cryptography.x509.oid import NameOID

from mso.benchmarks.common import provenance, write_results
from mso.protocol.framing import FrameCodec, psk_from_text

HERE = Path(__file__).resolve().parent
PEM = serialization.Encoding.PEM


def certificate(
    name: str, public: Ed25519PublicKey, issuer: str, signer: Ed25519PrivateKey, ca: bool
) -> x509.Certificate:
    now = dt.datetime.now(dt.UTC)
    return (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, issuer)]))
        .public_key(public)
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(days=1))
        .not_valid_after(now + dt.timedelta(days=365))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
        .sign(signer, None)
    )


class Tls:
    """An operator CA and two node certificates, and a context per side."""

    def __init__(self, tmp: Path) -> None:
        op = Ed25519PrivateKey.generate()
        ca = certificate("mso operator", op.public_key(), "mso operator", op, ca=True)
        self.contexts = {}
        for side, name in (("server", "N2"), ("client", "N1")):
            key = Ed25519PrivateKey.generate()
            cert = certificate(name, key.public_key(), "mso operator", op, ca=False)
            (tmp / f"{name}.pem").write_bytes(cert.public_bytes(PEM))
            (tmp / f"{name}.key").write_bytes(
                key.private_bytes(
                    PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
                )
            )
            purpose = ssl.PROTOCOL_TLS_SERVER if side == "server" else ssl.PROTOCOL_TLS_CLIENT
            ctx = ssl.SSLContext(purpose)
            ctx.minimum_version = ssl.TLSVersion.TLSv1_3
            ctx.load_cert_chain(tmp / f"{name}.pem", tmp / f"{name}.key")
            ctx.load_verify_locations(cadata=ca.public_bytes(PEM).decode())
            ctx.verify_mode = ssl.CERT_REQUIRED
            ctx.check_hostname = False  # the name is checked against the node id instead
            self.contexts[side] = ctx

    def pair(self) -> tuple[ssl.SSLObject, ssl.SSLObject, list[ssl.MemoryBIO]]:
        bios = [ssl.MemoryBIO() for _ in range(4)]  # c->s in, c out, s in, s out
        c = self.contexts["client"].wrap_bio(bios[0], bios[1], server_side=False)
        s = self.contexts["server"].wrap_bio(bios[2], bios[3], server_side=True)
        return c, s, bios

    def handshake(self) -> tuple[ssl.SSLObject, ssl.SSLObject, list[ssl.MemoryBIO], int]:
        c, s, (c_in, c_out, s_in, s_out) = self.pair()
        wire = 0
        done = {"c": False, "s": False}
        for _ in range(20):
            for side, obj in (("c", c), ("s", s)):
                if done[side]:
                    continue
                try:
                    obj.do_handshake()
                    done[side] = True
                except ssl.SSLWantReadError:
                    pass
            out = c_out.read()
            wire += len(out)
            s_in.write(out)
            out = s_out.read()
            wire += len(out)
            c_in.write(out)
            if done["c"] and done["s"]:
                break
        assert done["c"] and done["s"]
        return c, s, [c_in, c_out, s_in, s_out], wire

    @staticmethod
    def frame(c: ssl.SSLObject, s: ssl.SSLObject, bios: list[ssl.MemoryBIO], data: bytes) -> int:
        _, c_out, s_in, _ = bios
        c.write(data)
        out = c_out.read()
        s_in.write(out)
        got = b""
        while len(got) < len(data):
            got += s.read(len(data) - len(got))
        return len(out)


class Mso:
    """mso's handshake plus an Ed25519 certificate and transcript signature each way."""

    def __init__(self, encrypt: bool) -> None:
        self.encrypt = encrypt
        self.psk = psk_from_text("overlay")
        self.op = Ed25519PrivateKey.generate()
        self.op_pub = self.op.public_key()
        self.nodes: dict[str, tuple[Ed25519PrivateKey, bytes]] = {}
        for name in ("N1", "N2"):
            key = Ed25519PrivateKey.generate()
            pub = key.public_key().public_bytes_raw()
            cert = name.encode() + pub + self.op.sign(b"mso-node" + name.encode() + pub)
            self.nodes[name] = (key, cert)

    def handshake(self) -> tuple[FrameCodec, FrameCodec, int]:
        a = FrameCodec(self.psk, encrypt=self.encrypt)
        b = FrameCodec(self.psk, encrypt=self.encrypt, responder=True)
        ha, hb = a.hello(), b.hello()
        wire = len(ha) + len(hb)
        b.feed(ha)
        _, fa = a.feed(hb)
        proofs: dict[str, bytes] = {}
        for name, hellos in (("N1", ha + hb), ("N2", hb + ha)):
            key, cert = self.nodes[name]
            proofs[name] = cert + key.sign(b"mso-link" + hellos)
        fa += a.seal(proofs["N1"])
        wire += len(fa)
        got_b, fb = b.feed(fa)
        fb += b.seal(proofs["N2"])
        wire += len(fb)
        got_a, _ = a.feed(fb)
        for proof, hellos in ((got_b[0], ha + hb), (got_a[0], hb + ha)):
            who, pub, sig = proof[:2], proof[2:34], proof[34:98]
            self.op_pub.verify(sig, b"mso-node" + who + pub)
            Ed25519PublicKey.from_public_bytes(pub).verify(proof[98:], b"mso-link" + hellos)
        return a, b, wire

    @staticmethod
    def frame(a: FrameCodec, b: FrameCodec, data: bytes) -> int:
        sealed = a.seal(data)
        assert b.feed(sealed)[0] == [data]
        return len(sealed)


def cpu_each(fn: Any, n: int) -> float:
    """Median CPU microseconds of ``fn()`` over ``n`` calls."""
    times = []
    for _ in range(n):
        t = time.process_time_ns()
        fn()
        times.append((time.process_time_ns() - t) / 1000)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--handshakes", type=int, default=300)
    ap.add_argument("--json", type=Path, default=HERE / "results" / "identity.json")
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    rows = []
    with tempfile.TemporaryDirectory(prefix="mso-identity-") as tmp:
        tls = Tls(Path(tmp))
        c, s, bios, wire = tls.handshake()
        row: dict[str, Any] = {"scheme": "tls13 (ssl, Ed25519 certificates)", "wire": wire}
        row["handshake_us"] = cpu_each(tls.handshake, args.handshakes)
        for size in (100, 16384):
            data = b"x" * size
            row[f"frame_{size}_bytes"] = tls.frame(c, s, bios, data)
            row[f"frame_{size}_us"] = cpu_each(lambda d=data: tls.frame(c, s, bios, d), 2000)
        suite = c.cipher()
        row["cipher"] = suite[0] if suite else "?"
        rows.append(row)
    for encrypt in (False, True):
        mso = Mso(encrypt)
        a, b, wire = mso.handshake()
        label = "mso+ed25519" + (" (--encrypt)" if encrypt else "")
        cipher = "ChaCha20-Poly1305" if encrypt else "blake2b tag"
        row = {"scheme": label, "wire": wire, "cipher": cipher}
        row["handshake_us"] = cpu_each(mso.handshake, args.handshakes)
        for size in (100, 16384):
            data = b"x" * size
            row[f"frame_{size}_bytes"] = mso.frame(a, b, data)
            row[f"frame_{size}_us"] = cpu_each(lambda d=data, a=a, b=b: Mso.frame(a, b, d), 2000)
        rows.append(row)
    lines = [
        "Both ends in one process over memory buffers: CPU µs (median) for a whole handshake "
        "(both sides, certificates checked) and for one frame sealed and opened; bytes on the "
        "wire.",
        "",
        "| scheme | handshake CPU µs | handshake bytes | 100 B frame: bytes, µs "
        "| 16 KiB frame: bytes, µs | frames |",
        "|---|---:|---:|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scheme']} | {r['handshake_us']:.0f} | {r['wire']} "
            f"| {r['frame_100_bytes']}, {r['frame_100_us']:.1f} "
            f"| {r['frame_16384_bytes']}, {r['frame_16384_us']:.1f} | {r['cipher']} |"
        )
    result = {"benchmark": "identity", "rows": rows, "seconds": time.monotonic() - t0}
    result |= provenance()
    write_results(args.json, result, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
