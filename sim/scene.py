"""Build the cell's MuJoCo model in code (``mujoco.MjSpec``) from a :class:`CellConfig`.

The UR5e comes from ``assets/ur5e.xml``; table, part, tape, tools, cameras, lights and
actuators are added here. Geom groups (what the renderer shows or hides):
0 world, 1 tape, 2 arm, 3 cross plate, 4 needle, 5 gripper.

Contacts: only the gripper pads touch the tape (pads contype 2, tape conaffinity 2);
everything else is contact-free, so the curled tape never fights the part or itself. The
part and the table have contype 4 (:data:`BOX_CONTYPE`), which no geom here matches: only the
shell tape (:mod:`sim.shell`), which droops far enough to reach them, rests on them.
The tape is a chain of thin plates, each joined to the previous one by three hinges
(z edge bend, y flat bend, x twist: ``F_i = F_{i-1} Rz Ry Rx`` as in the estimator's
model) with their own stiffness, so it bends easily flatwise, hardly edgewise, and
twists moderately; the springs' reference angles are the seed's curled rest shape.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from tapecell.cell.config import TOOL_NAMES, CellConfig, look_at_world_from_cv, pose_to_matrix, scene_boxes

GROUP_WORLD, GROUP_TAPE, GROUP_ARM, GROUP_PLATE, GROUP_NEEDLE, GROUP_GRIPPER = range(6)
TOOL_GROUPS = {"plate": GROUP_PLATE, "needle": GROUP_NEEDLE, "gripper": GROUP_GRIPPER}
TAPE_HINGES = ("edge", "flat", "twist")   # joint order in each plate body: Rz, Ry, Rx
PAD_CONTYPE = 2
BOX_CONTYPE = 4
# Contacts act this far out from the sub-millimetre plates, so the pads cannot squeeze
# through a plate within a timestep.
TAPE_MARGIN = 0.0005
# Pad-tape contacts as a direct spring-damper (N/m, N s/m): MuJoCo's default contact
# stiffness scales with the colliding bodies' mass, and a 40 mg plate squeezed by a
# 6 N finger would let the pads pass through it.
CONTACT_SOLREF = (-2.0e5, -300.0)
OVERLAP = 0.2   # fraction of a plate each tape plate overlaps the next


def ur5e_model_path() -> Path:
    """``assets/ur5e.xml`` next to the cell file (checkout or installed package)."""
    from tapecell.cell.config import default_cell_path

    return default_cell_path().parent / "ur5e.xml"


def _quat(R: np.ndarray) -> list[float]:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return [w, x, y, z]


@dataclass(frozen=True)
class HingeGains:
    """Per-hinge stiffness [N m/rad], damping [N m s/rad] and armature [kg m^2]."""
    stiffness: float
    damping: float
    armature: float


def tape_hinge_gains(cfg: CellConfig) -> list[dict[str, HingeGains]]:
    """Per plate, the gains of its three hinges ("edge", "flat", "twist").

    The tape's stiffness per unit length (EI, GJ) becomes k = EI / L on hinges one plate
    apart. The plates' own inertia is tiny, so each hinge gets armature k/ω² (it rings
    at ``hinge_frequency`` on its own) and the stiff edgewise hinges do not need a
    microsecond timestep. Damping is ``damping_ratio`` of critical for the hinge carrying
    the rest of the tape (armature plus the distal plates' inertia about it).
    """
    t = cfg.tape
    L = t.plate_length
    w = t.hinge_frequency
    plate_mass = t.density * L * t.width * t.thickness
    out = []
    for i in range(t.plates):
        distal_mass = plate_mass * (t.plates - i)
        distal_len = L * (t.plates - i)
        gains = {}
        for name, ei in (("edge", t.edge_bend_stiffness), ("flat", t.flat_bend_stiffness),
                         ("twist", t.twist_stiffness)):
            k = ei / L
            armature = k / w**2
            inertia = armature + distal_mass * distal_len**2 / 3.0
            gains[name] = HingeGains(k, 2.0 * t.damping_ratio * np.sqrt(k * inertia), armature)
        out.append(gains)
    return out


def build_spec(cfg: CellConfig, n_cameras: int, tape: bool = True) -> mujoco.MjSpec:
    """The whole cell as an uncompiled spec; ``tape``: with the plate tape (else without a
    tape: ``sim.shell`` adds its flexible shell)."""
    spec = mujoco.MjSpec.from_file(str(ur5e_model_path()))
    spec.modelname = "tapecell"
    spec.compiler.degree = False
    spec.option.timestep = cfg.sim.timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10.0
    if tape:
        # Dense constraint Jacobians: the same equations, solved ~25 % faster with the pads on the
        # plate tape (98 dofs, ~80 contact rows; MuJoCo's automatic choice is sparse above 60).
        spec.option.jacobian = mujoco.mjtJacobian.mjJAC_DENSE
    ov = cfg.overview
    spec.visual.global_.offwidth = max(ov.width, cfg.cameras.width)
    spec.visual.global_.offheight = max(ov.height, cfg.cameras.height)
    spec.visual.headlight.ambient = [0.35, 0.35, 0.35]
    spec.visual.headlight.diffuse = [0.45, 0.45, 0.45]
    spec.visual.headlight.specular = [0.0, 0.0, 0.0]
    # A neutral grey backdrop (as a real cell's screen would be): edge pixels blend towards
    # grey, losing saturation, so a colour threshold cuts them near half coverage.
    spec.add_texture(name="backdrop", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
                     builtin=mujoco.mjtBuiltin.mjBUILTIN_FLAT, rgb1=[0.62, 0.62, 0.6], rgb2=[0.62, 0.62, 0.6],
                     width=16, height=16)
    _add_world(spec, cfg)
    if tape:
        _add_tape(spec, cfg)
    _add_tools(spec, cfg)
    _add_actuators(spec, cfg)
    _add_cameras(spec, cfg, n_cameras)
    return spec


def _add_world(spec: mujoco.MjSpec, cfg: CellConfig) -> None:
    wb = spec.worldbody
    rgba = {"table": cfg.table.rgba, "part": cfg.part.rgba}
    for box in scene_boxes(cfg):   # the same boxes the captures carry as their scene
        wb.add_geom(name=box.name, type=mujoco.mjtGeom.mjGEOM_BOX, size=box.half, pos=box.center,
                    rgba=list(rgba[box.name]), contype=BOX_CONTYPE, conaffinity=0, group=GROUP_WORLD)
    wb.add_light(name="key", pos=[1.2, 0.2, 1.5], dir=[-0.6, 0.2, -0.8], diffuse=[0.6, 0.6, 0.6],
                 specular=[0.1, 0.1, 0.1], castshadow=True, type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
    wb.add_light(name="fill", pos=[0.6, 0.5, 1.0], dir=[-0.3, 0.0, -1.0], diffuse=[0.3, 0.3, 0.3],
                 specular=[0.0, 0.0, 0.0], castshadow=False, type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)


def _add_tape(spec: mujoco.MjSpec, cfg: CellConfig) -> None:
    t = cfg.tape
    L = t.plate_length
    gains = tape_hinge_gains(cfg)
    axes = {"edge": [0, 0, 1], "flat": [0, 1, 0], "twist": [1, 0, 0]}
    mass = t.density * L * t.width * t.thickness
    parent = spec.worldbody.add_body(name="tape_base", pos=list(t.base_position), quat=_quat(t.world_from_base))
    parent.add_site(name="tape_base", size=[0.002, 0, 0], group=5)
    for i in range(t.plates):
        body = parent.add_body(name=f"tape_{i}", pos=[0.0 if i == 0 else L, 0.0, 0.0])
        for h in TAPE_HINGES:
            g = gains[i][h]
            body.add_joint(name=f"tape_{i}_{h}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=axes[h],
                           stiffness=[g.stiffness, 0, 0], damping=[g.damping, 0, 0], armature=g.armature)
        # Each plate but the last reaches a little over the next one: rigid plates that
        # twist against each other would otherwise leave slits a real tape does not have.
        reach = L if i == t.plates - 1 else L * (1.0 + OVERLAP)
        body.add_geom(name=f"tape_{i}", type=mujoco.mjtGeom.mjGEOM_BOX,
                      size=[reach / 2, t.width / 2, t.thickness / 2], pos=[reach / 2, 0, 0], mass=mass,
                      rgba=list(t.rgba), contype=0, conaffinity=PAD_CONTYPE, condim=3, margin=TAPE_MARGIN,
                      solref=list(CONTACT_SOLREF),
                      friction=[t.friction, 0.005, 0.0001], group=GROUP_TAPE)
        parent = body
    parent.add_site(name="tape_tip", pos=[L, 0, 0], size=[0.002, 0, 0], group=5)


def _tool_body(spec: mujoco.MjSpec, cfg: CellConfig, tool: str) -> mujoco.MjsBody:
    """A body at the tool's TCP frame on the flange; its geometry is drawn back to the flange."""
    flange = spec.body("flange")
    T = pose_to_matrix(getattr(cfg.tools, tool).flange_from_tcp)
    body = flange.add_body(name=f"{tool}_tcp", pos=list(T[:3, 3]), quat=_quat(T[:3, :3]))
    body.gravcomp = 1.0
    body.add_site(name=f"{tool}_tcp", size=[0.002, 0, 0], group=5)
    return body


def _flange_in_tcp(cfg: CellConfig, tool: str) -> np.ndarray:
    T = pose_to_matrix(getattr(cfg.tools, tool).flange_from_tcp)
    return -T[:3, :3].T @ T[:3, 3]


def _stem(body: mujoco.MjsBody, start: np.ndarray, end: np.ndarray, radius: float, rgba, group: int, name: str) -> None:
    if np.linalg.norm(end - start) > 1e-4:
        body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=list(start) + list(end),
                      size=[radius, 0, 0], rgba=rgba, contype=0, conaffinity=0, group=group, mass=0.05)


