"""No file runs code: a corpus of pickle payloads that escape restricted unpicklers, through every
route by which sage reads a FLAME model or mask file (docs/workspace.md "Files that cannot run code").

Each payload creates a marker file when it runs. The control (:func:`test_every_payload_runs_under_a_plain_unpickler`)
shows that each one does run under Python's own ``pickle.loads``, in a child process; every other
test feeds the same bytes to sage and asserts that the marker never appears, that the exit code is
non-zero and that the message names the file.
"""

from __future__ import annotations

import json
import pickle
import shutil
import struct
import subprocess
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from typer.testing import CliRunner

from sage_cli.app import app

ENV = {"COLUMNS": "400", "SAGE_LPIPS_WEIGHTS": "", "OMP_NUM_THREADS": "1"}


# --------------------------------------------------------------------------------------------
# payloads
# --------------------------------------------------------------------------------------------


def _code(marker: Path) -> str:
    return f"__import__('pathlib').Path({str(marker)!r}).touch()"


def _u(s: str) -> bytes:
    """SHORT_BINUNICODE or BINUNICODE."""
    b = s.encode("utf-8")
    return (b"\x8c" + bytes([len(b)]) + b) if len(b) < 256 else (b"X" + struct.pack("<I", len(b)) + b)


PROTO4 = b"\x80\x04"
STACK_GLOBAL, TUPLE1, TUPLE2, TUPLE3, REDUCE, STOP, MARK = b"\x93", b"\x85", b"\x86", b"\x87", b"R", b".", b"("
EMPTY_DICT, SETITEM, BUILD, NEWOBJ, EMPTY_TUPLE = b"}", b"s", b"b", b"\x81", b")"


def _g(module: str, name: str) -> bytes:
    return _u(module) + _u(name) + STACK_GLOBAL


def _call1(func: bytes, arg: bytes) -> bytes:
    return func + arg + TUPLE1 + REDUCE


def _in_dict(value: bytes) -> bytes:
    """A FLAME-looking top-level dict {"v_template": value}."""
    return PROTO4 + EMPTY_DICT + _u("v_template") + value + SETITEM + STOP


def _dotted_builtins(module: str) -> Callable[[Path], bytes]:
    """``module.__builtins__.get('eval')(code)``: a dotted name through a module sage uses."""
    def make(marker: Path) -> bytes:
        get = _g(module, "__builtins__.get")
        return _in_dict(_call1(_call1(get, _u("eval")), _u(_code(marker))))
    return make


def _builtins_getattr(marker: Path) -> bytes:
    builtins_mod = _call1(_g("builtins", "__import__"), _u("builtins"))
    ev = _g("builtins", "getattr") + builtins_mod + _u("eval") + TUPLE2 + REDUCE
    return _in_dict(_call1(ev, _u(_code(marker))))


def _operator_attrgetter(marker: Path) -> bytes:
    getter = _call1(_g("operator", "attrgetter"), _u("eval"))
    builtins_mod = _call1(_g("builtins", "__import__"), _u("builtins"))
    ev = _call1(getter, builtins_mod)
    return _in_dict(_call1(ev, _u(_code(marker))))


def _copyreg_reconstructor(marker: Path) -> bytes:
    """copyreg._reconstructor(Popen, Popen, argv): base.__init__(obj, argv) starts a process."""
    popen = _g("subprocess", "Popen")
    argv = b"]" + MARK + _u("touch") + _u(str(marker)) + b"e"  # EMPTY_LIST, MARK, items, APPENDS
    call = _g("copyreg", "_reconstructor") + popen + popen + argv + TUPLE3 + REDUCE
    return PROTO4 + EMPTY_DICT + _u("v_template") + call + SETITEM + _u("wait") + EMPTY_TUPLE + SETITEM + STOP


def _nested_reduce(marker: Path) -> bytes:
    """An allowed reconstructor whose arguments hold a forbidden call."""
    inner = _call1(_g("builtins", "eval"), _u(_code(marker)))
    outer = _g("numpy._core.multiarray", "_reconstruct") + _g("numpy", "ndarray") + inner + _u("b") + TUPLE3 + REDUCE
    return _in_dict(outer)


def _object_array(marker: Path) -> bytes:
    """An object-dtype array whose element is a forbidden call (numpy's own array pickling)."""
    class Runs:
        def __reduce__(self):
            return (eval, (_code(marker),))
    arr = np.empty(1, dtype=object)
    arr[0] = Runs()
    return pickle.dumps({"v_template": arr}, protocol=2)


