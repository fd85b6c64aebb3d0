"""The cell file (TOML) as typed, frozen dataclasses.

One file describes the whole cell: the simulated scene (table, part, tape, cameras, arm,
tools) and what the real cell needs (robot address, limits, calibration, grasp). Every
key is checked: an unknown or missing key, a wrong type or length, or a camera that does
not see the tape is one :class:`CellConfigError` naming the file and the key.

Vectors are tuples of floats (metres, radians unless a key ends in ``_deg``); convert
with ``np.asarray`` where used.
"""
from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tapecell.estimator.errors import TapecellError
from tapecell.estimator.geometry import look_at
from tapecell.estimator.scene import Box
from tapecell.estimator.tape import TapeSpec

Vec3 = tuple[float, float, float]
Pose6 = tuple[float, float, float, float, float, float]
Rgba = tuple[float, float, float, float]


class CellConfigError(TapecellError):
    """The cell file is missing, unreadable or inconsistent."""


# ----------------------------------------------------------------------------- sections
@dataclass(frozen=True)
class SimSection:
    """timestep, settle_s (longest settling): s. settle_velocity: rad/s. mask_source: "rgb" (the estimator's OpenCV
    segmentation of the rendered image) or "segmentation" (MuJoCo's exact mask).
    shadows: render shadows and reflections. ignore_dilate_px: margin of ignore masks."""
    timestep: float
    settle_s: float
    settle_velocity: float
    mask_source: str
    shadows: bool
    ignore_dilate_px: int


@dataclass(frozen=True)
class BoxSection:
    """A box standing on the table (or the table itself): size = full extents [m],
    center_xy [m], rgba colour."""
    size: Vec3
    center_xy: tuple[float, float]
    rgba: Rgba


@dataclass(frozen=True)
class TapeSection:
    """The simulated tape. Lengths in m; stiffnesses per unit length (EI, GJ) in N m^2;
    hinge_frequency in rad/s; base_trunk/base_normal are directions in the world frame."""
    length: float
    width: float
    thickness: float
    plates: int
    estimator_plates: int
    density: float
    base_position: Vec3
    base_trunk: Vec3
    base_normal: Vec3
    flat_bend_stiffness: float
    edge_bend_stiffness: float
    twist_stiffness: float
    hinge_frequency: float
    damping_ratio: float
    max_flat_bend_deg: float
    max_twist_deg: float
    max_edge_bend_deg: float
    edge_on_deg: float
    rgba: Rgba
    friction: float

    @property
    def plate_length(self) -> float:
        return self.length / self.plates

    @property
    def world_from_base(self) -> np.ndarray:
        """(3, 3) frame F0: columns trunk, left (across the width), normal."""
        trunk = _unit(self.base_trunk)
        normal = _unit(self.base_normal)
        left = np.cross(normal, trunk)
        return np.column_stack([trunk, left, normal])


@dataclass(frozen=True)
class CameraPlacement:
    """A camera at ``position`` looking at ``target`` with ``up`` up in its image [m]."""
    name: str
    position: Vec3
    target: Vec3
    up: Vec3


@dataclass(frozen=True)
class CamerasSection:
    """Common intrinsics (no lens distortion in simulation) and the placements in order;
    a 2-camera cell uses the first two."""
    width: int
    height: int
    fx: float
    margin_px: int
    camera: tuple[CameraPlacement, ...]

    @property
    def fovy_deg(self) -> float:
        return float(np.degrees(2.0 * np.arctan(0.5 * self.height / self.fx)))


@dataclass(frozen=True)
class OverviewSection:
    """A wide camera for snapshots (not used by the estimator)."""
    position: Vec3
    target: Vec3
    fovy_deg: float
    width: int
    height: int


@dataclass(frozen=True)
class ArmSection:
    """UR5e. Joints in rad; kp N m/rad; damping N m s/rad; speeds rad/s."""
    model: str
    home_joints: tuple[float, ...]
    park_joints: tuple[float, ...]
    kp: float
    damping: float
    max_joint_speed: float
    joint_tolerance: float
    mounted_tool: str


@dataclass(frozen=True)
class PlateTool:
    """Cross calibration plate; flange_from_tcp puts the TCP at the cross centre on the
    plate's face. Sizes in m."""
    flange_from_tcp: Pose6
    size: float
    thickness: float
    cross_width: float
    cross_length: float