def _add_tools(spec: mujoco.MjSpec, cfg: CellConfig) -> None:
    box = mujoco.mjtGeom.mjGEOM_BOX
    # Cross plate: white plate, black cross raised 0.3 mm; the TCP is the cross's top centre.
    pl = cfg.tools.plate
    body = _tool_body(spec, cfg, "plate")
    bar_h = 0.00003  # a printed cross: raised walls would shift the seen centre sideways
    body.add_geom(name="plate", type=box, size=[pl.size / 2, pl.size / 2, pl.thickness / 2],
                  pos=[0, 0, -bar_h - pl.thickness / 2], rgba=[0.95, 0.95, 0.95, 1], contype=0, conaffinity=0,
                  group=GROUP_PLATE, mass=0.2)
    for k, size in enumerate(([pl.cross_length / 2, pl.cross_width / 2, bar_h / 2],
                              [pl.cross_width / 2, pl.cross_length / 2, bar_h / 2])):
        body.add_geom(name=f"plate_cross_{k}", type=box, size=size, pos=[0, 0, -bar_h / 2], rgba=[0.02, 0.02, 0.02, 1],
                      contype=0, conaffinity=0, group=GROUP_PLATE, mass=0.001)
    _stem(body, _flange_in_tcp(cfg, "plate"), np.array([0, 0, -bar_h - pl.thickness - 0.01]), 0.01,  # cap stays behind the plate
          [0.3, 0.3, 0.3, 1], GROUP_PLATE, "plate_stem")
    # Needle: its tip is the TCP.
    nd = cfg.tools.needle
    body = _tool_body(spec, cfg, "needle")
    start = _flange_in_tcp(cfg, "needle")
    body.add_geom(name="needle", type=mujoco.mjtGeom.mjGEOM_CYLINDER, fromto=list(0.5 * start) + [0, 0, 0],
                  size=[nd.radius, 0, 0], rgba=[0.85, 0.85, 0.2, 1], contype=0, conaffinity=0,
                  group=GROUP_NEEDLE, mass=0.01)
    _stem(body, start, 0.5 * start, 0.008, [0.3, 0.3, 0.3, 1], GROUP_NEEDLE, "needle_holder")
    _add_gripper(spec, cfg)


