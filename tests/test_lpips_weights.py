"""``sage lpips-weights``: the LPIPS weights file merged from the lpips package's heads and
torchvision's AlexNet, through the Python API and the command; clear errors on bad inputs. The
reference file is split into the two published layouts; pip is replaced by a local stand-in."""

from __future__ import annotations

import sys
import zipfile
from collections import OrderedDict
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from helpers import LPIPS_WEIGHTS
from sage_core.errors import InputError
from sage_core.evaluate import lpips_weights as lw
from sage_core.evaluate.lpips import ENV_VAR, EXPECTED_SHAPES, LPIPS_ALEX_SHA256
from sage_core.workspace import file_sha256

REPO = Path(__file__).resolve().parents[1]


def _reference() -> Path | None:
    """The reference weights where sage finds them, else beside the checkout (../shared/weights)."""
    for p in (LPIPS_WEIGHTS, REPO.parent / "shared" / "weights" / "lpips_alex_v0.1.pth"):
        if p is not None and Path(p).is_file():
            return Path(p)
    return None


REFERENCE = _reference()
needs_reference = pytest.mark.skipif(
    REFERENCE is None, reason="LPIPS reference weights not found: set SAGE_LPIPS_WEIGHTS or place lpips_alex_v0.1.pth in ../shared/weights/")


def _random_state() -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return {k: torch.randn(shape, generator=g) for k, shape in EXPECTED_SHAPES.items()}


def _split(sd: dict[str, torch.Tensor], folder: Path, patch: pytest.MonkeyPatch | None = None) -> SimpleNamespace:
    """Write ``sd`` as the two published layouts in ``folder``: torchvision's AlexNet checkpoint
    (``features.*`` plus ``classifier.*``) and the lpips heads file (``lin{i}.model.1.weight``).
    With ``patch``, the expected SHA-256 of both sources become those of these files."""
    folder.mkdir(parents=True, exist_ok=True)
    trunk = OrderedDict((k, v.clone()) for k, v in sd.items() if k.startswith("features."))
    for i, (o, n) in zip((1, 4, 6), ((32, 64), (32, 32), (10, 32))):  # small stand-ins of the classifier
        trunk[f"classifier.{i}.weight"], trunk[f"classifier.{i}.bias"] = torch.ones(o, n), torch.zeros(o)
    heads = OrderedDict((f"lin{i}.model.1.weight", sd[f"lin.{i}.weight"].clone()) for i in range(5))
    src = SimpleNamespace(alexnet=folder / lw.ALEXNET_FILE, heads=folder / "alex.pth")
    torch.save(trunk, src.alexnet)
    torch.save(heads, src.heads)
    if patch is not None:
        patch.setattr(lw, "ALEXNET_SHA256", file_sha256(src.alexnet))
        patch.setattr(lw, "HEADS_SHA256", file_sha256(src.heads))
    return src


def _wheel(path: Path, heads: Path) -> Path:
    """A wheel-like zip holding the heads at their path in the lpips wheel."""
    with zipfile.ZipFile(path, "w") as zf:
        zf.write(heads, lw.HEADS_WHEEL_PATH)
        zf.writestr("lpips-0.1.4.dist-info/LICENSE", "BSD 2-Clause (test copy)")
    return path


def _assert_equal(path: Path, expected: dict[str, torch.Tensor]) -> None:
    got = torch.load(path, map_location="cpu", weights_only=True)
    assert list(got) == list(EXPECTED_SHAPES)
    for k, v in expected.items():
        assert got[k].dtype == torch.float32 and torch.equal(got[k], v), k


def invoke(args: list[object], **env: str):
    """``sage <args>`` in-process (the full app) with wide output; ``env`` adds variables."""
    from typer.testing import CliRunner

    from sage_cli.app import app

    return CliRunner().invoke(app, [str(a) for a in args], env={ENV_VAR: "", "COLUMNS": "250", **env})