@dataclass(frozen=True)
class NeedleTool:
    """Probing needle; the TCP is its tip. radius in m."""
    flange_from_tcp: Pose6
    radius: float


@dataclass(frozen=True)
class GripperTool:
    """Parallel gripper; the TCP is midway between the pads, which close along the TCP's y.
    max_opening m; pad_size m (along x, thickness y, depth z); finger_kp N/m; max_force N;
    close_speed m/s: how fast the pad distance shrinks when closing (simulated arm);
    finger_thickness m: each finger's thickness behind its pad (along y), which the
    collision check and the simulated gripper both use."""
    flange_from_tcp: Pose6
    max_opening: float
    pad_size: Vec3
    finger_kp: float
    max_force: float
    friction: float
    close_speed: float = 0.1
    finger_thickness: float = 0.006


@dataclass(frozen=True)
class ToolsSection:
    plate: PlateTool
    needle: NeedleTool
    gripper: GripperTool

    def flange_from_tcp(self, tool: str) -> np.ndarray:
        """4x4 flange_from_tcp of ``tool`` ("flange", "plate", "needle", "gripper")."""
        if tool == "flange":
            return np.eye(4)
        if tool not in TOOL_NAMES:
            raise CellConfigError(f"unknown tool '{tool}' (known: flange, {', '.join(TOOL_NAMES)})")
        return pose_to_matrix(getattr(self, tool).flange_from_tcp)


TOOL_NAMES = ("plate", "needle", "gripper")


@dataclass(frozen=True)
class LimitsSection:
    """Safety limits for every commanded pose: TCP workspace box and keep-out box
    around the part [m], speeds m/s and rad/s, accelerations m/s^2 and rad/s^2, and the
    clearance [m] the tool and the wrist keep from the table and the part."""
    workspace_min: Vec3
    workspace_max: Vec3
    max_tcp_speed: float
    max_tcp_accel: float
    max_joint_speed: float
    keepout_min: Vec3
    keepout_max: Vec3
    max_joint_accel: float = 1.4
    clearance: float = 0.005


@dataclass(frozen=True)
class CalibrationSection:
    """Robot-moved cross-plate calibration: a grid of grid_counts points between grid_min
    and grid_max [m], plate tilts [deg], acceptance (min_poses, max_rms_px) and the
    distortion terms to fit."""
    grid_counts: tuple[int, int, int]
    grid_min: Vec3
    grid_max: Vec3
    tilts_deg: tuple[float, ...]
    min_poses: int
    max_rms_px: float
    distortion_model: str


@dataclass(frozen=True)
class GripperIOSection:
    """How the real gripper is wired to the UR controller's digital I/O (``[robot.gripper]``).

    output_kind: "standard" (control box outputs 0-7) or "tool" (tool flange outputs 0-1).
    close_output: the output that closes the jaws; open_output: the one that opens them, or
    -1 when one output does both (then ``close_output`` at the other level opens).
    active_high: the level that switches an output on (false for inverted wiring).
    close_wait_s, open_wait_s: how long the jaws take to move [s].
    closed_input: a standard digital input (0-7) that is on while the jaws are closed, or -1
    for none; closed_input_timeout_s: how long to wait for it after ``close_wait_s`` [s]."""
    output_kind: str = "standard"
    close_output: int = 0
    open_output: int = -1
    active_high: bool = True
    close_wait_s: float = 0.5
    open_wait_s: float = 0.5
    closed_input: int = -1
    closed_input_timeout_s: float = 1.0


@dataclass(frozen=True)
class RobotSection:
    """The real cell: UR controller address and the cameras in ``[[cameras.camera]]`` order,
    each an OpenCV ``VideoCapture`` device index (int) or a URL / device path (str).

    gripper: its I/O wiring. Deadlines [s]: connect_timeout_s for connecting, call_timeout_s
    for every read, check and I/O call, and a move may take its expected duration plus
    move_margin_s. dashboard_port and script_port are where a stop is sent when the robot
    stops answering (the dashboard server's "stop" and a URScript ``stopj``)."""
    host: str
    port: int
    camera_devices: tuple[int | str, ...]
    gripper: GripperIOSection = GripperIOSection()
    connect_timeout_s: float = 10.0
    call_timeout_s: float = 2.0
    move_margin_s: float = 2.0
    dashboard_port: int = 29999
    script_port: int = 30002


