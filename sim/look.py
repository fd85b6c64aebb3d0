"""The simulated cell as a recording shows it: the MuJoCo model's own geometry.

:func:`body_look` lists the arm's links, the tools and the tape's plates with the
primitive geoms attached to each, a flexible tape's vertices as small spheres (as
:class:`~tapecell.cell.story.BodyLook`);
:class:`MotionSampler` takes every body's world pose, the joints and the gripper opening
while the cell steps (``SimCell.step_hook``), for :meth:`Recorder.motion`. The sampler
runs whether or not anything is recorded: the episode's stages read the same either way.
"""
from __future__ import annotations

import mujoco
import numpy as np

from tapecell.cell.story import BodyLook, BodySample, Shape

from .scene import GROUP_ARM, GROUP_TAPE, TOOL_GROUPS

SAMPLE_PERIOD_S = 0.05
"""Cell time between two motion samples [s]."""
TRUE_TAPE_RGBA = (40, 200, 40, 150)
"""The true tape's plates (the estimate is blue)."""
FLEX_VERTEX_M = 0.0015
"""Radius of the sphere drawn at each vertex of a flexible tape [m]."""

_KINDS = {int(mujoco.mjtGeom.mjGEOM_BOX): "box", int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
          int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinder", int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere"}


def body_look(model: mujoco.MjModel) -> tuple[BodyLook, np.ndarray, dict[str, list[str]]]:
    """(the look, the MuJoCo body id of each of its bodies, per tool the names of its bodies)."""
    groups = {GROUP_ARM: "arm", GROUP_TAPE: "tape", **{g: f"tools/{t}" for t, g in TOOL_GROUPS.items()}}
    names: list[str] = []
    ids: list[int] = []
    shapes: list[Shape] = []
    tools: dict[str, list[str]] = {t: [] for t in TOOL_GROUPS}
    for b in range(1, model.nbody):
        geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == b
                 and int(model.geom_group[g]) in groups and int(model.geom_type[g]) in _KINDS]
        if not geoms:
            continue
        group = int(model.geom_group[geoms[0]])
        body = model.body(b).name
        name = f"{groups[group]}_{body}" if group in TOOL_GROUPS.values() else f"{groups[group]}/{body}"
        j = len(names)
        names.append(name)
        ids.append(b)
        for tool, g in TOOL_GROUPS.items():
            if g == group:
                tools[tool].append(name)
        for g in geoms:
            T = np.eye(4)
            T[:3, 3] = model.geom_pos[g]
            q = model.geom_quat[g]
            T[:3, :3] = _quat_matrix(q)
            kind = _KINDS[int(model.geom_type[g])]
            size = tuple(float(v) for v in model.geom_size[g][:3 if kind == "box" else 2 if kind != "sphere" else 1])
            rgba = TRUE_TAPE_RGBA if group == GROUP_TAPE else tuple(int(round(255 * v)) for v in model.geom_rgba[g])
            shapes.append(Shape(j, kind, size, T, rgba))
    # A flexible tape (the shell, sim.shell) has no geoms: each moving vertex is a small
    # sphere of the true tape's colour.
    for f in range(model.nflex):
        adr, num = model.flex_vertadr[f], model.flex_vertnum[f]
        for b in sorted({int(b) for b in model.flex_vertbodyid[adr:adr + num] if b > 0}):
            names.append(f"tape/{model.body(b).name or f'vertex_{b}'}")
            ids.append(b)
            shapes.append(Shape(len(names) - 1, "sphere", (FLEX_VERTEX_M,), np.eye(4), TRUE_TAPE_RGBA))
    return BodyLook(tuple(names), tuple(shapes)), np.array(ids), tools


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, np.asarray(q, float))
    return R.reshape(3, 3)


class MotionSampler:
    """Takes a :class:`BodySample` every :data:`SAMPLE_PERIOD_S` of cell time while ``cell``
    steps, and on :meth:`mark` (an event: a move begins, the gripper closes)."""

    def __init__(self, cell, sim_arm, samples: list[BodySample] | None = None) -> None:
        self.cell = cell
        self.sim_arm = sim_arm
        self.look, self._ids, self._tools = body_look(cell.model)
        self.samples: list[BodySample] = [] if samples is None else samples
        self._last = -np.inf

    def start(self) -> None:
        """Sample from now on (the cell's step hook)."""
        self.cell.step_hook = self._on_step

    def _on_step(self) -> None:
        if self.cell.data.time - self._last >= SAMPLE_PERIOD_S:
            self.take()

    def take(self, event: str | None = None) -> None:
        d = self.cell.data
        self.cell.sync()      # a step may have left the poses of the step before
        self._last = float(d.time)
        T = np.zeros((len(self._ids), 4, 4))
        T[:, :3, :3] = d.xmat[self._ids].reshape(-1, 3, 3)
        T[:, :3, 3] = d.xpos[self._ids]
        T[:, 3, 3] = 1.0
        mounted = self.cell.mounted_tool
        hidden = frozenset(n for tool, names in self._tools.items() if tool != mounted for n in names)
        opening = self.sim_arm.gripper_opening() if mounted == "gripper" else None
        self.samples.append(BodySample(float(d.time), T, self.sim_arm.joints(), opening, hidden, event))
