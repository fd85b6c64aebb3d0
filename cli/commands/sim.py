"""``tapecell sim capture|cameras|snapshot|view``: the simulated cell from the command line."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from tapecell.cli.options import add_force, add_seed, check_dir, check_files
from tapecell.estimator.errors import TapecellError


def register(subparsers) -> None:
    p = subparsers.add_parser("sim", help="the simulated MuJoCo cell: captures, true cameras, snapshots, viewer")
    sub = p.add_subparsers(dest="sim_command", metavar="SUBCOMMAND", required=True)

    def common(q: argparse.ArgumentParser, seed: bool = True) -> None:
        q.add_argument("--config", type=Path, default=None, help="cell file (default: the bundled assets/cell.toml)")
        q.add_argument("--cameras", type=int, choices=(2, 3), default=2, help="number of cameras (default 2)")
        if seed:
            add_seed(q, "tape shape seed, 0 or more (default 0)")

    q = sub.add_parser("capture", help="write a tape-capture/1 directory with truth.json")
    common(q)
    q.add_argument("--tape", choices=("plates", "shell"), default="plates",
                   help="plates: the chain of flexible plates (default); shell: a MuJoCo flexible shell, "
                        "a tape that is not the estimator's model (masks only, no arm)")
    q.add_argument("--rgb", action="store_true", help="also write the rendered colour images (plate tape)")
    q.add_argument("--out", type=Path, required=True,
                   help="capture directory to write (a new or empty folder, or add --force)")
    add_force(q)
    q.set_defaults(func=run_capture)

    q = sub.add_parser("cameras", help="write the true cameras as tape-cameras/1")
    common(q, seed=False)
    q.add_argument("--out", type=Path, required=True, help="cameras JSON file to write")
    add_force(q)
    q.set_defaults(func=run_cameras)

    q = sub.add_parser("snapshot", help="save a PNG from every camera and an overview camera")
    common(q)
    q.add_argument("--out", type=Path, required=True,
                   help="directory for the PNGs (a new or empty folder, or add --force)")
    add_force(q)
    q.set_defaults(func=run_snapshot)

    q = sub.add_parser("view", help="open MuJoCo's interactive viewer (needs a display)")
    common(q)
    q.set_defaults(func=run_view)


def _cell(args):
    from tapecell.sim.cell import SimCell
    from tapecell.cell.config import load_cell_config

    return SimCell(load_cell_config(args.config), getattr(args, "seed", 0), n_cameras=args.cameras)


def run_capture(args) -> int:
    from tapecell.estimator.capture import save_capture

    check_dir(args.out, args.force)
    if args.tape == "shell":
        from tapecell.cell.config import load_cell_config
        from tapecell.sim.shell import ShellCell

        if args.rgb:
            raise TapecellError("--rgb: the shell tape's captures hold masks only")
        with ShellCell(load_cell_config(args.config), args.seed, args.cameras) as cell:
            cap = cell.capture()
            save_capture(cap, args.out, force=args.force)
            print(f"wrote {args.out}: shell tape, seed {args.seed} ({cell.draw.case}, Young's modulus "
                  f"{cell.young / 1e9:.2f} GPa), {len(cap.views)} cameras, tip at "
                  f"{[round(float(v), 4) for v in cap.truth.points[-1]]} m; settle {cell.settle_s * 1000:.0f} ms")
        return 0
    with _cell(args) as cell:
        cap = cell.capture(rgb=args.rgb)
        save_capture(cap, args.out, rgb=args.rgb, force=args.force)
        t = cell.timing
        print(f"wrote {args.out}: seed {cell.seed} ({cell.rest.case}), {len(cap.views)} cameras, "
              f"tip at {[round(float(v), 4) for v in cap.truth.points[-1]]} m; "
              f"settle {t.settle_s * 1000:.0f} ms, render {t.render_s * 1000:.0f} ms")
    return 0


def run_cameras(args) -> int:
    from tapecell.estimator.capture import save_cameras

    check_files([args.out], args.force)
    with _cell(args) as cell:
        save_cameras(cell.cameras(), args.out)
        print(f"wrote {args.out}: {', '.join(cell.camera_names)}")
    return 0


def run_snapshot(args) -> int:
    import cv2

    from tapecell.estimator.io import atomic_dir

    out = Path(args.out)
    check_dir(out, args.force)
    with _cell(args) as cell:
        names = cell.camera_names + ["overview"]
        with atomic_dir(out, args.force) as tmp:
            for n in names:
                _, buf = cv2.imencode(".png", cv2.cvtColor(cell.render_rgb(n), cv2.COLOR_RGB2BGR))
                (tmp / f"{n}.png").write_bytes(buf.tobytes())
        print(f"wrote {', '.join(f'{n}.png' for n in names)} to {out} (seed {cell.seed}, {cell.rest.case})")
    return 0


def run_view(args) -> int:
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise TapecellError("no display here (DISPLAY is not set): use 'tapecell sim snapshot --out DIR' to "
                            "render images instead")
    import mujoco.viewer

    with _cell(args) as cell:
        mujoco.viewer.launch(cell.model, cell.data)
    return 0
