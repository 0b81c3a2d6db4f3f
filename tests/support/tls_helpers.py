"""Certificates for TLS tests, made with ``openssl`` (never committed): a CA, a server
certificate for localhost/127.0.0.1 and a client certificate signed by it, and a second CA
that signed neither (the "unknown CA" case)."""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Pki:
    ca: Path
    server_cert: Path
    server_key: Path
    client_cert: Path
    client_key: Path
    other_ca: Path


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["timeout", "-s", "KILL", "30", "openssl", *args], cwd=cwd, check=True, capture_output=True)


def _ca(directory: Path, name: str) -> tuple[Path, Path]:
    key, cert = directory / f"{name}.key", directory / f"{name}.pem"
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-days", "2",
             "-subj", f"/CN={name}", "-keyout", str(key), "-out", str(cert),
             "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=directory)
    return cert, key


def _signed(directory: Path, name: str, ca: tuple[Path, Path], extensions: str, common_name: str) -> tuple[Path, Path]:
    key, csr, cert = directory / f"{name}.key", directory / f"{name}.csr", directory / f"{name}.pem"
    ext = directory / f"{name}.ext"
    ext.write_text(extensions)
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-subj", f"/CN={common_name}",
             "-keyout", str(key), "-out", str(csr), cwd=directory)
    _openssl("x509", "-req", "-in", str(csr), "-CA", str(ca[0]), "-CAkey", str(ca[1]), "-CAcreateserial",
             "-days", "2", "-extfile", str(ext), "-out", str(cert), cwd=directory)
    key.chmod(0o644)  # the broker runs as another user in some setups; these are throwaway test keys
    return cert, key


def make_pki(directory: Path, server_names: tuple[str, ...] = ("localhost",), client_name: str = "farmer") -> Pki:
    directory.mkdir(parents=True, exist_ok=True)
    ca = _ca(directory, "ca")
    other = _ca(directory, "other-ca")
    names = ",".join([*(f"DNS:{n}" for n in server_names), "IP:127.0.0.1"])
    server = _signed(directory, "server", ca, f"subjectAltName={names}\nextendedKeyUsage=serverAuth\n", server_names[0])
    client = _signed(directory, "client", ca, "extendedKeyUsage=clientAuth\n", client_name)
    return Pki(ca[0], server[0], server[1], client[0], client[1], other[0])


def renew_client(pki: Pki, cert: Path, key: Path, client_name: str) -> None:
    """A new key and certificate for the same client from the same CA, written over ``cert``
    and ``key`` in place (as certbot or cert-manager renew)."""
    directory = cert.parent / "renewal"
    directory.mkdir(exist_ok=True)
    new_cert, new_key = _signed(directory, "client", (pki.ca, pki.ca.with_suffix(".key")), "extendedKeyUsage=clientAuth\n", client_name)
    key.write_bytes(new_key.read_bytes())
    cert.write_bytes(new_cert.read_bytes())
