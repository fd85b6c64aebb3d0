"""The simulated cell: MuJoCo model, data and renderers, captures with ground truth.

MuJoCo's cameras are converted to OpenCV :class:`estimator.geometry.Camera` objects once,
here (``cameras()``); everything downstream works in OpenCV's convention.
"""
from __future__ import annotations

import time
from typing import Callable
from dataclasses import dataclass

import cv2
import mujoco
import numpy as np

from tapecell.estimator.capture import Capture, Truth, View
from tapecell.estimator.geometry import Camera
from tapecell.estimator.segment import SegmentationParams, segment_tape

from tapecell.cell.config import scene_boxes, TOOL_NAMES, CellConfig, CellConfigError
from .scene import GROUP_ARM, GROUP_TAPE, TAPE_HINGES, TOOL_GROUPS, build_spec
from .tape_shape import RestShape, rest_shape, tape_spec
from tapecell.cell.kinematics import JOINT_NAMES

_CV_FROM_MJ_CAM = np.diag([1.0, -1.0, -1.0])   # MuJoCo camera looks down -z with y up


def camera_from_mujoco(model: mujoco.MjModel, data: mujoco.MjData, cam_id: int, width: int, height: int) -> Camera:
    """MuJoCo camera ``cam_id`` rendered at ``width`` x ``height`` as an OpenCV camera.

    The one place MuJoCo's camera convention is converted (dependencies.md): MuJoCo looks
    down its -z with y up, so world_from_cv = cam_xmat @ diag(1, -1, -1);
    f = (H/2) / tan(fovy/2); the principal point is the image centre in pixel-centre
    coordinates, (W/2 - 0.5, H/2 - 0.5). No lens distortion."""
    f = 0.5 * height / np.tan(0.5 * np.radians(model.cam_fovy[cam_id]))
    K = np.array([[f, 0.0, width / 2 - 0.5], [0.0, f, height / 2 - 0.5], [0.0, 0.0, 1.0]])
    world_from_cv = data.cam_xmat[cam_id].reshape(3, 3) @ _CV_FROM_MJ_CAM
    R = world_from_cv.T
    t = -R @ data.cam_xpos[cam_id]
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, cam_id) or f"camera{cam_id}"
    return Camera(name, width, height, K, np.zeros(5), R, t)


class SimError(CellConfigError):
    """The simulation went wrong (unstable, warnings, unknown camera or tool)."""


