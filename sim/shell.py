"""A tape that is not our model: a MuJoCo flexible shell (``flexcomp``, dim 2).

The estimator assumes a chain of rigid plates; this tape is a triangulated elastic sheet
(bending and stretching, ``elastic2d="both"``) pinned at its base on the part, whose rest
shape is a random bend, twist or tip curl (the plate tape's rest shapes of the same seed,
sampled finely) and whose stiffness is drawn from the seed, so that gravity droops it more
or less from that rest shape. It is settled, rendered by the cell's cameras (masks from
MuJoCo's segmentation of the sheet alone), and its truth is read off the sheet's vertices:
the centre line along the tape and the frame at its end.

Used to measure the estimator on tape it did not assume (``tapecell sim capture --tape
shell``, ``scripts/bench_verdict.py --shell N``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import mujoco
import numpy as np

from tapecell.cell.config import CellConfig, scene_boxes, tape_spec
from tapecell.estimator.capture import Capture, Truth, View
from tapecell.estimator.tape import TapeSpec, forward_kinematics

from .cell import SimError, camera_from_mujoco
from .scene import _add_cameras, _add_world
from .tape_shape import rest_shape

STATIONS = 31
"""Vertex rows along the sheet (the first two pinned: the base is clamped)."""
ACROSS = 3
"""Vertices across the sheet's width (edges and centre line)."""
YOUNG_PA = (2e9, 1.2e10)
"""Range of the sheet's Young's modulus [Pa], drawn log-uniformly per seed: the softest
droop far below their rest shape, the stiffest keep it."""
SETTLE_S = 1.5
"""Simulated settling time [s] before the views are taken."""
TIMESTEP_S = 0.0005


@dataclass(frozen=True)
class ShellDraw:
    """What a seed drew: the rest shape's case and the sheet's Young's modulus [Pa]."""

    case: str
    young_pa: float


def _rest_vertices(cfg: CellConfig, seed: int) -> tuple[np.ndarray, str]:
    """(STATIONS * ACROSS, 3) world vertices of the sheet's rest shape, and its case: the
    plate tape's rest shape of ``seed`` as a smooth strip (its chain at STATIONS - 1 plates)."""
    rest = rest_shape(cfg, seed)
    n_sim = len(rest.angles)
    spec = tape_spec(cfg, n_sim)
    k = (STATIONS - 1) // n_sim if (STATIONS - 1) % n_sim == 0 else None
    # Resample the plate angles to STATIONS - 1 finer segments of the same total turn.
    s_coarse = (np.arange(n_sim) + 0.5) / n_sim
    s_fine = (np.arange(STATIONS - 1) + 0.5) / (STATIONS - 1)
    rates = np.stack([np.interp(s_fine, s_coarse, rest.angles[:, a]) for a in range(3)], axis=1)
    fine = rates * n_sim / (STATIONS - 1)
    fine_spec = TapeSpec(np.full(STATIONS - 1, cfg.tape.length / (STATIONS - 1)), cfg.tape.width,
                         spec.base_position, spec.base_rotation)
    shape = forward_kinematics(fine_spec, fine)
    del k
    across = np.linspace(0.5, -0.5, ACROSS) * cfg.tape.width
    verts = shape.nodes[:, None, :] + across[None, :, None] * shape.frames[:, None, :, 1]
    return verts.reshape(-1, 3), rest.case


def _flex_xml(verts: np.ndarray, cfg: CellConfig, young: float) -> str:
    el = []
    for i in range(STATIONS - 1):
        for j in range(ACROSS - 1):
            a, b, c, d = i * ACROSS + j, (i + 1) * ACROSS + j, (i + 1) * ACROSS + j + 1, i * ACROSS + j + 1
            el += [a, b, c, a, c, d]
    pin = list(range(2 * ACROSS))
    t = cfg.tape
    mass = t.density * t.length * t.width * t.thickness
    rgba = " ".join(f"{v:g}" for v in t.rgba)
    return (f'<flexcomp name="shell" type="direct" dim="2" radius="{t.thickness / 2:g}" rgba="{rgba}" '
            f'mass="{mass:g}" point="{" ".join(f"{v:.6f}" for v in verts.ravel())}" '
            f'element="{" ".join(map(str, el))}">'
            f'<pin id="{" ".join(map(str, pin))}"/><edge equality="false"/>'
            f'<elasticity young="{young:g}" poisson="0.35" thickness="{t.thickness:g}" elastic2d="both" damping="0.001"/>'
            f'<contact selfcollide="none" contype="0" conaffinity="0"/></flexcomp>')