def _build_state(marker: Path) -> bytes:
    """BUILD on an allowed class's instance with a state whose value is a forbidden call."""
    inner = _call1(_g("builtins", "eval"), _u(_code(marker)))
    obj = _g("collections", "OrderedDict") + EMPTY_TUPLE + REDUCE
    state = EMPTY_DICT + _u("x") + inner + SETITEM
    return _in_dict(obj + state + BUILD)


def _reduce_protocol(protocol: int) -> Callable[[Path], bytes]:
    """Plain ``__reduce__`` to ``eval``, pickled by Python at ``protocol``."""
    def make(marker: Path) -> bytes:
        class Runs:
            def __reduce__(self):
                return (eval, (_code(marker),))
        return pickle.dumps({"v_template": Runs()}, protocol=protocol)
    return make


def _dotted_protocol5(marker: Path) -> bytes:
    return b"\x80\x05" + _dotted_builtins("numpy.dtypes")(marker)[2:]


def _inst_opcode(marker: Path) -> bytes:
    """Protocol 0 INST: ``(S'code'\\nibuiltins\\neval\\n``."""
    return b"(dS'v_template'\n(S" + repr(_code(marker)).encode() + b"\nibuiltins\neval\nsb."


def _obj_opcode(marker: Path) -> bytes:
    """Protocol 1 OBJ: MARK, class, args, OBJ."""
    return b"}" + _u("v_template") + MARK + _g("builtins", "eval") + _u(_code(marker)) + b"o" + SETITEM + STOP


EXT_CODE = 0x7A51


def _ext_opcode(marker: Path) -> bytes:
    """EXT2 through the copyreg extension registry (the control registers builtins.eval first)."""
    return _in_dict(_call1(b"\x83" + struct.pack("<H", EXT_CODE), _u(_code(marker))))


PAYLOADS: dict[str, Callable[[Path], bytes]] = {
    "numpy.dtypes dotted": _dotted_builtins("numpy.dtypes"),
    "numpy dotted": _dotted_builtins("numpy"),
    "numpy._core.multiarray dotted": _dotted_builtins("numpy._core.multiarray"),
    "scipy.sparse._csc dotted": _dotted_builtins("scipy.sparse._csc"),
    "copyreg dotted": _dotted_builtins("copyreg"),
    "collections dotted": _dotted_builtins("collections"),
    "dotted protocol 5": _dotted_protocol5,
    "builtins.getattr": _builtins_getattr,
    "operator.attrgetter": _operator_attrgetter,
    "copyreg._reconstructor Popen": _copyreg_reconstructor,
    "nested reduce": _nested_reduce,
    "object array": _object_array,
    "BUILD state": _build_state,
    **{f"reduce protocol {p}": _reduce_protocol(p) for p in range(6)},
    "INST opcode": _inst_opcode,
    "OBJ opcode": _obj_opcode,
    "EXT2 opcode": _ext_opcode,
}


def _write(path: Path, name: str, marker: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(PAYLOADS[name](marker))
    return path


# --------------------------------------------------------------------------------------------
# control: each payload is live
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(PAYLOADS))
def test_every_payload_runs_under_a_plain_unpickler(name, tmp_path):
    marker = tmp_path / "RAN"
    path = _write(tmp_path / "evil.pkl", name, marker)
    code = (
        "import copyreg, pickle, sys, numpy, numpy.dtypes, numpy._core.multiarray, scipy.sparse._csc\n"
        f"copyreg.add_extension('builtins', 'eval', {EXT_CODE})\n"
        "try:\n    pickle.loads(open(sys.argv[1], 'rb').read(), encoding='latin1')\nexcept Exception:\n    pass\n"
    )
    subprocess.run([sys.executable, "-c", code, str(path)], check=True, timeout=60)
    for _ in range(50):  # a started process (Popen) may touch the marker a moment later
        if marker.exists():
            break
        subprocess.run(["sleep", "0.1"], check=True)
    assert marker.exists(), f"payload {name!r} did not run under pickle.loads: the corpus would test nothing"


# --------------------------------------------------------------------------------------------
# the loaders
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(PAYLOADS))
def test_no_payload_runs_through_any_loader(name, tmp_path):
    from sage_core.errors import InputError
    from sage_core.flame import load_flame_model
    from sage_core.flame.regions import load_masks

    marker = tmp_path / "RAN"
    model = _write(tmp_path / "evil.pkl", name, marker)
    masks = _write(tmp_path / "FLAME_masks.pkl", name, marker)
    npz = _write(tmp_path / "ws" / "init" / "flame_model.npz", name, marker)
    for load, path in ((load_flame_model, model), (load_masks, masks), (load_flame_model, npz)):
        with pytest.raises(InputError) as ei:
            load(path)
        assert str(path) in str(ei.value)
    with pytest.raises(InputError, match="not a zip archive"):
        load_flame_model(npz)
    with pytest.raises(InputError, match="not a zip archive"):
        load_flame_model(model, npz_only=True)
    assert not marker.exists()


