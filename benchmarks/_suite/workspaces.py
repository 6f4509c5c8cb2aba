"""In-process steps of the plan: the synthetic capture check, copying finished stages from a base
workspace, and the test-split motion for ``sage reenact``."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from sage_core.errors import SageError, StageError
from sage_core.workspace import STAGE_FOLDERS, Workspace


def capture_is_current(capture: Path, argv: list[str]) -> bool:
    """True when ``capture`` already holds the synthetic capture ``sage synth ARGV`` would write
    (its ``gt/info.json`` config equals the one the arguments resolve to)."""
    from sage_core.data.synthetic import preset

    info = capture / "gt" / "info.json"
    if not info.is_file():
        return False
    try:
        opts = _synth_options(argv)
    except (ValueError, SageError):  # an argument sage synth would refuse: nothing is current
        return False
    opts.setdefault("tracking", "fitted")  # sage synth's defaults
    opts.setdefault("appearance", "detailed")
    try:
        cfg = preset(opts.pop("preset", "default"), regime=opts.pop("regime", "multiview"), **opts)
        return json.loads(info.read_text(encoding="utf-8"))["config"] == cfg.to_dict()
    except (OSError, ValueError, KeyError, TypeError):
        return False


def _synth_options(argv: list[str]) -> dict:
    names = {"--regime": ("regime", str), "--preset": ("preset", str), "--cameras": ("n_cameras", int), "--width": ("width", int),
             "--height": ("height", int), "--train-timesteps": ("train_timesteps", int), "--test-timesteps": ("test_timesteps", int),
             "--seed": ("seed", int), "--tracking": ("tracking", str), "--appearance": ("appearance", str)}  # fmt: skip
    out: dict = {}
    for i, a in enumerate(argv[:-1]):
        if a in names:
            key, tp = names[a]
            out[key] = tp(argv[i + 1])
    from sage_core.data.synthetic.config import parse_sets

    out.update(parse_sets([argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--set"]))
    return out


def write_photo(path: Path) -> Path:
    """Write the photo head's photograph (scikit-image's ``data.astronaut()``, 512 x 512 RGB) as a
    PNG at ``path`` unless it is already there."""
    if path.is_file():
        return path
    import imageio.v3 as iio
    from skimage import data

    from sage_core.atomic import atomic_write_bytes

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, iio.imwrite("<bytes>", data.astronaut(), extension=".png"))
    return path


def photo_command(path: Path) -> str:
    """The shell line that writes the photo head's photograph (:func:`write_photo`)."""
    code = f"from skimage import data; import imageio.v3 as iio; iio.imwrite({str(path)!r}, data.astronaut())"
    return f'python -c "{code}"'


def track_is_current(capture: Path, argv: list[str]) -> bool:
    """True when ``capture`` already holds what ``sage track ARGV`` would write: its report names
    the same photograph, FLAME model and seed, and is newer than the model."""
    report = capture / "track" / "report.json"
    try:
        doc = json.loads(report.read_text(encoding="utf-8"))
        model = Path(argv[argv.index("--flame-model") + 1])
        seed = int(argv[argv.index("--seed") + 1]) if "--seed" in argv else 0
        return (Path(doc["input"]["path"]).resolve() == Path(argv[1]).resolve() and Path(doc["flame_model"]).resolve() == model.resolve()
                and doc.get("seed") == seed and report.stat().st_mtime >= model.stat().st_mtime)  # fmt: skip
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return False


def _link_or_copy(src: str, dst: str) -> str:
    """Hard link (same file system) else copy with metadata: stage outputs are never modified in
    place (stages write a work folder and rename it), so a link is as safe as a copy."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)
    return dst


def copy_stages(src: Path, dst: Path, stages: tuple[str, ...]) -> list[str]:
    """Copy the finished ``stages`` of workspace ``src`` into workspace ``dst``.

    A stage whose manifest in ``dst`` already has the source's fingerprint and finish time is
    kept; any other is replaced as a whole (the old folder is moved aside first). The destination
    workspace is locked meanwhile; the source is not (it may be training a later stage): its stage
    folders are only ever replaced whole, and a source stage whose manifest changed during the copy
    fails the copy. Returns the stages copied. StageError when a source stage is not complete and fresh.
    """
    sw, dw = Workspace(src), Workspace(dst)
    for st in stages:
        sw.require(st, f"copying into {dw.root}")
    dw.root.mkdir(parents=True, exist_ok=True)
    copied: list[str] = []
    with dw.lock:
        for st in stages:
            sm = sw.manifest(st) or {}
            dm = dw.manifest(st) or {}
            if dm.get("fingerprint") == sm.get("fingerprint") and dm.get("finished_at") == sm.get("finished_at"):
                continue
            final = dw.stage_dir(st)
            tmp = dw.root / ".work" / f".copy-{STAGE_FOLDERS[st]}-{os.getpid()}"
            if tmp.exists():
                shutil.rmtree(tmp)
            tmp.parent.mkdir(parents=True, exist_ok=True)
            shutil.copytree(sw.stage_dir(st), tmp, copy_function=_link_or_copy)
            after = sw.manifest(st) or {}
            if (after.get("fingerprint"), after.get("finished_at")) != (sm.get("fingerprint"), sm.get("finished_at")):
                shutil.rmtree(tmp, ignore_errors=True)
                raise StageError(f"{sw.root}: stage '{st}' was replaced while it was being copied into {dw.root}; run the suite again")
            if final.exists():
                old = dw.root / ".work" / f".old-{STAGE_FOLDERS[st]}-{os.getpid()}"
                if old.exists():
                    shutil.rmtree(old)
                os.replace(final, old)
                shutil.rmtree(old, ignore_errors=True)
            os.replace(tmp, final)
            copied.append(st)
    for st in stages:
        if dw.status(st).status != "complete":
            raise StageError(f"{dw.root}: the copied stage '{st}' is not accepted as complete ({dw.status(st).reason})")
    return copied


def copy_command(src: Path, dst: Path, stages: tuple[str, ...]) -> str:
    """The shell line equivalent to :func:`copy_stages` (``cp -a`` keeps the files' times)."""
    folders = " ".join(str(src / STAGE_FOLDERS[s]) for s in stages)
    return f"mkdir -p {dst} && cp -a {folders} {dst}/"


def write_test_motion(capture: Path, out: Path, steps: int) -> tuple[Path, list[int]]:
    """The reenactment clip: the capture's test timesteps as keys, ``steps`` interpolated frames
    from one to the next (GaussianAvatars motion npz). Returns (path, key timesteps)."""
    from sage_core.export.motion import write_key_motion

    return write_key_motion(capture, out, steps)


def ceiling_command(capture: Path, ws: Path, split: str, lpips_weights: Path | None) -> str:
    """The shell line equivalent to the suite's ceiling step (:func:`sage_core.evaluate.ceiling.evaluate_ceiling`)."""
    lp = "None" if lpips_weights is None else f"'{lpips_weights}'"
    code = f"from sage_core.evaluate.ceiling import evaluate_ceiling; evaluate_ceiling('{capture}', '{ws}', '{split}', {lp})"
    return f'python -c "{code}"'


def motion_command(capture: Path, out: Path, steps: int) -> str:
    """The shell line equivalent to :func:`write_test_motion`."""
    code = f"from pathlib import Path; from sage_core.export.motion import write_key_motion; write_key_motion(Path('{capture}'), Path('{out}'), {steps})"
    return f'python -c "{code}"'