FINGER_STOP_M = 0.001
"""How far past the gripper's fully open command [m] each finger's joint stop lies."""


def _add_gripper(spec: mujoco.MjSpec, cfg: CellConfig) -> None:
    """Palm on the flange, two fingers sliding along the TCP's y, pads at the TCP."""
    gr = cfg.tools.gripper
    box = mujoco.mjtGeom.mjGEOM_BOX
    body = _tool_body(spec, cfg, "gripper")
    flange_at = _flange_in_tcp(cfg, "gripper")
    depth = float(np.linalg.norm(flange_at))
    px, py, pz = gr.pad_size
    palm_z = -depth + 0.02
    _stem(body, flange_at, np.array([0, 0, palm_z]), 0.025, [0.2, 0.2, 0.22, 1], GROUP_GRIPPER, "gripper_mount")
    body.add_geom(name="gripper_palm", type=box, size=[0.02, gr.max_opening / 2 + 0.02, 0.012],
                  pos=[0, 0, palm_z], rgba=[0.2, 0.2, 0.22, 1], contype=0, conaffinity=0,
                  group=GROUP_GRIPPER, mass=0.3)
    finger_len = -palm_z - 0.012
    for side, sgn in (("left", 1.0), ("right", -1.0)):
        f = body.add_body(name=f"finger_{side}", pos=[0, 0, 0])
        f.gravcomp = 1.0
        # q = 0: pad faces meet at the TCP; q > 0 opens by q on each side.
        # The joint's stop lies FINGER_STOP_M beyond the fully open command: an open finger
        # rests on its servo, not on the stop (a joint-limit row in every step of the arm's
        # moves doubled a step's cost while the tape sleeps).
        f.add_joint(name=f"finger_{side}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, sgn, 0],
                    range=[-0.002, gr.max_opening / 2 + FINGER_STOP_M], damping=[20.0, 0, 0], armature=0.01)
        ft = gr.finger_thickness / 2
        f.add_geom(name=f"finger_{side}", type=box, size=[px / 2, ft, finger_len / 2],
                   pos=[0, sgn * (py + ft), -pz / 2 - finger_len / 2 + pz / 2 - 0.0],
                   rgba=[0.25, 0.25, 0.27, 1], contype=0, conaffinity=0, group=GROUP_GRIPPER, mass=0.05)
        f.add_geom(name=f"pad_{side}", type=box, size=[px / 2, py / 2, pz / 2], pos=[0, sgn * py / 2, 0],
                   rgba=[0.1, 0.1, 0.1, 1], contype=PAD_CONTYPE, conaffinity=0, condim=3,
                   friction=[gr.friction, 0.005, 0.0001], solref=list(CONTACT_SOLREF), solimp=[0.95, 0.99, 0.0005, 0.5, 2],
                   group=GROUP_GRIPPER, mass=0.01)