def test_refusals_name_the_global_or_opcode(tmp_path):
    from sage_core.errors import InputError
    from sage_core.flame import load_flame_model

    marker = tmp_path / "RAN"
    for name, expected in (("numpy.dtypes dotted", "refusing to load global numpy.dtypes.__builtins__.get"),
                           ("INST opcode", "opcode INST is not accepted"), ("EXT2 opcode", "opcode EXT2"),
                           ("object array", "dtype 'O8' is not accepted"),
                           ("copyreg._reconstructor Popen", "refusing to load global subprocess.Popen")):
        with pytest.raises(InputError, match=expected.replace(".", r"\.")):
            load_flame_model(_write(tmp_path / f"{len(name)}.pkl", name, marker))
    assert not marker.exists()


def test_allow_list_is_exact_pairs_without_dots():
    from sage_core.flame._unpickle import ALLOWED, RefusedPickle, resolve_global

    assert all("." not in name for _module, name in ALLOWED)
    for module, name in (("numpy.dtypes", "Float64DType"), ("numpy", "load"), ("numpy", "dtype.__init__"),
                         ("builtins", "eval"), ("builtins", "getattr"), ("copyreg", "__newobj__"),
                         ("scipy.sparse", "csc_matrix.__init__"), ("chumpy.ch", "Ch.__init__")):
        with pytest.raises(RefusedPickle):
            resolve_global(module, name)


def test_deep_nesting_is_refused_not_a_recursion_error(tmp_path):
    from sage_core.errors import InputError
    from sage_core.flame import load_flame_model

    deep: object = [1]
    for _ in range(5000):
        deep = [deep]
    path = tmp_path / "deep.pkl"
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 20000))
    path.write_bytes(pickle.dumps({"v_template": deep}, protocol=4))
    with pytest.raises(InputError, match="nested deeper"):
        load_flame_model(path)


# --------------------------------------------------------------------------------------------
# the commands
# --------------------------------------------------------------------------------------------


def _invoke(*args: object):
    return CliRunner().invoke(app, [str(a) for a in args], env=ENV)


def _text(res) -> str:
    return " ".join(res.output.split())


@pytest.mark.parametrize("name", sorted(PAYLOADS))
def test_ingest_with_a_hostile_model_runs_nothing_and_writes_nothing(name, tmp_path, tiny_capture):
    marker = tmp_path / "RAN"
    model = _write(tmp_path / "evil.pkl", name, marker)
    res = _invoke("ingest", tiny_capture, tmp_path / "ws", "--flame-model", model, "--preset", "tiny", "--quiet")
    assert res.exit_code == 2, _text(res)
    assert str(model) in _text(res)
    assert not marker.exists() and not (tmp_path / "ws" / "data").exists()


def test_hostile_masks_beside_a_genuine_model_are_refused(tmp_path, tiny_capture):
    marker = tmp_path / "RAN"
    folder = tmp_path / "model"
    shutil.copytree(Path(tiny_capture.model_path).parent, folder)
    masks = _write(folder / "FLAME_masks.pkl", "numpy.dtypes dotted", marker)
    res = _invoke("ingest", tiny_capture, tmp_path / "ws", "--flame-model", folder / Path(tiny_capture.model_path).name,
                  "--preset", "tiny", "--quiet")
    assert res.exit_code == 2, _text(res)
    assert str(masks) in _text(res) and not marker.exists()
    assert not (tmp_path / "ws" / "data").exists()


def test_replaced_workspace_models_are_refused_by_later_stages(tmp_path, tiny_ws, cmd_avatar_ws):
    marker = tmp_path / "RAN"
    ws = tmp_path / "ws"
    shutil.copytree(tiny_ws, ws)
    data_model = _write(ws / "data" / "flame_model.npz", "numpy.dtypes dotted", marker)
    res = _invoke("init-mesh", ws, "--preset", "tiny", "--quiet")
    assert res.exit_code != 0 and str(data_model) in _text(res), _text(res)
    assert not (ws / "init").exists()

    ws2 = tmp_path / "ws2"
    shutil.copytree(cmd_avatar_ws, ws2)
    init_model = _write(ws2 / "init" / "flame_model.npz", "numpy.dtypes dotted", marker)
    res = _invoke("export", ws2, "--ply", "--quiet")
    assert res.exit_code != 0, _text(res)
    assert "flame_model.npz" in _text(res)
    assert not (ws2 / "export").exists()
    assert not marker.exists()
    assert init_model.exists()