@dataclass(frozen=True)
class GraspSection:
    """Grasp planning (only on estimates whose verdict is "ok"): grasp inset [m] from the
    tip; approach from pregrasp_distance [m]; lift [m] along lift_mode's path ("arc" or
    "peel", see ``cell.planner``)."""
    inset: float
    pregrasp_distance: float
    lift: float
    lift_mode: str = "arc"


@dataclass(frozen=True)
class EpisodeSection:
    """Sim episodes: cameras_file is a tape-cameras/1 file (relative to the cell file) to
    estimate with, e.g. from ``tapecell calibrate --sim``; empty uses the simulator's true
    cameras."""
    cameras_file: str


@dataclass(frozen=True)
class CellConfig:
    """The whole cell file. ``source`` is the file it was read from."""
    sim: SimSection
    table: BoxSection
    part: BoxSection
    tape: TapeSection
    cameras: CamerasSection
    overview: OverviewSection
    arm: ArmSection
    tools: ToolsSection
    limits: LimitsSection
    calibration: CalibrationSection
    robot: RobotSection
    grasp: GraspSection
    episode: EpisodeSection
    randomize: dict = dataclasses.field(default_factory=dict)
    """The ``[randomize]`` table as written (optional): domain randomisation of sim episodes,
    checked and applied by the simulator (tapecell.sim.randomize), which the real cell
    never loads."""
    source: str = ""

    def camera_placements(self, n_cameras: int) -> tuple[CameraPlacement, ...]:
        if not 1 <= n_cameras <= len(self.cameras.camera):
            raise CellConfigError(f"{self.source}: asked for {n_cameras} cameras, the cell has "
                                 f"{len(self.cameras.camera)}")
        return self.cameras.camera[:n_cameras]


# ------------------------------------------------------------------------------ loading
def default_cell_path() -> Path:
    """The bundled ``cell.toml`` (``assets/`` in a checkout, ``tapecell.assets`` installed)."""
    from tapecell.assets import asset_path

    return asset_path("cell.toml")


def load_cell_config(path: str | Path | None = None) -> CellConfig:
    """Read and check a cell file; ``None`` reads the bundled ``assets/cell.toml``."""
    path = Path(path) if path is not None else default_cell_path()
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except FileNotFoundError:
        raise CellConfigError(f"{path}: cell file not found") from None
    except OSError as e:
        raise CellConfigError(f"{path}: cannot read cell file ({e.strerror})") from None
    except tomllib.TOMLDecodeError as e:
        raise CellConfigError(f"{path}: not valid TOML ({e})") from None
    cfg = _build(CellConfig, doc, str(path), "", skip={"source"})
    cfg = dataclasses.replace(cfg, source=str(path))
    _check(cfg)
    return cfg


def _build(cls: type, table: Any, source: str, where: str, skip: frozenset | set = frozenset()):
    """Build dataclass ``cls`` from a TOML table, rejecting unknown and missing keys."""
    what = f"[{where}]" if where else "the top level"
    if not isinstance(table, dict):
        raise CellConfigError(f"{source}: {where or 'document'} must be a table")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls) if f.name not in skip]
    unknown = sorted(set(table) - set(names))
    if unknown:
        key = f"{where}.{unknown[0]}" if where else unknown[0]
        raise CellConfigError(f"{source}: unknown key '{key}' in {what} (known: {', '.join(names)})")
    values = {}
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        key = f"{where}.{f.name}" if where else f.name
        if f.name not in table:
            if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING:
                continue
            raise CellConfigError(f"{source}: missing key '{key}'")
        values[f.name] = _convert(hints[f.name], table[f.name], source, key)
    return cls(**values)