class ShellCell:
    """The cell's boxes and cameras with the shell tape of ``seed`` (no arm: the views are
    the tape's alone). ``capture()`` settles it and returns a capture with truth."""

    def __init__(self, cfg: CellConfig, seed: int, n_cameras: int = 2):
        if seed < 0:
            raise SimError(f"seed must be >= 0, got {seed}")
        self.config, self.seed = cfg, seed
        rng = np.random.default_rng([seed, 4417])
        self.young = float(np.exp(rng.uniform(*np.log(YOUNG_PA))))
        verts, case = _rest_vertices(cfg, seed)
        self.draw = ShellDraw(case, self.young)
        spec = mujoco.MjSpec()
        spec.compiler.degree = False
        spec.option.timestep = TIMESTEP_S
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_DISCRETE if hasattr(mujoco.mjtIntegrator, "mjINT_DISCRETE") \
            else mujoco.mjtIntegrator.mjINT_EULER
        spec.visual.global_.offwidth = cfg.cameras.width
        spec.visual.global_.offheight = cfg.cameras.height
        _add_world(spec, cfg)
        _add_cameras(spec, cfg, n_cameras)
        xml = spec.to_xml()
        xml = xml.replace("</worldbody>", _flex_xml(verts, cfg, self.young) + "</worldbody>", 1)
        xml = xml.replace('integrator="implicitfast"', 'integrator="discrete"')
        try:
            self.model = mujoco.MjModel.from_xml_string(xml)
        except ValueError as e:
            raise SimError(f"shell tape of seed {seed}: {e}") from None
        self.data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, self.data)
        self.camera_names = [c.name for c in cfg.camera_placements(n_cameras)]
        self._renderer = mujoco.Renderer(self.model, cfg.cameras.height, cfg.cameras.width)
        self.settle_s = 0.0

    def close(self) -> None:
        self._renderer.close()

    def __enter__(self) -> "ShellCell":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def settle(self) -> None:
        t0 = time.perf_counter()
        for _ in range(int(SETTLE_S / TIMESTEP_S)):
            mujoco.mj_step(self.model, self.data)
        if not np.all(np.isfinite(self.data.flexvert_xpos)):
            raise SimError(f"shell tape of seed {self.seed} went unstable")
        self.settle_s = time.perf_counter() - t0

    def vertices(self) -> np.ndarray:
        """(STATIONS, ACROSS, 3) the sheet's vertices [m], base row first."""
        return self.data.flexvert_xpos.reshape(STATIONS, ACROSS, 3).copy()

    def truth(self) -> Truth:
        v = self.vertices()
        centre = v[:, ACROSS // 2]
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centre, axis=0), axis=1))])
        trunk = centre[-1] - centre[-2]
        trunk /= np.linalg.norm(trunk)
        left = v[-1, 0] - v[-1, -1]
        left -= (left @ trunk) * trunk
        left /= np.linalg.norm(left)
        return Truth(s, centre, np.column_stack([trunk, left, np.cross(trunk, left)]))

    def _mask(self, name: str) -> np.ndarray:
        r = self._renderer
        r.enable_segmentation_rendering()
        r.update_scene(self.data, camera=name)
        seg = r.render()
        r.disable_segmentation_rendering()
        return seg[..., 1] == int(mujoco.mjtObj.mjOBJ_FLEX)

    def capture(self) -> Capture:
        """Settle, then the views of every camera with the truth and the scene boxes."""
        self.settle()
        cfg = self.config
        views = []
        for name in self.camera_names:
            cam_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, name)
            camera = camera_from_mujoco(self.model, self.data, cam_id, cfg.cameras.width, cfg.cameras.height)
            views.append(View(camera, self._mask(name)))
        return Capture(tape_spec(cfg, cfg.tape.estimator_plates), views, self.truth(), scene=scene_boxes(cfg))


def make_capture(cfg: CellConfig, seed: int, n_cameras: int = 2) -> Capture:
    """The shell tape of ``seed`` settled and seen by ``n_cameras`` cameras, with truth."""
    with ShellCell(cfg, seed, n_cameras) as cell:
        return cell.capture()
