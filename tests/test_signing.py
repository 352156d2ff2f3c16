"""``msdnet-export --sign`` / ``msdnet-infer --trusted-key`` (ed25519 over manifest.json), and the
export's early checks: a corrupt model.safetensors whose hash was updated or removed, an unknown
preset name, the permissions of what it writes (issue 16)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from export_helpers import make_checkpoint, one_torch_thread

from msdnet.export.cli import main as export_main
from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.frontends.infer.cli import main as infer_main
from msdnet.runtime.io.atomic import _umask
from msdnet.runtime.io.files import write_cloud
from msdnet.runtime.model.signing import SIGNATURE_FILE, generate_keypair

pytest.importorskip("cryptography")  # extra "sign"; .ci/run installs it, so CI runs these


@pytest.fixture(scope="module")
def signed(tmp_path_factory) -> dict[str, Path]:
    """A tiny student checkpoint, two key pairs, and the checkpoint exported and signed."""
    root = tmp_path_factory.mktemp("sign")
    ckpt = make_checkpoint(root / "ckpt", "student")
    generate_keypair(root / "key.pem", root / "key.pub")
    generate_keypair(root / "other.pem", root / "other.pub")
    with one_torch_thread():
        r = CliRunner().invoke(
            export_main,
            [str(ckpt), "--out", str(root / "art"), "--sign", str(root / "key.pem"), "--threads", "1"],
        )
    assert r.exit_code == 0, r.output
    scan = root / "scan.ply"
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.random((100, 3)) * [12.8, 12.8, 6.0] - [0, 6.4, 2.0], rng.random((100, 2))], 1)
    write_cloud(scan, PointCloud(pts.astype(np.float32), ("x", "y", "z", "rcs", "v_r_compensated")))
    return {"root": root, "ckpt": ckpt, "art": root / "art", "scan": scan}


def _infer(signed: dict[str, Path], art: Path, key: str | None, out: Path) -> object:
    args = [str(signed["scan"]), "--model", str(art), "--out", str(out), "--steps", "2", "--threads", "1"]
    if key:
        args += ["--trusted-key", str(signed["root"] / key)]
    return CliRunner().invoke(infer_main, args)


def test_signed_export_runs_with_its_key_and_has_normal_permissions(signed, tmp_path):
    art = signed["art"]
    body = json.loads((art / SIGNATURE_FILE).read_text())
    assert body["algorithm"] == "ed25519" and len(body["signature"]) == 88  # base64 of 64 bytes
    mask = _umask()
    assert art.stat().st_mode & 0o777 == 0o777 & ~mask  # not mkdtemp's 0700
    for f in art.iterdir():
        assert f.stat().st_mode & 0o777 == 0o666 & ~mask, f.name
    assert not [p for p in art.parent.iterdir() if p.name.endswith(".tmp")]
    r = _infer(signed, art, "key.pub", tmp_path / "o")
    assert r.exit_code == 0, r.output


def test_trusted_key_refuses_unsigned_foreign_and_edited(signed, tmp_path):
    art = signed["art"]
    unsigned = shutil.copytree(art, tmp_path / "unsigned")
    (unsigned / SIGNATURE_FILE).unlink()
    r = _infer(signed, unsigned, "key.pub", tmp_path / "o")
    assert r.exit_code == 2 and len(r.output.splitlines()) == 1
    assert r.output.startswith(f"error: {unsigned / SIGNATURE_FILE}: model is not signed")
    r = _infer(signed, art, "other.pub", tmp_path / "o")
    assert (
        r.exit_code == 2 and "signature does not verify" in r.output and "signed by another key" in r.output
    )
    # the attack integrity alone cannot see: a graph edited and its manifest entry re-hashed
    edited = shutil.copytree(art, tmp_path / "edited")
    graph = edited / "recon_head.onnx"
    graph.write_bytes(graph.read_bytes() + b"\0")
    manifest = json.loads((edited / "manifest.json").read_text())
    for g in manifest["graphs"]:
        if g["file"] == graph.name:
            g["bytes"], g["sha256"] = graph.stat().st_size, hashlib.sha256(graph.read_bytes()).hexdigest()
    (edited / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    r = _infer(signed, edited, "key.pub", tmp_path / "o")
    assert r.exit_code == 2 and len(r.output.splitlines()) == 1
    assert "signature does not verify" in r.output and "manifest.json changed after signing" in r.output
    assert not (tmp_path / "o").exists()


def test_bad_keys_are_one_line(signed, tmp_path):
    junk = tmp_path / "junk.pem"
    junk.write_text("not a key\n")
    r = _infer(signed, signed["art"], None, tmp_path / "o")
    assert r.exit_code == 0  # no key given: integrity checks only, as before
    r = CliRunner().invoke(
        infer_main,
        [
            str(signed["scan"]),
            "--model",
            str(signed["art"]),
            "--out",
            str(tmp_path / "o"),
            "--trusted-key",
            str(junk),
        ],
    )
    assert r.exit_code == 2 and r.output.startswith(f"error: {junk}: not a PEM public key")
    pub = signed["root"] / "key.pub"
    r = CliRunner().invoke(
        export_main, [str(signed["ckpt"]), "--out", str(tmp_path / "a"), "--sign", str(pub)]
    )
    assert r.exit_code == 2 and r.output.startswith(f"error: {pub}: not an unencrypted PEM private key")
    assert not (tmp_path / "a").exists()


@pytest.mark.parametrize("hash_entry", ["updated", "removed"])
def test_corrupt_weights_with_matching_or_no_hash_is_one_line(signed, tmp_path, hash_entry):
    ckpt = shutil.copytree(signed["ckpt"], tmp_path / "ckpt")
    weights = ckpt / "model.safetensors"
    data = weights.read_bytes()
    weights.write_bytes(data[: len(data) // 2])
    meta = json.loads((ckpt / "checkpoint.json").read_text())
    if hash_entry == "updated":
        meta["files"]["model.safetensors"] = hashlib.sha256(weights.read_bytes()).hexdigest()
    else:
        del meta["files"]["model.safetensors"]
    (ckpt / "checkpoint.json").write_text(json.dumps(meta))
    r = CliRunner().invoke(export_main, [str(ckpt), "--out", str(tmp_path / "a")])
    assert r.exit_code == 2 and len(r.output.splitlines()) == 1, r.output
    assert r.output.startswith(f"error: {weights}: cannot load weights: ")


def test_unknown_preset_name_refused(signed, tmp_path):
    ckpt = shutil.copytree(signed["ckpt"], tmp_path / "ckpt")
    meta = json.loads((ckpt / "checkpoint.json").read_text())
    meta["model_config"]["preset"] = "tiny-but-renamed"
    (ckpt / "checkpoint.json").write_text(json.dumps(meta))
    r = CliRunner().invoke(export_main, [str(ckpt), "--out", str(tmp_path / "a")])
    assert r.exit_code == 2 and "unknown preset 'tiny-but-renamed' in model_config (known: tiny" in r.output
    assert os.listdir(tmp_path) == ["ckpt"]
