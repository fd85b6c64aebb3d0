"""A tape that is not our model: a MuJoCo flexible shell (``flexcomp``, dim 2).

The estimator assumes a chain of rigid plates; this tape is a triangulated elastic sheet
(bending and stretching, ``elastic2d="both"``) pinned at its base on the part, whose rest
shape is a random bend, twist or tip curl (the plate tape's rest shapes of the same seed,
sampled finely) and whose stiffness is drawn from the seed, so that gravity droops it more
or less from that rest shape. It is settled, rendered by the cell's cameras (masks from
MuJoCo's segmentation of the sheet alone), and its truth is read off the sheet's vertices:
the centre line along the tape and the frame at its end.

Used to measure the estimator on tape it did not assume (``tapecell sim capture --tape
shell``, ``scripts/bench_verdict.py --shell N``: :class:`ShellCell`, the tape and the
cameras alone), and the whole system on it (:class:`ShellSimCell`, the whole cell with this
tape in place of the plate chain: grasp episodes with ``--randomize tape_model=shell``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import mujoco
import numpy as np

from tapecell.cell.config import CellConfig, scene_boxes, tape_spec
from tapecell.estimator.capture import Capture, Truth, View
from tapecell.estimator.tape import TapeSpec, forward_kinematics

from .cell import SimCell, SimError, camera_from_mujoco
from .scene import BOX_CONTYPE, CONTACT_SOLREF, GROUP_TAPE, PAD_CONTYPE, TAPE_MARGIN, _add_cameras, _add_world, build_spec
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


def _flex_xml(verts: np.ndarray, cfg: CellConfig, young: float, conaffinity: int = BOX_CONTYPE,
              radius: float | None = None) -> str:
    """The sheet as a ``flexcomp`` element (pinned base rows, no self-collision); the geoms
    of the contypes in ``conaffinity`` touch it: the part and the table (a sheet passing
    through them would be seen to end at their edge, where a real tape rests on the part and
    hangs down its side: fresh 929000 drooped 2.4 mm into the part, its last 17 mm hidden in
    it), and in the grasp cell the gripper's pads; ``radius``: its half thickness as
    collided and rendered (default half the tape's thickness)."""
    radius = cfg.tape.thickness / 2 if radius is None else radius
    el = []
    for i in range(STATIONS - 1):
        for j in range(ACROSS - 1):
            a, b, c, d = i * ACROSS + j, (i + 1) * ACROSS + j, (i + 1) * ACROSS + j + 1, i * ACROSS + j + 1
            el += [a, b, c, a, c, d]
    pin = list(range(2 * ACROSS))
    t = cfg.tape
    mass = t.density * t.length * t.width * t.thickness
    rgba = " ".join(f"{v:g}" for v in t.rgba)
    return (f'<flexcomp name="shell" type="direct" dim="2" radius="{radius:g}" rgba="{rgba}" '
            f'mass="{mass:g}" point="{" ".join(f"{v:.6f}" for v in verts.ravel())}" '
            f'element="{" ".join(map(str, el))}">'
            f'<pin id="{" ".join(map(str, pin))}"/><edge equality="false"/>'
            f'<elasticity young="{young:g}" poisson="0.35" thickness="{t.thickness:g}" elastic2d="both" damping="0.001"/>'
            f'<contact selfcollide="none" contype="0" conaffinity="{conaffinity}" margin="{TAPE_MARGIN:g}" '
            f'solref="{CONTACT_SOLREF[0]:g} {CONTACT_SOLREF[1]:g}" friction="{t.friction:g} 0.005 0.0001"/>'
            f'</flexcomp>')


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
        return _truth(self.vertices())

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


GRASP_RADIUS_M = 0.0005
"""Half thickness of the grasp cell's sheet as collided and rendered [m]: at half the tape's
0.2 mm the pads squeezed it out between them within the close (the fingers met through it)."""
SHEET_SOLIMP = (0.99, 0.999, 0.0002, 0.5, 2.0)
"""Impedance of the pads' contacts with the sheet (MuJoCo's solimp: dmin, dmax, width [m],
midpoint, power)."""
SETTLE_VELOCITY_M_S = 3e-5
"""The whole cell's shell tape is settled when no vertex moves faster than this [m/s] (or
after SETTLE_MAX_S)."""
SETTLE_QUIET_STEPS = 50
"""... for this many steps in a row, none of them a zeroing (see SimCell.settle)."""
SETTLE_MAX_S = 6.0
"""Longest settling of the whole cell's shell tape [s] (at least ``sim.settle_s``): a soft
sheet droops for seconds, and with the plate tape's 1 s one was still falling when the
cameras took it (903036: its tip 63 mm lower at the grasp, which closed on air)."""


class ShellSimCell(SimCell):
    """The whole cell (:class:`SimCell`: the arm, its tools, the part, the cameras) with the
    shell tape of ``seed`` in place of the plate chain: what a grasp episode with
    ``tape_model = "shell"`` runs on. The gripper's pads touch the sheet (flex contacts with
    the plate tape's stiffness and friction, a sharper impedance: :data:`SHEET_SOLIMP`); the
    sheet is collided and rendered 1 mm thick (:data:`GRASP_RADIUS_M`); the needle's
    distance to it is its tip disc's distance to the sheet's triangles (:meth:`tape_gap`).

    Differences from the plate tape's cell: the sheet's rest shape is compiled into the model
    (its vertices), so a cell serves its own seed only (:meth:`reusable_for`); the whole model
    steps with MuJoCo's ``discrete`` integrator (flex elasticity is implicit only there; the
    plate tape's cell uses ``implicitfast``); the sheet never sleeps; its Young's modulus is
    the seed's draw (:data:`YOUNG_PA`) times ``stiffness_scale``."""

    def __init__(self, config: CellConfig, seed: int = 0, n_cameras: int = 2, tool: str | None = None,
                 stiffness_scale: float = 1.0):
        if seed < 0:
            raise SimError(f"seed must be >= 0, got {seed}")
        rng = np.random.default_rng([seed, 4417])
        self.young = float(np.exp(rng.uniform(*np.log(YOUNG_PA)))) * float(stiffness_scale)
        self._built_seed = int(seed)
        super().__init__(config, seed, n_cameras, tool)
        self._is_tape_geom[self._flex_pixel] = True

    def _build_model(self) -> mujoco.MjModel:
        cfg = self.config
        verts, case = _rest_vertices(cfg, self._built_seed)
        self.draw = ShellDraw(case, self.young)
        self.spec = None
        xml = build_spec(cfg, self.n_cameras, tape=False).to_xml()
        xml = xml.replace('integrator="implicitfast"', 'integrator="discrete"')
        flex = _flex_xml(verts, cfg, self.young, conaffinity=PAD_CONTYPE | BOX_CONTYPE,
                          radius=GRASP_RADIUS_M).replace(
            '<flexcomp name="shell"', f'<flexcomp name="shell" group="{GROUP_TAPE}"', 1)
        xml = xml.replace("</worldbody>", flex + "</worldbody>", 1)
        try:
            model = mujoco.MjModel.from_xml_string(xml)
        except ValueError as e:
            raise SimError(f"shell tape of seed {self._built_seed}: {e}") from None
        # The pads' contacts with the sheet reach full impedance within 0.2 mm (the plate
        # tape's pads ramp it over 0.5 mm): softer, the pads closed through the sheet on 7
        # of 30 tries (seeds 902000-902029); so, none.
        model.flex_solimp[:] = SHEET_SOLIMP
        for side in ("left", "right"):
            model.geom_solimp[model.geom(f"pad_{side}").id] = SHEET_SOLIMP
        return model

    def _init_tape(self) -> None:
        m = self.model
        self._flex = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_FLEX, "shell")
        adr, num = m.flex_vertadr[self._flex], m.flex_vertnum[self._flex]
        bodies = np.unique(m.flex_vertbodyid[adr:adr + num])
        self._tape_dofs = np.array([k for b in bodies if b > 0
                                    for k in range(m.body_dofadr[b], m.body_dofadr[b] + m.body_dofnum[b])], int)
        self._tape_geoms = np.zeros(0, int)
        self._tape_qadr = np.zeros((0, 3), int)
        # Equal vertex masses: the kinetic energy's weights are all alike.
        self._tape_armature = np.ones(len(self._tape_dofs))
        self._settle_velocity = SETTLE_VELOCITY_M_S
        self._settle_s = max(self.config.sim.settle_s, SETTLE_MAX_S)
        # Still for SETTLE_QUIET_STEPS steps since the relaxation last zeroed the sheet: right
        # after a zeroing every vertex is slow while the sheet is still on its way.
        self._settle_every, self._settle_quiet = 1, SETTLE_QUIET_STEPS
        self._flex_pixel = m.ngeom          # the segmentation id its pixels get

    def reusable_for(self, seed: int) -> bool:
        """Only for its own seed: the sheet's rest shape is compiled into the model."""
        return int(seed) == self._built_seed

    def reset(self, seed: int | None = None, arm_joints: np.ndarray | None = None):
        if seed is not None and int(seed) != self._built_seed:
            raise SimError(f"this shell tape cell was built for seed {self._built_seed}, not {seed}: "
                           f"the sheet's rest shape is compiled into the model (build a new cell)")
        return super().reset(seed, arm_joints)

    def _reset_tape(self) -> None:
        """Nothing: ``mj_resetData`` puts the sheet's vertices at its rest shape."""

    def _sleep_flag(self, on: bool) -> None:
        super()._sleep_flag(False)        # the sheet never sleeps

    def show_tape(self, visible: bool) -> None:
        self._option.flexgroup[GROUP_TAPE] = bool(visible)

    # -------------------------------------------------------------- the tape
    def vertices(self) -> np.ndarray:
        """(STATIONS, ACROSS, 3) the sheet's vertices [m] now, base row first."""
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_flex(self.model, self.data)
        adr = self.model.flex_vertadr[self._flex]
        return self.data.flexvert_xpos[adr:adr + STATIONS * ACROSS].reshape(STATIONS, ACROSS, 3).copy()

    def tape_tip_position(self) -> np.ndarray:
        return self.vertices()[-1, ACROSS // 2]

    def tape_tip_frame(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = _end_frame(self.vertices())
        T[:3, 3] = self.tape_tip_position()
        return T

    def truth(self) -> Truth:
        return _truth(self.vertices())

    def tape_frames(self):
        raise SimError("the shell tape has no plates (its vertices: ShellSimCell.vertices)")

    def tape_centerline(self, per_plate: int = 2):
        raise SimError("the shell tape has no plates (its truth: ShellSimCell.truth)")

    def tape_angles(self) -> np.ndarray:
        raise SimError("the shell tape has no hinge angles")

    def tape_gap(self, geom: int) -> float:
        """Distance [m] from the tip of geom ``geom`` (the needle, a cylinder: its body's
        origin is the tool's TCP, the centre of its tip disc) to the sheet's mid-surface,
        less the sheet's radius (its half thickness as collided and rendered; <= 0:
        contact): the nearest of the disc's centre and eight points on its rim. The needle
        meets the tape with its tip, approaching along its axis; its shaft's side is not
        measured (MuJoCo's geom distance, which the plate tape's cell uses, has no flex)."""
        v = self.vertices()             # (also brings the bodies' poses up to date)
        m, d = self.model, self.data
        R = d.geom_xmat[geom].reshape(3, 3)
        turn = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)
        rim = m.geom_size[geom][0] * (np.outer(np.cos(turn), R[:, 0]) + np.outer(np.sin(turn), R[:, 1]))
        centre = d.xpos[m.geom_bodyid[geom]]
        points = np.vstack([centre, centre + rim])
        a, b, c = (np.concatenate([v[:-1, :-1], v[1:, 1:]]).reshape(-1, 3),
                   np.concatenate([v[1:, :-1], v[:-1, 1:]]).reshape(-1, 3),
                   np.concatenate([v[1:, 1:], v[:-1, :-1]]).reshape(-1, 3))
        gaps = [np.nanmin(point_triangles_distance(p, a, b, c), initial=np.inf) for p in points]
        return float(min(gaps) - m.flex_radius[self._flex])

    def gripper_pad_contacts_with_tape(self) -> dict[str, int]:
        """Number of active contacts of each pad ("left", "right") with the sheet."""
        d = self.data
        out = {"left": 0, "right": 0}
        if d.ncon == 0:
            return out
        geoms, flexes = d.contact.geom[:d.ncon], d.contact.flex[:d.ncon]
        on_sheet = (flexes == self._flex).any(axis=1)
        for side, pad in zip(("left", "right"), self._pad_geoms):
            out[side] = int(np.count_nonzero(on_sheet & (geoms == pad).any(axis=1)))
        return out


def _end_frame(v: np.ndarray) -> np.ndarray:
    """world_from_tip (3, 3) of vertices ``v`` (STATIONS, ACROSS, 3): trunk along the
    centre line's last segment, left across the end row, normal their cross product."""
    centre = v[:, ACROSS // 2]
    trunk = centre[-1] - centre[-2]
    trunk /= np.linalg.norm(trunk)
    left = v[-1, 0] - v[-1, -1]
    left -= (left @ trunk) * trunk
    left /= np.linalg.norm(left)
    return np.column_stack([trunk, left, np.cross(trunk, left)])


def _truth(v: np.ndarray) -> Truth:
    """The truth of vertices ``v`` (STATIONS, ACROSS, 3): the centre line by arc length and
    the end frame."""
    centre = v[:, ACROSS // 2]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centre, axis=0), axis=1))])
    return Truth(s, centre, _end_frame(v))


def point_triangles_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(k,) distances [m] from point ``p`` (3,) to the triangles (a[i], b[i], c[i]) (k, 3)
    each: the closest point by its Voronoi region (vertex, edge or face; Ericson,
    Real-Time Collision Detection, 5.1.5). NaN for a degenerate triangle that falls in
    none of them (zero area)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_, w_ = vb / denom, vc / denom
        q = a + v_[:, None] * ab + w_[:, None] * ac                      # inside the face
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    cases = [
        (d1 <= 0) & (d2 <= 0), a,
        (d3 >= 0) & (d4 <= d3), b,
        (d6 >= 0) & (d5 <= d6), c,
        (vc <= 0) & (d1 >= 0) & (d3 <= 0), a + t_ab[:, None] * ab,
        (vb <= 0) & (d2 >= 0) & (d6 <= 0), a + t_ac[:, None] * ac,
        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), b + t_bc[:, None] * (c - b),
    ]
    closest = q
    for cond, point in reversed(list(zip(cases[0::2], cases[1::2]))):
        closest = np.where(cond[:, None], point, closest)
    return np.linalg.norm(closest - p, axis=1)