def _add_actuators(spec: mujoco.MjSpec, cfg: CellConfig) -> None:
    from tapecell.cell.kinematics import JOINT_LOWER, JOINT_UPPER, JOINT_NAMES

    for j, name in enumerate(JOINT_NAMES):
        jt = spec.joint(name)
        # The joint torque limits (ur5e.xml) must leave the servo room to drive a joint at
        # full speed against its damping: at most half the limit (the wrist's 28 N m).
        jt.damping = [min(cfg.arm.damping, 0.5 * jt.actfrcrange[1] / cfg.arm.max_joint_speed), 0, 0]
        a = spec.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        a.set_to_position(kp=cfg.arm.kp)
        a.ctrlrange = [JOINT_LOWER[j], JOINT_UPPER[j]]
        a.ctrllimited = True
    gr = cfg.tools.gripper
    for side in ("left", "right"):
        a = spec.add_actuator(name=f"finger_{side}", target=f"finger_{side}", trntype=mujoco.mjtTrn.mjTRN_JOINT)
        a.set_to_position(kp=gr.finger_kp)
        a.ctrlrange = [-0.002, gr.max_opening / 2]
        a.ctrllimited = True
        a.forcerange = [-gr.max_force, gr.max_force]
        a.forcelimited = True


def _add_cameras(spec: mujoco.MjSpec, cfg: CellConfig, n_cameras: int) -> None:
    flip = np.diag([1.0, -1.0, -1.0])   # OpenCV camera axes -> MuJoCo's (looks down -z, y up)
    for cam in cfg.camera_placements(n_cameras):
        world_from_cv = look_at_world_from_cv(cam.position, cam.target, cam.up, cfg.source, cam.name)
        spec.worldbody.add_camera(name=cam.name, pos=list(cam.position), quat=_quat(world_from_cv @ flip),
                                  fovy=cfg.cameras.fovy_deg)
    ov = cfg.overview
    world_from_cv = look_at_world_from_cv(ov.position, ov.target, [0, 0, 1], cfg.source, "overview")
    spec.worldbody.add_camera(name="overview", pos=list(ov.position), quat=_quat(world_from_cv @ flip),
                              fovy=ov.fovy_deg)


def tool_names() -> tuple[str, ...]:
    return TOOL_NAMES
