"""Authenticity of an exported model: an ed25519 signature over ``manifest.json``.

The manifest already records the size and sha256 of every graph (``runtime/model/artifact``), so one
signature over its exact bytes covers the whole artifact: a graph edited together with a
re-hashed manifest no longer verifies. ``msdnet-export --sign KEY`` writes ``manifest.sig``;
``msdnet-infer --trusted-key PUB`` refuses, in one line, an artifact that has no signature or
whose signature does not verify with that key.

Keys are PEM files (PKCS#8 private, SubjectPublicKeyInfo public), e.g. from OpenSSL::

    openssl genpkey -algorithm ed25519 -out msdnet-key.pem
    openssl pkey -in msdnet-key.pem -pubout -out msdnet-key.pub

or ``generate_keypair``. ``manifest.sig`` is JSON: ``algorithm`` ("ed25519"), ``key_sha256``
(sha256 of the raw 32-byte public key, to tell keys apart) and ``signature`` (base64, 64 bytes).
Needs the ``cryptography`` package (extra ``sign``), imported only when a key is given.
"""

from __future__ import annotations

import base64
import hashlib
import json
from pathlib import Path
from typing import Any

from msdnet.runtime.errors import MsdnetError

SIGNATURE_FILE = "manifest.sig"
ALGORITHM = "ed25519"


def _crypto() -> Any:
    try:
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric import ed25519  # noqa: F401
    except ImportError:
        raise MsdnetError("signing", "needs the 'cryptography' package: pip install 'msdnet[sign]'") from None
    return serialization


def _read_key_bytes(path: Path, what: str) -> bytes:
    try:
        data = Path(path).read_bytes()
    except OSError as err:
        raise MsdnetError(path, f"cannot read the {what} ({err.strerror or err})") from None
    if len(data) > 64 * 1024:
        raise MsdnetError(path, f"{what} file is too large to be a PEM key")
    return data


def load_private_key(path: str | Path) -> Any:
    """An ed25519 private key from a PEM file (unencrypted); MsdnetError otherwise."""
    serialization = _crypto()
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    data = _read_key_bytes(Path(path), "signing key")
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as err:
        raise MsdnetError(path, f"not an unencrypted PEM private key ({_first_line(err)})") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise MsdnetError(path, f"signing key is {type(key).__name__}, not ed25519")
    return key


def load_public_key(path: str | Path) -> Any:
    """An ed25519 public key from a PEM file; MsdnetError otherwise."""
    serialization = _crypto()
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    data = _read_key_bytes(Path(path), "trusted key")
    try:
        key = serialization.load_pem_public_key(data)
    except (ValueError, TypeError) as err:
        raise MsdnetError(path, f"not a PEM public key ({_first_line(err)})") from None
    if not isinstance(key, Ed25519PublicKey):
        raise MsdnetError(path, f"trusted key is {type(key).__name__}, not ed25519")
    return key


def key_id(public_key: Any) -> str:
    """sha256 hex of the raw 32-byte public key."""
    from cryptography.hazmat.primitives import serialization

    raw = public_key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return hashlib.sha256(raw).hexdigest()


def sign_bytes(manifest: bytes, private_key: Any) -> dict[str, str]:
    """The ``manifest.sig`` body for the exact ``manifest`` bytes."""
    signature = private_key.sign(manifest)
    return {
        "algorithm": ALGORITHM,
        "key_sha256": key_id(private_key.public_key()),
        "signature": base64.b64encode(signature).decode("ascii"),
    }


def sign_folder(folder: str | Path, private_key: Any, manifest_name: str = "manifest.json") -> Path:
    """Sign ``folder/manifest.json`` with a loaded private key (``load_private_key``); -> the
    ``manifest.sig`` written."""
    folder = Path(folder)
    body = sign_bytes((folder / manifest_name).read_bytes(), private_key)
    path = folder / SIGNATURE_FILE
    path.write_text(json.dumps(body, indent=1) + "\n", encoding="ascii")
    return path


def verify_bytes(manifest: bytes, folder: Path, public_key_file: str | Path) -> None:
    """Check ``folder/manifest.sig`` against the exact ``manifest`` bytes and the trusted key;
    MsdnetError (one line) when the signature is missing, malformed, or does not verify."""
    from cryptography.exceptions import InvalidSignature

    public_key = load_public_key(public_key_file)
    sig_path = Path(folder) / SIGNATURE_FILE
    if not sig_path.is_file() or sig_path.is_symlink():
        raise MsdnetError(sig_path, "model is not signed (no manifest.sig) but --trusted-key was given")
    try:
        body = json.loads(sig_path.read_text(encoding="ascii"))
        algorithm, signature = body["algorithm"], base64.b64decode(body["signature"], validate=True)
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as err:
        raise MsdnetError(sig_path, f"malformed signature file ({_first_line(err)})") from None
    if algorithm != ALGORITHM:
        raise MsdnetError(sig_path, f"signature algorithm {algorithm!r} is not {ALGORITHM}")
    try:
        public_key.verify(signature, manifest)
    except InvalidSignature:
        signer = body.get("key_sha256", "?") if isinstance(body, dict) else "?"
        same = signer == key_id(public_key)
        why = "manifest.json changed after signing" if same else f"signed by another key ({signer[:16]}...)"
        raise MsdnetError(sig_path, f"signature does not verify with {public_key_file}: {why}") from None


def generate_keypair(private_path: str | Path, public_path: str | Path) -> None:
    """Write a new ed25519 key pair as PEM files (private key mode 600)."""
    serialization = _crypto()
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    key = Ed25519PrivateKey.generate()
    private = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    public = key.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    Path(private_path).touch(mode=0o600)
    Path(private_path).write_bytes(private)
    Path(public_path).write_bytes(public)


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0][:160] if text else type(err).__name__