def _convert(tp: Any, value: Any, source: str, key: str) -> Any:
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, source, key)
    if tp is dict:
        if not isinstance(value, dict):
            raise CellConfigError(f"{source}: [{key}] must be a table, got {value!r}")
        return dict(value)
    if tp is bool:
        if not isinstance(value, bool):
            raise CellConfigError(f"{source}: '{key}' must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise CellConfigError(f"{source}: '{key}' must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise CellConfigError(f"{source}: '{key}' must be a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise CellConfigError(f"{source}: '{key}' must be a string, got {value!r}")
        return value
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        options = typing.get_args(tp)
        for option in options:
            try:
                return _convert(option, value, source, key)
            except CellConfigError:
                continue
        names = " or ".join({int: "an integer", float: "a number", str: "a string", bool: "true or false"}
                            .get(o, str(o)) for o in options)
        raise CellConfigError(f"{source}: '{key}' must be {names}, got {value!r}")
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list):
            raise CellConfigError(f"{source}: '{key}' must be a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, source, f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise CellConfigError(f"{source}: '{key}' must have {len(args)} entries, got {len(value)}")
        return tuple(_convert(a, v, source, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    raise TypeError(f"cell config field type {tp} not supported")  # a programming error


# ------------------------------------------------------------------------------- checks
def _check(cfg: CellConfig) -> None:
    src = cfg.source

    def need(ok: bool, msg: str) -> None:
        if not ok:
            raise CellConfigError(f"{src}: {msg}")

    s, t = cfg.sim, cfg.tape
    need(0 < s.timestep <= 0.005, "'sim.timestep' must be in (0, 0.005] s")
    need(s.settle_s >= 0, "'sim.settle_s' must be >= 0")
    need(s.mask_source in ("rgb", "segmentation"), "'sim.mask_source' must be \"rgb\" or \"segmentation\"")
    need(t.plates >= 2 and t.estimator_plates >= 1, "'tape.plates' must be >= 2, 'tape.estimator_plates' >= 1")
    for k in ("length", "width", "thickness", "density", "flat_bend_stiffness", "edge_bend_stiffness",
              "twist_stiffness", "hinge_frequency", "damping_ratio"):
        need(getattr(t, k) > 0, f"'tape.{k}' must be positive")
    need(np.linalg.norm(t.base_trunk) > 0 and np.linalg.norm(t.base_normal) > 0,
         "'tape.base_trunk' and 'tape.base_normal' must be non-zero")
    need(abs(np.dot(_unit(t.base_trunk), _unit(t.base_normal))) < 1e-6,
         "'tape.base_trunk' and 'tape.base_normal' must be perpendicular")
    need(len(cfg.arm.home_joints) == 6 and len(cfg.arm.park_joints) == 6,
         "'arm.home_joints' and 'arm.park_joints' need 6 joint angles")
    need(cfg.arm.model == "ur5e", "'arm.model' must be \"ur5e\" (the only arm modelled)")
    need(cfg.arm.mounted_tool in TOOL_NAMES, f"'arm.mounted_tool' must be one of {', '.join(TOOL_NAMES)}")
    need(len(cfg.cameras.camera) >= 2, "at least two [[cameras.camera]] entries are needed")
    names = [c.name for c in cfg.cameras.camera]
    need(len(set(names)) == len(names), f"camera names must be unique, got {names}")
    need(cfg.calibration.distortion_model in ("none", "k1", "k1k2", "k1k2p1p2", "k1k2p1p2k3"),
         "'calibration.distortion_model' must be none, k1, k1k2, k1k2p1p2 or k1k2p1p2k3")
    need(cfg.tools.gripper.close_speed > 0, "'tools.gripper.close_speed' must be positive")
    need(cfg.tools.gripper.finger_thickness > 0, "'tools.gripper.finger_thickness' must be positive")
    need(cfg.grasp.lift_mode in ("arc", "peel"), "'grasp.lift_mode' must be \"arc\" or \"peel\"")
    need(all(a < b for a, b in zip(cfg.limits.workspace_min, cfg.limits.workspace_max)),
         "'limits.workspace_min' must be below 'limits.workspace_max' on every axis")
    _check_robot(cfg.robot, need)
    for cam in cfg.cameras.camera:
        _check_camera_sees_tape(cfg, cam)


def _check_robot(r: RobotSection, need) -> None:
    g = r.gripper
    need(bool(r.host.strip()), "'robot.host' must not be empty")
    for key in ("port", "dashboard_port", "script_port"):
        need(1 <= getattr(r, key) <= 65535, f"'robot.{key}' must be a TCP port (1-65535)")
    for key in ("connect_timeout_s", "call_timeout_s", "move_margin_s"):
        need(getattr(r, key) > 0, f"'robot.{key}' must be positive")
    need(g.output_kind in ("standard", "tool"), "'robot.gripper.output_kind' must be \"standard\" or \"tool\"")
    pins = 8 if g.output_kind == "standard" else 2
    need(0 <= g.close_output < pins, f"'robot.gripper.close_output' must be a {g.output_kind} digital output "
                                     f"0-{pins - 1}")
    need(g.open_output == -1 or (0 <= g.open_output < pins and g.open_output != g.close_output),
         f"'robot.gripper.open_output' must be -1 (none) or another {g.output_kind} digital output 0-{pins - 1}")
    need(g.closed_input == -1 or 0 <= g.closed_input < 8,
         "'robot.gripper.closed_input' must be -1 (none) or a standard digital input 0-7")
    for key in ("close_wait_s", "open_wait_s", "closed_input_timeout_s"):
        need(getattr(g, key) >= 0, f"'robot.gripper.{key}' must be >= 0")


def _check_camera_sees_tape(cfg: CellConfig, cam: CameraPlacement) -> None:
    """The straight, flat tape (its four corners) must lie inside the camera's image."""
    t, c = cfg.tape, cfg.cameras
    F0 = t.world_from_base
    base = np.asarray(t.base_position)
    corners = np.array([base + a * t.length * F0[:, 0] + b * 0.5 * t.width * F0[:, 1]
                        for a in (0.0, 1.0) for b in (-1.0, 1.0)])
    world_from_cv = look_at_world_from_cv(cam.position, cam.target, cam.up, cfg.source, cam.name)
    pc = (corners - np.asarray(cam.position)) @ world_from_cv
    m = c.margin_px
    if np.any(pc[:, 2] <= 0):
        raise CellConfigError(f"{cfg.source}: camera '{cam.name}' does not see the tape (it is behind the camera)")
    u = c.fx * pc[:, 0] / pc[:, 2] + 0.5 * c.width - 0.5
    v = c.fx * pc[:, 1] / pc[:, 2] + 0.5 * c.height - 0.5
    if np.any((u < m) | (u > c.width - 1 - m) | (v < m) | (v > c.height - 1 - m)):
        raise CellConfigError(f"{cfg.source}: camera '{cam.name}' does not see the tape (it leaves the "
                             f"{c.width}x{c.height} image; corners at u={np.round(u).tolist()}, "
                             f"v={np.round(v).tolist()})")


# ---------------------------------------------------------------------- small geometry
def _unit(v: Any) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def look_at_world_from_cv(position: Any, target: Any, up: Any, source: str = "", name: str = "") -> np.ndarray:
    """(3, 3) world_from_camera rotation in OpenCV's convention (x right, y down, z forward)
    for a camera at ``position`` looking at ``target`` with ``up`` up in the image."""
    z = np.asarray(target, float) - np.asarray(position, float)
    if np.linalg.norm(z) < 1e-9:
        raise CellConfigError(f"{source}: camera '{name}' has its target at its position")
    z = z / np.linalg.norm(z)
    down = -np.asarray(up, float)
    if np.linalg.norm(down - np.dot(down, z) * z) < 1e-9:
        raise CellConfigError(f"{source}: camera '{name}' looks along its 'up' direction")
    return look_at(position, target, up)


def pose_to_matrix(pose: Any) -> np.ndarray:
    """[x, y, z, rx, ry, rz] (m, rotation vector in rad) -> 4x4 transform."""
    from scipy.spatial.transform import Rotation

    pose = np.asarray(pose, float)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(pose[3:6]).as_matrix()
    T[:3, 3] = pose[:3]
    return T


def matrix_to_pose(T: np.ndarray) -> np.ndarray:
    """4x4 transform -> [x, y, z, rx, ry, rz] (rotation vector via scipy, safe near pi)."""
    from scipy.spatial.transform import Rotation

    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])


def tape_spec(cfg: CellConfig, plates: int | None = None) -> TapeSpec:
    """The tape as a plate chain of ``plates`` equal plates (default: the simulated ones)."""
    t = cfg.tape
    n = plates or t.plates
    return TapeSpec(np.full(n, t.length / n), t.width, np.asarray(t.base_position, float), t.world_from_base)


def scene_boxes(cfg: CellConfig) -> tuple[Box, ...]:
    """The cell's known solid boxes in the world frame: the part and the table (the
    simulator builds its geoms from the same numbers; the real cell's estimates use them)."""
    p, tb = cfg.part, cfg.table
    return (Box("part", np.array([p.center_xy[0], p.center_xy[1], p.size[2] / 2]), np.asarray(p.size, float), np.eye(3)),
            Box("table", np.array([tb.center_xy[0], tb.center_xy[1], -tb.size[2] / 2]), np.asarray(tb.size, float),
                np.eye(3)))
