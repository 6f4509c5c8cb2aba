"""The one atomic-write implementation: all or nothing, no temp files left, normal permissions."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from sage_core.atomic import atomic_path, atomic_write_bytes, atomic_writer


def _mode(p) -> int:
    return stat.S_IMODE(os.stat(p).st_mode)


def test_writes_replace_whole_files_with_umask_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        p = atomic_write_bytes(tmp_path / "sub" / "a.bin", b"one")
        assert p.read_bytes() == b"one" and _mode(p) == 0o644
        with atomic_writer(p) as fh:
            np.savez(fh, x=np.arange(3))
        assert _mode(p) == 0o644 and np.load(p)["x"].tolist() == [0, 1, 2]
    finally:
        os.umask(old)
    assert [q.name for q in (tmp_path / "sub").iterdir()] == ["a.bin"]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temp(tmp_path):
    p = atomic_write_bytes(tmp_path / "a.txt", b"old")
    with pytest.raises(RuntimeError):
        with atomic_writer(p) as fh:
            fh.write(b"half")
            raise RuntimeError("interrupted")
    with pytest.raises(OSError):
        with atomic_path(tmp_path / "b.png") as tmp:
            tmp.write_bytes(b"partial")
            raise OSError("writer failed")
    assert p.read_bytes() == b"old" and sorted(q.name for q in tmp_path.iterdir()) == ["a.txt"]


def test_flame_parameter_files_get_normal_permissions(tmp_path, tiny_capture):
    from sage_core.data.capture import read_capture
    from sage_core.flame.params import save_param_npz

    old = os.umask(0o022)
    try:
        cap = read_capture(tiny_capture, check_images=False)
        out = save_param_npz(tmp_path / "00000.npz", cap.params, 0)
        assert _mode(out) == 0o644
    finally:
        os.umask(old)
