"""Drive a trained avatar from Python: load it, pose it with FLAME expression parameters, render.

Run ``sage demo`` first (it leaves a trained workspace in ./sage-demo), then::

    python examples/python_api.py sage-demo --out frames --frames 4

It writes ``frames/frame_000.png`` ... : the avatar seen by the workspace's reference camera, its
expression blended from neutral towards a smile-like mix of the first FLAME expression components
with the jaw opening, and ``frames/normal_000.png`` ... with the world normals of the same frames.
Any workspace of ``sage run``, a bundle folder of ``sage export --bundle`` (with ``--flame-model
PATH``, the FLAME model file the bundle names) or an avatar file works.
``--motion FILE`` renders the first frames of a FLAME sequence instead (``sage demo`` writes one:
``sage-demo/motion/demo_motion.npz``).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("avatar", type=Path, help="workspace (after `sage demo` / `sage run`), bundle folder or avatar file")
    p.add_argument("--out", type=Path, default=Path("frames"), help="folder for the PNG frames (default: ./frames)")
    p.add_argument("--frames", type=int, default=4, help="number of frames from neutral to the full expression (default: 4)")
    p.add_argument("--camera", type=int, default=None, help="camera index of the workspace (default: its reference camera)")
    p.add_argument("--strength", type=float, default=1.5, help="size of the expression coefficients at the last frame")
    p.add_argument("--jaw", type=float, default=0.25, help="jaw opening (radians) at the last frame")
    p.add_argument("--motion", type=Path, default=None, help="FLAME sequence (.npz, folder or capture) to render instead")
    p.add_argument("--flame-model", type=Path, default=None, help="the FLAME model file a bundle names (bundles do not carry it)")
    p.add_argument("--device", default="cpu", help="cpu or cuda[:N] (default: cpu)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> list[Path]:
    args = parse_args(argv)
    if args.frames < 1:
        raise SystemExit("--frames must be at least 1")

    import numpy as np

    import sage_core as sage  # torch is loaded only when the first avatar name is used

    avatar = sage.load_avatar(args.avatar, device=args.device, flame_model=args.flame_model)
    camera = sage.reference_camera(args.avatar, args.camera)

    # a few FLAME expression components, blended in over the frames (expr: (E,) coefficients)
    direction = np.zeros(avatar.params.n_expr, np.float32)
    direction[: min(4, direction.size)] = [1.0, -0.6, 0.4, 0.3][: min(4, direction.size)]

    motion = None if args.motion is None else sage.load_flame_params(args.motion, n_expr=avatar.params.n_expr)
    n = args.frames if motion is None else min(args.frames, motion.n_timesteps)

    written: list[Path] = []
    for i in range(n):
        if motion is not None:  # row i of the sequence, with the avatar's own identity
            frame: dict = {"flame": motion, "row": i}
        else:
            w = i / max(args.frames - 1, 1)
            frame = {"expr": args.strength * w * direction, "jaw_pose": [args.jaw * w, 0.0, 0.0]}
        posed = avatar.pose(**frame)  # world-space surfels: means (N, 3), colors (N, 3), ...
        out = sage.render_avatar(avatar, camera, **frame)  # image (H, W, 3), alpha, depth, normal (H, W, 3)
        image = out.image.clamp(0, 1).cpu().numpy()
        normal = (0.5 * (out.normal + 1.0) * out.alpha[..., None]).cpu().numpy()
        for name, img in (("frame", image), ("normal", normal)):
            path = args.out / f"{name}_{i:03d}.png"
            sage.write_image(path, img)
            written.append(path)
        print(f"frame {i}: {len(posed.means)} surfels, coverage {float(out.alpha.mean()):.3f} -> {args.out / f'frame_{i:03d}.png'}")
    return written


if __name__ == "__main__":
    main()