def _edit_avatar_tree(path: Path, edit: Callable[[dict], None], fix_digest: bool) -> None:
    """Rewrite an avatar file's JSON tree in place (and its digest when ``fix_digest``)."""
    from safetensors.torch import load, save

    from sage_core.serialization import META_DIGEST, META_SHA, META_TREE, _read_header, tree_digest

    data = path.read_bytes()
    header, _ = _read_header(data)
    meta = dict(header["__metadata__"])
    tree = json.loads(meta[META_TREE])
    edit(tree)
    meta[META_TREE] = json.dumps(tree)
    if fix_digest:
        meta[META_DIGEST] = tree_digest(meta["sage.kind"], meta["sage.format"], meta[META_TREE], meta[META_SHA])
    path.write_bytes(save(load(data), metadata=meta))


@pytest.fixture(scope="module")
def bundle_dir(cmd_avatar_ws, tmp_path_factory):
    ws = tmp_path_factory.mktemp("sec_bundle") / "ws"
    shutil.copytree(cmd_avatar_ws, ws)
    res = _invoke("export", ws, "--bundle", "--include-flame-model", "--quiet")
    assert res.exit_code == 0, _text(res)
    return ws / "export" / "bundle"


@pytest.mark.parametrize("ref_name,fix_digest", [("model.pkl", False), ("model.pkl", True), ("model.npz", True)])
def test_a_bundle_pointing_at_a_hostile_file_inside_it_runs_nothing(ref_name, fix_digest, bundle_dir, tmp_path, tiny_capture):
    marker = tmp_path / "RAN"
    bundle = tmp_path / "bundle"
    shutil.copytree(bundle_dir, bundle)
    _write(bundle / ref_name, "numpy.dtypes dotted", marker)

    def point_at_payload(tree: dict) -> None:
        tree.pop("flame", None)
        tree["flame_ref"] = {"file": ref_name, "sha256": "0" * 64}

    avatar = bundle / "avatar.safetensors"
    _edit_avatar_tree(avatar, point_at_payload, fix_digest)
    res = _invoke("reenact", "--bundle", bundle, "--flame-seq", tiny_capture, "--out", tmp_path / "out", "--device", "cpu", "--quiet")
    msg = _text(res)
    assert res.exit_code == 2, msg
    if not fix_digest:
        assert str(avatar) in msg and "structure does not match its checksum" in msg
    else:  # a checksum is no signature: the reference itself is then refused (not an npz / not a zip)
        assert str(avatar if ref_name.endswith(".pkl") else bundle / ref_name) in msg
    assert not marker.exists() and not (tmp_path / "out").exists()


def test_a_referenced_model_is_hashed_before_it_is_parsed(tmp_path, cmd_avatar_ws, monkeypatch):
    """A workspace model replaced by another valid npz is refused on its bytes; the parser never runs."""
    import sage_core.flame.model_io as model_io
    from sage_core.avatar.model import Avatar
    from sage_core.errors import InputError

    ws = tmp_path / "ws"
    shutil.copytree(cmd_avatar_ws, ws)
    model = ws / "init" / "flame_model.npz"
    with np.load(model) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["v_template"] = arrays["v_template"] + 1e-3
    with open(model, "wb") as fh:
        np.savez(fh, **arrays)
    parsed: list[Path] = []
    real = model_io._from_npz
    monkeypatch.setattr(model_io, "_from_npz", lambda p: (parsed.append(p), real(p))[1])
    with pytest.raises(InputError, match="changed since the avatar was saved"):
        Avatar.load(ws / "phase1" / "avatar.pt")
    assert parsed == []


def test_batch_with_a_hostile_model_runs_nothing(tmp_path, tiny_capture):
    marker = tmp_path / "RAN"
    model = _write(tmp_path / "evil.pkl", "numpy.dtypes dotted", marker)
    subjects = tmp_path / "subjects.csv"
    subjects.write_text(f"id,capture,flame_model\nevil,{tiny_capture},{model}\n")
    code = "import typer; from sage_cli.commands.batch_cmd import batch; typer.run(batch)"
    res = subprocess.run([sys.executable, "-c", code, str(subjects), str(tmp_path / "root"), "--preset", "tiny",
                          "--device", "cpu", "--quiet"], capture_output=True, text=True, timeout=600,
                         env={**__import__("os").environ, **ENV})
    assert res.returncode != 0
    summary = json.loads((tmp_path / "root" / "batch_summary.json").read_text())
    (subject,) = summary["subjects"]
    assert subject["status"] == "failed" and subject["returncode"] == 2
    assert str(model) in subject["error"] and "refusing to load global" in subject["error"]
    assert not marker.exists()
    assert not (tmp_path / "root" / "evil" / "data").exists()