@pytest.fixture(scope="module")
def reference() -> dict[str, torch.Tensor]:
    if REFERENCE is None:
        pytest.skip("LPIPS reference weights not found")
    return torch.load(REFERENCE, map_location="cpu", weights_only=True)


@needs_reference
def test_api_merges_the_two_sources_into_the_reference(reference, tmp_path, monkeypatch):
    src = _split(reference, tmp_path / "src", monkeypatch)
    monkeypatch.delenv(ENV_VAR, raising=False)
    out = tmp_path / "out" / "merged.pth"
    r = lw.build_lpips_weights(src.heads, src.alexnet, out)
    _assert_equal(out, reference)
    assert r.path == out and r.sha256 == file_sha256(out) and "--lpips-weights" in r.eval_finds
    if file_sha256(REFERENCE) == LPIPS_ALEX_SHA256:  # same values: the same bytes, whatever the file's name
        assert r.reference and r.sha256 == LPIPS_ALEX_SHA256
    assert [p.name for p in out.parent.iterdir()] == ["merged.pth"]  # no temp file left
    with pytest.raises(InputError, match="already exists; pass --force"):
        lw.build_lpips_weights(src.heads, src.alexnet, out)
    assert lw.build_lpips_weights(src.heads, src.alexnet, out, force=True).sha256 == r.sha256


@needs_reference
def test_command_with_wheel_and_default_paths(reference, tmp_path, monkeypatch):
    """--heads WHEEL; the AlexNet from torch hub's folder; the file into sage's cache folder."""
    src = _split(reference, tmp_path / "src", monkeypatch)
    torch_home, home = tmp_path / "torch", tmp_path / "home"
    (torch_home / "hub" / "checkpoints").mkdir(parents=True)
    src.alexnet.rename(torch_home / "hub" / "checkpoints" / lw.ALEXNET_FILE)
    wheel = _wheel(tmp_path / "lpips-0.1.4-py3-none-any.whl", src.heads)
    env = {"HOME": str(home), "TORCH_HOME": str(torch_home)}
    res = invoke(["lpips-weights", "--heads", wheel], **env)
    assert res.exit_code == 0, res.output
    cached = home / ".cache" / "sage" / "lpips_alex_v0.1.pth"
    _assert_equal(cached, reference)
    assert "sage lpips-weights" in res.output and file_sha256(cached) in res.output
    assert "finds it in its cache folder" in res.output and "SHA-256 checked" in res.output
    res = invoke(["lpips-weights", "--heads", wheel], **env)
    assert res.exit_code == 2 and "already exists" in res.output and "--force" in res.output
    res = invoke(["lpips-weights", "--heads", wheel, "--force"], **env)
    assert res.exit_code == 0, res.output


@needs_reference
def test_heads_fetched_with_pip_without_network(reference, tmp_path, monkeypatch):
    """Without --heads the wheel comes from `pip download` (here a stand-in copying a local wheel)."""
    src = _split(reference, tmp_path / "src", monkeypatch)
    wheel = _wheel(tmp_path / "lpips-0.1.4-py3-none-any.whl", src.heads)
    fake = tmp_path / "fake_pip.py"
    fake.write_text(
        "import shutil, sys\n"
        "args = sys.argv[1:]\n"
        "assert args[:2] == ['download', 'lpips==0.1.4'] and '--no-deps' in args, args\n"
        f"shutil.copy({str(wheel)!r}, args[args.index('--dest') + 1])\n"
    )
    r = lw.build_lpips_weights(None, src.alexnet, tmp_path / "w.pth", pip=[sys.executable, str(fake)])
    _assert_equal(r.path, reference)
    assert "pip download" in r.heads
    failing = tmp_path / "failing_pip.py"
    failing.write_text("import sys\nprint('ERROR: No matching distribution found', file=sys.stderr)\nsys.exit(1)\n")
    with pytest.raises(InputError, match="No matching distribution.*--heads"):
        lw.build_lpips_weights(None, src.alexnet, tmp_path / "w2.pth", pip=[sys.executable, str(failing)])
    assert not (tmp_path / "w2.pth").exists()