def _view(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``a[idx]`` as a view of ``a``: ``idx`` must be a run of consecutive indices (as the
    scene is built: the arm's six joints and actuators first, then the two fingers')."""
    idx = np.asarray(idx)
    if len(idx) and np.array_equal(idx, np.arange(idx[0], idx[0] + len(idx))):
        return a[idx[0]:idx[0] + len(idx)]
    raise SimError("the arm's or the fingers' joints or actuators are not consecutive in the model")


@dataclass(frozen=True)
class CaptureTiming:
    """Seconds spent in the last reset (settling) and capture (rendering + segmentation)."""
    settle_s: float
    render_s: float


class SimCell:
    """The cell in MuJoCo: a UR5e with tools, a part with a curled tape, 2 or 3 cameras.

    ``SimCell(config, seed, n_cameras=2)`` builds and compiles the scene, creates the
    renderers once, and resets to ``seed``'s tape. ``model`` / ``data`` are MuJoCo's.
    """

    def __init__(self, config: CellConfig, seed: int = 0, n_cameras: int = 2, tool: str | None = None):
        self.config = config
        self.n_cameras = n_cameras
        self.camera_names = [c.name for c in config.camera_placements(n_cameras)]
        self.seed = seed
        self.model = self._build_model()
        self.data = mujoco.MjData(self.model)
        # a view of the data's warning counters, read after every step (fetching it anew
        # each time cost a tenth of a step); compared as bytes with all zeros (a fifth of
        # the cost of counts.any())
        self._warning_counts = self.data.warning.number
        self._no_warnings = bytes(self._warning_counts.nbytes)
        m = self.model
        self._init_tape()
        self.arm_qadr = np.array([m.jnt_qposadr[m.joint(n).id] for n in JOINT_NAMES])
        self.arm_dofs = np.array([m.jnt_dofadr[m.joint(n).id] for n in JOINT_NAMES])
        self.arm_actuators = np.array([m.actuator(n).id for n in JOINT_NAMES])
        self.finger_qadr = np.array([m.jnt_qposadr[m.joint(f"finger_{s}").id] for s in ("left", "right")])
        self.finger_actuators = np.array([m.actuator(f"finger_{s}").id for s in ("left", "right")])
        # Views of the arm's and the fingers' entries of the data (the same numbers as
        # indexing with the arrays above, without a copy per read in the moves' loops).
        d = self.data
        self.arm_qpos = _view(d.qpos, self.arm_qadr)
        self.arm_qvel = _view(d.qvel, self.arm_dofs)
        self.arm_ctrl = _view(d.ctrl, self.arm_actuators)
        self.finger_qpos = _view(d.qpos, self.finger_qadr)
        self.finger_ctrl = _view(d.ctrl, self.finger_actuators)
        self._pad_geoms = np.array([m.geom(f"pad_{s}").id for s in ("left", "right")])
        # Known objects that can hide the tape: the arm and its tools (a real cell knows
        # where they are from the joints). The part is not one: marking its whole image
        # region unknown throws away the evidence that the tape is not there, which cost far
        # more than it gained (sim, 2 cameras, seeds 0-99: gross failures 5 -> 16).
        self._occluder_geoms = np.array([g for g in range(m.ngeom) if m.geom_group[g] >= GROUP_ARM])
        # Indexed by a segmentation pixel's id (-1, the background, the last entry: False).
        self._is_tape_geom = np.zeros(m.ngeom + 2, bool)
        self._is_tape_geom[self._tape_geoms] = True
        self._is_occluder = np.zeros(m.ngeom + 1, bool)
        self._is_occluder[self._occluder_geoms] = True
        self._pad_contype = m.geom_contype[self._pad_geoms].copy()
        c = config.cameras
        self._renderer = mujoco.Renderer(m, c.height, c.width)
        self._overview_renderer: mujoco.Renderer | None = None
        self._option = mujoco.MjvOption()
        # Renders are noise-free: no opening, which would erase the tape where it is seen
        # edge-on (a line 2-3 px wide). Recorded in the capture so re-segmenting agrees.
        self.segmentation_overrides = {"open_px": 0}
        self.segmentation_params = SegmentationParams().with_overrides(self.segmentation_overrides)
        self.mounted_tool = ""
        self.mount_tool(tool or config.arm.mounted_tool)
        self.rest: RestShape | None = None
        self.timing = CaptureTiming(0.0, 0.0)
        # Called after every step() (e.g. to record the arm while it moves); None: nothing.
        self.step_hook: Callable[[], None] | None = None
        # Let the settled tape sleep while nothing touches it (set_tape_sleep); off as built.
        self.tape_sleep = False
        # What an episode may change in the compiled model (tools, springs, lights), as
        # built: reuse() puts it back.
        self._as_built = {"geom_contype": m.geom_contype.copy(), "qpos_spring": m.qpos_spring.copy(),
                          "light_dir": m.light_dir.copy(), "light_diffuse": m.light_diffuse.copy(),
                          "headlight_ambient": m.vis.headlight.ambient.copy(),
                          "geomgroup": self._option.geomgroup.copy()}
        self._tool_as_built = self.mounted_tool
        self.reset(seed)

    def _build_model(self) -> mujoco.MjModel:
        """The compiled cell (the plate tape's rest shape is set per seed by :meth:`reset`)."""
        self.spec = build_spec(self.config, self.n_cameras)
        return self.spec.compile()

    def _init_tape(self) -> None:
        """The model's tape ids: plates (geoms, bodies), hinges (qpos, dofs), tip site; the
        settling's kinetic-energy weights and the speed it stops at."""
        m, plates = self.model, self.config.tape.plates
        self._tape_geoms = np.array([m.geom(f"tape_{i}").id for i in range(plates)])
        self._tape_bodies = np.array([m.body(f"tape_{i}").id for i in range(plates)])
        self._tape_qadr = np.array([[m.jnt_qposadr[m.joint(f"tape_{i}_{h}").id] for h in ("twist", "flat", "edge")]
                                    for i in range(plates)])
        self._tape_dofs = np.array([m.jnt_dofadr[m.joint(f"tape_{i}_{h}").id]
                                    for i in range(plates) for h in TAPE_HINGES])
        self._tip_site = m.site("tape_tip").id
        # Inertia weights of the tape's hinges for the kinetic energy used in settling.
        self._tape_armature = m.dof_armature[self._tape_dofs] + m.dof_damping[self._tape_dofs] * m.opt.timestep
        self._settle_velocity = self.config.sim.settle_velocity
        self._settle_s = self.config.sim.settle_s
        self._settle_every, self._settle_quiet = 10, 1    # see settle()
        self._flex_pixel: int | None = None   # the segmentation id of a flex tape's pixels

    def reusable_for(self, seed: int) -> bool:
        """Can :meth:`reuse` reset this cell to ``seed``? (Always: the plate tape's rest shape
        is its springs' reference angles.)"""
        return True

    def reuse(self, seed: int) -> RestShape:
        """The cell as a new ``SimCell`` of the same config would be, at ``seed``: the model
        put back as built (tools, springs, lights, what is rendered), no step hook, then
        :meth:`reset`. Saves building the model and the renderer (EGL context) again, most
        of an episode's capture time; a campaign's worker reuses one cell."""
        m, b = self.model, self._as_built
        m.geom_contype[:] = b["geom_contype"]
        m.qpos_spring[:] = b["qpos_spring"]
        m.light_dir[:] = b["light_dir"]
        m.light_diffuse[:] = b["light_diffuse"]
        m.vis.headlight.ambient[:] = b["headlight_ambient"]
        self._option.geomgroup[:] = b["geomgroup"]
        self.mount_tool(self._tool_as_built)
        self.step_hook = None
        self.tape_sleep = False
        self.timing = CaptureTiming(0.0, 0.0)
        return self.reset(seed)

    # ------------------------------------------------------------------ state
    def close(self) -> None:
        """Free the renderers' GL contexts."""
        self._renderer.close()
        if self._overview_renderer is not None:
            self._overview_renderer.close()

    def __enter__(self) -> "SimCell":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def mount_tool(self, tool: str) -> None:
        """Show ``tool`` ("plate", "needle", "gripper") on the flange and hide the others.
        All three are modelled; only the mounted one is rendered and has contacts."""
        if tool not in TOOL_NAMES:
            raise SimError(f"unknown tool '{tool}' (known: {', '.join(TOOL_NAMES)})")
        for name, group in TOOL_GROUPS.items():
            self._option.geomgroup[group] = name == tool
        self.model.geom_contype[self._pad_geoms] = self._pad_contype if tool == "gripper" else 0
        self.mounted_tool = tool

    def show_tape(self, visible: bool) -> None:
        """Render the tape (the default) or not, e.g. to calibrate the cameras as on the real
        cell, which is calibrated without a tape. Only rendering changes: the tape is still
        simulated."""
        self._option.geomgroup[GROUP_TAPE] = bool(visible)

    def reset(self, seed: int | None = None, arm_joints: np.ndarray | None = None) -> RestShape:
        """Reset to ``seed``'s curled tape (arm parked, gripper open) and let it settle under
        gravity for ``sim.settle_s``. Deterministic: the same seed gives the same state."""
        t0 = time.perf_counter()
        if seed is not None:
            self.seed = int(seed)
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        self.rest = rest_shape(self.config, self.seed)
        self._reset_tape()
        q_arm = np.asarray(self.config.arm.park_joints if arm_joints is None else arm_joints, float)
        d.qpos[self.arm_qadr] = q_arm
        d.ctrl[self.arm_actuators] = q_arm
        open_half = self.config.tools.gripper.max_opening / 2
        d.qpos[self.finger_qadr] = open_half
        d.ctrl[self.finger_actuators] = open_half
        self._sleep_flag(False)        # settling is simulated in full, as always
        mujoco.mj_forward(m, d)
        self.settle()
        self._sleep_flag(self.tape_sleep)
        self.timing = CaptureTiming(time.perf_counter() - t0, self.timing.render_s)
        return self.rest

    def _reset_tape(self) -> None:
        """Put the tape at :attr:`rest` (after ``mj_resetData``)."""
        # The springs' reference angles are the rest shape; start there so settling is short.
        self.model.qpos_spring[self._tape_qadr] = self.rest.angles
        self.data.qpos[self._tape_qadr] = self.rest.angles

    def set_tape_sleep(self, enabled: bool) -> None:
        """Let the tape sleep (MuJoCo's island sleeping, ``mjENBL_SLEEP``) while nothing
        touches it, from now on and after every :meth:`reset`'s settling (never during it).

        Only the pads can touch the tape (``scene``): the arm's tree never sleeps (it is
        actuated), and the settled tape falls asleep once its hinges stay slower than
        ``opt.sleep_tolerance`` for a few steps. A sleeping tape is not stepped (its pose is
        kept, its velocities are zero): a physics step costs ~13 us instead of ~85 us. A pad
        contact (within the tape's contact margin) wakes it in that step, and while the
        pads hold it the tape is in the arm's island, awake and simulated as before. What
        differs from an always-awake tape is the settled tape's residual creep while it
        sleeps (about 13 um at the tip in 5 s on seed 1). Off by default."""
        self.tape_sleep = bool(enabled)
        self._sleep_flag(self.tape_sleep)

    def _sleep_flag(self, on: bool) -> None:
        bit = int(mujoco.mjtEnableBit.mjENBL_SLEEP)
        if on:
            self.model.opt.enableflags |= bit
        else:
            self.model.opt.enableflags &= ~bit

    def settle(self) -> int:
        """Let the tape come to rest under gravity; returns the steps taken.

        Dynamic relaxation: the tape is simulated as usual, but whenever its kinetic energy
        passes a peak its velocities are zeroed, so it slides into the static equilibrium
        within a few of its (slow, ~2 Hz) swings instead of ringing for seconds. Stops when
        no tape hinge moves faster than ``sim.settle_velocity`` (tested every
        ``_settle_every`` steps from the 20th on; a tape may ask for ``_settle_quiet`` steps
        in a row that slow since the last zeroing) or after ``sim.settle_s``.
        """
        m, d = self.model, self.data
        dofs = self._tape_dofs
        arm = self._tape_armature
        n_max = int(round(self._settle_s / m.opt.timestep))
        v_stop = self._settle_velocity
        ke_prev, quiet = 0.0, 0
        for i in range(1, n_max + 1):
            mujoco.mj_step(m, d)
            v = d.qvel[dofs]
            ke = float(np.dot(arm, v * v))
            if ke < ke_prev:
                d.qvel[dofs] = 0.0
                ke, quiet = 0.0, 0
            ke_prev = ke
            quiet = quiet + 1 if np.abs(v).max() < v_stop else 0
            if i >= 20 and i % self._settle_every == 0 and quiet >= self._settle_quiet:
                break
        mujoco.mj_kinematics(m, d)
        self.check_warnings()
        return i

    def step(self, n: int = 1, sync: bool = True) -> None:
        """Advance the simulation ``n`` steps; a MuJoCo warning (instability) is a SimError.

        ``sync``: bring the world poses (``xpos``, ``xmat``, ``geom_xpos``, ``site_xpos``)
        up to date with the new joints; a loop that reads only joints and velocities
        between its steps passes False and calls :meth:`sync` once at its end (the physics
        is the same either way: ``mj_step`` computes the poses it uses itself)."""
        m, d = self.model, self.data
        for _ in range(n):
            mujoco.mj_step(m, d)
        if sync:
            self.sync()
        if self._warning_counts.tobytes() != self._no_warnings:
            self.check_warnings()
        if self.step_hook is not None:
            self.step_hook()

    def step_targets(self, ctrl: np.ndarray, targets: np.ndarray) -> None:
        """One physics step per row of ``targets`` (k, m), each after writing the row into
        ``ctrl`` (m,) (a view of ``data.ctrl``, e.g. :attr:`arm_ctrl`): the same steps as
        ``ctrl[:] = row; step(1, sync=False)`` row by row (warnings checked and the step
        hook called after every step), with less Python around each."""
        m, d = self.model, self.data
        counts, clean = self._warning_counts, self._no_warnings
        for row in targets:
            ctrl[:] = row
            mujoco.mj_step(m, d)
            if counts.tobytes() != clean:
                self.check_warnings()
            if self.step_hook is not None:
                self.step_hook()

    def sync(self) -> None:
        """World poses from the current joints (``mj_kinematics``): ``mj_step`` leaves the
        previous step's poses in ``xpos`` / ``xmat``."""
        mujoco.mj_kinematics(self.model, self.data)

    def check_warnings(self) -> None:
        counts = self._warning_counts
        if counts.any():
            kinds = [mujoco.mjtWarning(i).name for i in np.flatnonzero(counts)]
            raise SimError(f"MuJoCo warned during simulation ({', '.join(kinds)}); seed {self.seed}")

    # -------------------------------------------------------------- the tape
    def tape_frames(self) -> tuple[np.ndarray, np.ndarray]:
        """(nodes (n+1, 3) [m], frames (n+1, 3, 3) world_from_node) of the simulated plates;
        node 0 is the fixed base, node n the tip."""
        d = self.data
        base = self.model.body("tape_base").id
        nodes = np.vstack([d.xpos[self._tape_bodies], d.site_xpos[self._tip_site][None]])
        frames = np.concatenate([d.xmat[base].reshape(1, 3, 3), d.xmat[self._tape_bodies].reshape(-1, 3, 3)])
        nodes[0] = d.xpos[base]
        return nodes, frames

    def tape_centerline(self, per_plate: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """(s (M,) arc length [m], points (M, 3) [m]): the centre line sampled ``per_plate``
        times per plate, base first, tip last."""
        nodes, frames = self.tape_frames()
        L = self.config.tape.plate_length
        f = np.arange(per_plate) / per_plate
        pts = (nodes[:-1, None, :] + f[None, :, None] * L * frames[1:, None, :, 0]).reshape(-1, 3)
        pts = np.vstack([pts, nodes[-1:]])
        s = np.arange(len(pts)) * (L / per_plate)
        return s, pts

    def tape_tip_position(self) -> np.ndarray:
        """(3,) the centre of the tape's free end [m]."""
        return self.data.site_xpos[self._tip_site].copy()

    def tape_tip_frame(self) -> np.ndarray:
        """4x4 world_from_tip: columns trunk, left, normal of the last plate, at the tip."""
        T = np.eye(4)
        T[:3, :3] = self.data.xmat[self._tape_bodies[-1]].reshape(3, 3)
        T[:3, 3] = self.tape_tip_position()
        return T

    def truth(self) -> Truth:
        s, pts = self.tape_centerline()
        return Truth(s, pts, self.tape_tip_frame()[:3, :3])

    def tape_angles(self) -> np.ndarray:
        """(n, 3) current hinge angles (twist, flat, edge) [rad] of the simulated plates."""
        return self.data.qpos[self._tape_qadr].copy()

    def tape_gap(self, geom: int) -> float:
        """Smallest distance [m] between geom ``geom`` (the needle) and the tape (<= 0:
        contact), as MuJoCo measures it between geoms (``mj_geomDistance``)."""
        m, d = self.model, self.data
        fromto = np.zeros(6)
        return float(min(mujoco.mj_geomDistance(m, d, geom, g, 0.05, fromto) for g in self._tape_geoms))

    def tape_gap_at(self, geom: int, arm_q: np.ndarray) -> float:
        """:meth:`tape_gap` were the arm at joints ``arm_q`` [rad]; the arm is not moved and no
        time passes (the world poses are put back as they were)."""
        qpos = self.arm_qpos                      # a view of the data
        saved = qpos.copy()
        qpos[:] = arm_q
        mujoco.mj_kinematics(self.model, self.data)
        try:
            return self.tape_gap(geom)
        finally:
            qpos[:] = saved
            mujoco.mj_kinematics(self.model, self.data)

    def gripper_pad_contacts_with_tape(self) -> dict[str, int]:
        """Number of active contacts of each pad ("left", "right") with tape plates."""
        d = self.data
        out = {"left": 0, "right": 0}
        for i in range(d.ncon):
            g = (d.contact.geom1[i], d.contact.geom2[i])
            for side, pad in zip(("left", "right"), self._pad_geoms):
                if pad in g and self._is_tape_geom[g[0] if g[1] == pad else g[1]]:
                    out[side] += 1
        return out

    # --------------------------------------------------------------- cameras
    def cameras(self) -> list[Camera]:
        """The true cameras in OpenCV's convention (exact K, zero distortion, R, t)."""
        return [self.camera(n) for n in self.camera_names]

    def camera(self, name: str) -> Camera:
        m, d = self.model, self.data
        cid = self._camera_id(name)
        h, w = self._renderer.height, self._renderer.width
        if name == "overview":
            h, w = self.config.overview.height, self.config.overview.width
        return camera_from_mujoco(m, d, cid, w, h)

    def _camera_id(self, name: str) -> int:
        cid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, name)
        if cid < 0:
            raise SimError(f"no camera '{name}' (have {', '.join(self.camera_names)}, overview)")
        return cid

    def _renderer_for(self, name: str) -> mujoco.Renderer:
        if name != "overview":
            return self._renderer
        if self._overview_renderer is None:
            ov = self.config.overview
            self._overview_renderer = mujoco.Renderer(self.model, ov.height, ov.width)
        return self._overview_renderer

    def _update(self, name: str, option: mujoco.MjvOption | None = None) -> mujoco.Renderer:
        self._camera_id(name)
        r = self._renderer_for(name)
        r.update_scene(self.data, camera=name, scene_option=option or self._option)
        if not self.config.sim.shadows:
            r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
            r.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        return r

    def render_rgb(self, name: str) -> np.ndarray:
        """(H, W, 3) uint8 image from camera ``name`` (or "overview")."""
        return self._update(name).render().copy()

    def render_segmentation(self, name: str, option: mujoco.MjvOption | None = None) -> np.ndarray:
        """(H, W) int geom id per pixel, -1 for background."""
        r = self._renderer_for(name)
        r.enable_segmentation_rendering()
        try:
            self._update(name, option)
            seg = r.render()
        finally:
            r.disable_segmentation_rendering()
        ids = seg[..., 0].copy()
        ids[seg[..., 1] != int(mujoco.mjtObj.mjOBJ_GEOM)] = -1
        if self._flex_pixel is not None:
            ids[seg[..., 1] == int(mujoco.mjtObj.mjOBJ_FLEX)] = self._flex_pixel
        return ids

    def true_mask(self, name: str) -> np.ndarray:
        """(H, W) bool: pixels where the tape is visible, from segmentation rendering."""
        return self._is_tape_geom[self.render_segmentation(name)]

    def _masks(self, name: str) -> tuple[np.ndarray, np.ndarray | None]:
        """(visible tape mask, ignore mask or None) from segmentation rendering.

        The ignore mask is every pixel where a known occluder (arm, tool) is seen, widened by
        ``sim.ignore_dilate_px``: there the tape may be hidden. As on the real cell, it
        comes from the occluder alone, never from where the tape runs behind it (that
        would hand the estimator the truth)."""
        ids = self.render_segmentation(name)
        visible = self._is_tape_geom[ids]
        occluder = self._is_occluder[ids]
        if not occluder.any():
            return visible, None
        k = 2 * self.config.sim.ignore_dilate_px + 1
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
        ignore = cv2.dilate(occluder.astype(np.uint8), kernel).astype(bool) & ~visible
        return visible, ignore

    def _occluder_may_be_seen(self, cam: Camera, margin_px: float = 4.0) -> bool:
        """False when no known occluder (arm, tools: every one, shown or not) can appear in
        ``cam``'s image: each geom's bounding sphere (``geom_rbound`` about ``geom_xpos``)
        lies wholly behind the camera or wholly outside one of the side planes of its view
        (widened by ``margin_px``). True means only "render and see"."""
        centres = self.data.geom_xpos[self._occluder_geoms] @ cam.R.T + cam.t   # camera frame [m]
        radii = self.model.geom_rbound[self._occluder_geoms]
        fx, fy = cam.K[0, 0], cam.K[1, 1]
        cx, cy = cam.K[0, 2], cam.K[1, 2]
        x, y, z = centres[:, 0], centres[:, 1], centres[:, 2]
        out = z < -radii                                     # wholly behind the image plane
        # side planes through the centre of projection, outward unit normals
        for normal in ((fx, 0.0, -(cam.width - 0.5 - cx + margin_px)), (-fx, 0.0, -(cx + 0.5 + margin_px)),
                       (0.0, fy, -(cam.height - 0.5 - cy + margin_px)), (0.0, -fy, -(cy + 0.5 + margin_px))):
            n = np.asarray(normal) / np.linalg.norm(normal)
            out |= n[0] * x + n[1] * y + n[2] * z > radii
        return not bool(np.all(out))

    def capture(self, rgb: bool = False) -> Capture:
        """A capture of the current state: the estimator's tape model (``estimator_plates``
        plates) with the fixed base, one view per camera, and the ground truth.

        Masks come from the estimator's OpenCV segmentation of the rendered RGB when
        ``sim.mask_source = "rgb"``, else from segmentation rendering. ``rgb`` keeps the
        images in the views."""
        t0 = time.perf_counter()
        views = []
        use_rgb = self.config.sim.mask_source == "rgb"
        for cam in self.cameras():
            if use_rgb and not self._occluder_may_be_seen(cam):
                # The segmentation render would show no arm or tool (the usual capture, the
                # arm parked): no ignore mask, and the mask comes from the RGB image.
                ignore = None
            else:
                true_visible, ignore = self._masks(cam.name)
            image = self.render_rgb(cam.name) if (use_rgb or rgb) else None
            mask = segment_tape(image, self.segmentation_params) if use_rgb else true_visible
            views.append(View(cam, mask, ignore, image if rgb else None))
        spec = tape_spec(self.config, self.config.tape.estimator_plates)
        self.timing = CaptureTiming(self.timing.settle_s, time.perf_counter() - t0)
        return Capture(spec, views, self.truth(), segmentation=dict(self.segmentation_overrides),
                       scene=scene_boxes(self.config))