class _Opens:
    """Unpickling this would create a file: a checkpoint that is not plain tensors."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return (open, (str(self.path), "w"))


def test_bad_inputs_exit_2_naming_the_file(tmp_path, monkeypatch):
    src = _split(_random_state(), tmp_path / "src", monkeypatch)
    out = tmp_path / "out.pth"

    def run(heads: Path, alexnet: Path):
        res = invoke(["lpips-weights", "--heads", heads, "--alexnet", alexnet, "--out", out])
        assert res.exit_code == 2 and not out.exists(), res.output
        return res.output

    sd = torch.load(src.heads, weights_only=True)
    sd["lin2.model.1.weight"] = torch.zeros(1, 383, 1, 1)
    torch.save(sd, tmp_path / "shape.pth")
    msg = run(tmp_path / "shape.pth", src.alexnet)
    assert "shape.pth" in msg and "'lin2.model.1.weight' has shape (1, 383, 1, 1), expected (1, 384, 1, 1)" in msg

    sd = torch.load(src.alexnet, weights_only=True)
    del sd["features.8.bias"]
    torch.save(sd, tmp_path / "short.pth")
    msg = run(src.heads, tmp_path / "short.pth")
    assert "short.pth" in msg and "missing keys ['features.8.bias']" in msg

    (tmp_path / "notes.pth").write_text("not a checkpoint\n")
    msg = run(tmp_path / "notes.pth", src.alexnet)
    assert "notes.pth" in msg and "cannot be read as a PyTorch checkpoint" in msg

    marker = tmp_path / "created-by-unpickling"
    torch.save({"lin0.model.1.weight": _Opens(marker)}, tmp_path / "code.pth")
    msg = run(src.heads, tmp_path / "code.pth")
    assert "code.pth" in msg and "cannot be read" in msg and not marker.exists()

    msg = run(src.alexnet, src.heads)  # the two swapped
    assert "missing keys" in msg and "alex.pth" in msg

    junk = tmp_path / "junk.whl"
    junk.write_bytes(b"not a zip")
    assert "not a wheel" in run(junk, src.alexnet)
    with zipfile.ZipFile(tmp_path / "empty.whl", "w") as zf:
        zf.writestr("lpips/__init__.py", "")
    assert "holds no lpips/weights/v0.1/alex.pth" in run(tmp_path / "empty.whl", src.alexnet)


def test_other_heads_or_alexnet_are_refused_by_hash(tmp_path):
    """Right keys and shapes but not the published files (e.g. the v0.0 heads): refused by SHA-256."""
    src = _split(_random_state(), tmp_path / "src")
    with pytest.raises(InputError, match=r"alex\.pth: LPIPS heads file has SHA-256 .*v0\.0"):
        lw.read_heads(src.heads)
    with pytest.raises(InputError, match=r"alexnet-owt-7be5be79\.pth: AlexNet checkpoint has SHA-256 .*download\.pytorch\.org"):
        lw.read_alexnet(src.alexnet)
    assert not (tmp_path / "out.pth").exists()


def test_missing_alexnet_says_where_to_get_it(tmp_path):
    heads = tmp_path / "alex.pth"
    heads.write_bytes(b"unused")
    res = invoke(["lpips-weights", "--heads", heads, "--out", tmp_path / "out.pth"], TORCH_HOME=str(tmp_path / "torch"))
    assert res.exit_code == 2, res.output
    assert str(tmp_path / "torch" / "hub" / "checkpoints" / lw.ALEXNET_FILE) in res.output
    assert lw.ALEXNET_URL in res.output and "--alexnet" in res.output
    res = invoke(["lpips-weights", "--heads", heads, "--alexnet", tmp_path / "nope.pth"])
    assert res.exit_code == 2 and "nope.pth" in res.output and "not found" in res.output
