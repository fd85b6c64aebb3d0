"""Domain randomisation of sim episodes: what varies from episode to episode, drawn from the
episode's seed so that a campaign is reproducible on any machine and any backend.

Settings come from the cell file's ``[randomize]`` table and from the command line
(``--randomize NAME=VALUE``, ``tapecell sweep --param randomize.NAME=V1,V2``). Each setting
is fixed (a number), a uniform range (``[lo, hi]`` in the cell file, ``lo:hi`` on the
command line) or, for ``cameras`` and ``tape_model``, a list of choices. A setting left
out keeps the cell file's value: with no settings, episodes are exactly the unrandomised
ones.

Names (units in the name):

- ``light_azimuth_deg``, ``light_elevation_deg``: direction of the key light (from where it
  shines; azimuth about world z from +x, elevation above the table);
- ``light_intensity``: the key light's diffuse intensity (the cell file's is 0.6);
- ``ambient``: the ambient light (0.35);
- ``tape_rgb_jitter``: largest change of each of the tape's colour channels (0-1);
- ``tape_width_mm``, ``tape_length_mm``, ``tape_thickness_mm``: the tape's dimensions;
- ``tape_stiffness_scale``: factor on its bending and twist stiffness;
- ``tape_model``: ``"chain"`` (the plate chain, the estimator's own model) or ``"shell"`` (a
  MuJoCo flexible shell, :class:`~tapecell.sim.shell.ShellSimCell`: a tape that is not the
  estimator's model, grasped like the chain);
- ``calib_rot_deg``, ``calib_trans_mm``: calibration error: the estimator gets each camera
  turned by this angle about a random axis and moved by this distance in a random
  direction, while the scene renders with the true cameras;
- ``mask_noise``: probability that the masks get segmentation-like noise (ragged
  boundaries, speckles, pinholes);
- ``cameras``: the number of cameras (2 or 3).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping

import cv2
import numpy as np

from tapecell.estimator.capture import Capture, View
from tapecell.estimator.errors import TapecellError
from tapecell.estimator.synthetic import roughen

SEED_SALT = 0x5EED
"""Mixed with the episode's seed for the randomisation's own random stream (the tape's
shape uses the seed alone, so randomising does not change the shapes)."""

NUMERIC = ("light_azimuth_deg", "light_elevation_deg", "light_intensity", "ambient", "tape_rgb_jitter",
           "tape_width_mm", "tape_length_mm", "tape_thickness_mm", "tape_stiffness_scale", "calib_rot_deg",
           "calib_trans_mm", "mask_noise")
CHOICES = {"cameras": (2, 3), "tape_model": ("chain", "shell")}
NAMES = NUMERIC + tuple(CHOICES)
LIMITS = {"light_elevation_deg": (0.0, 90.0), "light_intensity": (0.0, 2.0), "ambient": (0.0, 1.0),
          "tape_rgb_jitter": (0.0, 1.0), "tape_width_mm": (5.0, 60.0), "tape_length_mm": (60.0, 250.0),
          "tape_thickness_mm": (0.02, 1.0), "tape_stiffness_scale": (0.1, 10.0), "calib_rot_deg": (0.0, 5.0),
          "calib_trans_mm": (0.0, 20.0), "mask_noise": (0.0, 1.0), "light_azimuth_deg": (-360.0, 360.0)}


class RandomizeError(TapecellError):
    """A randomisation setting that cannot be used."""


@dataclass(frozen=True)
class Randomize:
    """Settings by name: a float (fixed), a (lo, hi) tuple (uniform) or, for the choices, a
    tuple of values drawn from with equal chance."""

    settings: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    @classmethod
    def from_table(cls, table: Mapping[str, Any] | None, source: str = "[randomize]") -> "Randomize":
        out: dict[str, Any] = {}
        for name, value in (table or {}).items():
            out[name] = _check(name, value, source)
        return cls(out)

    def with_overrides(self, items: list[str] | None, source: str = "--randomize") -> "Randomize":
        """A copy with ``NAME=VALUE`` strings applied (VALUE: a number, ``lo:hi``, or for the
        choices a comma-separated list)."""
        out = dict(self.settings)
        for item in items or []:
            name, sep, text = item.partition("=")
            name = name.strip()
            if not sep or not text.strip():
                raise RandomizeError(f"{source} {item!r}: expected NAME=VALUE")
            out[name] = _check(name, parse_value(name, text, source), source)
        return Randomize(out)

    def with_settings(self, settings: Mapping[str, Any], source: str = "--param") -> "Randomize":
        """A copy with ``settings`` (name -> a number, a (lo, hi) range or choices) checked
        and applied."""
        out = dict(self.settings)
        for name, value in settings.items():
            out[name] = _check(name, value, source)
        return Randomize(out)

    def draw(self, seed: int) -> dict[str, Any]:
        """The values of episode ``seed`` (in a fixed order, from its own random stream)."""
        rng = np.random.default_rng([int(seed), SEED_SALT])
        out: dict[str, Any] = {}
        for name in NAMES:
            u = rng.random()     # drawn for every name, so one setting never shifts another
            if name not in self.settings:
                continue
            v = self.settings[name]
            if name in CHOICES:
                choices = v if isinstance(v, tuple) else (v,)
                out[name] = choices[min(int(u * len(choices)), len(choices) - 1)]
            elif isinstance(v, tuple):
                out[name] = round(float(v[0] + u * (v[1] - v[0])), 6)
            else:
                out[name] = float(v)
        return out


def parse_value(name: str, text: str, source: str = "--randomize") -> Any:
    """A command-line value of setting ``name``: a number, ``lo:hi`` or a list of choices."""
    text = text.strip()
    try:
        if name in CHOICES:
            items = [t.strip() for t in text.split(",") if t.strip()]
            values = tuple(int(t) if name == "cameras" else t for t in items)
            return values if len(values) > 1 else values[0]
        if ":" in text:
            lo, hi = text.split(":", 1)
            return (float(lo), float(hi))
        return float(text)
    except ValueError:
        raise RandomizeError(f"{source} {name}={text!r}: not a number, lo:hi range or list") from None


def _check(name: str, value: Any, source: str) -> Any:
    if name not in NAMES:
        raise RandomizeError(f"{source}: unknown setting {name!r} (known: {', '.join(NAMES)})")
    if name in CHOICES:
        values = tuple(value) if isinstance(value, (list, tuple)) else (value,)
        if not values or any(v not in CHOICES[name] for v in values):
            raise RandomizeError(f"{source}: {name} must be one of {CHOICES[name]}, got {value!r}")
        return values if len(values) > 1 else values[0]
    if isinstance(value, (list, tuple)):
        if len(value) != 2:
            raise RandomizeError(f"{source}: {name} must be a number or a [lo, hi] range, got {value!r}")
        lo, hi = (_number(name, v, source) for v in value)
        if hi < lo:
            raise RandomizeError(f"{source}: {name} range [{lo}, {hi}] is reversed")
        _in_limits(name, lo, source)
        _in_limits(name, hi, source)
        return (lo, hi)
    v = _number(name, value, source)
    _in_limits(name, v, source)
    return v


def _number(name: str, value: Any, source: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise RandomizeError(f"{source}: {name} must be a finite number, got {value!r}")
    return float(value)


def _in_limits(name: str, v: float, source: str) -> None:
    lo, hi = LIMITS[name]
    if not lo <= v <= hi:
        raise RandomizeError(f"{source}: {name} = {v:g} is outside [{lo:g}, {hi:g}]")


# ------------------------------------------------------------------------- applying them

def apply_to_config(cfg: Any, drawn: Mapping[str, Any], seed: int) -> Any:
    """The cell config with the drawn tape dimensions, stiffness and colour (episode ``seed``
    turns the colour's jitter)."""
    t = cfg.tape
    changes: dict[str, Any] = {}
    if "tape_width_mm" in drawn:
        changes["width"] = drawn["tape_width_mm"] * 1e-3
    if "tape_length_mm" in drawn:
        changes["length"] = drawn["tape_length_mm"] * 1e-3
    if "tape_thickness_mm" in drawn:
        changes["thickness"] = drawn["tape_thickness_mm"] * 1e-3
    if "tape_stiffness_scale" in drawn:
        k = drawn["tape_stiffness_scale"]
        changes.update(flat_bend_stiffness=t.flat_bend_stiffness * k, twist_stiffness=t.twist_stiffness * k,
                       edge_bend_stiffness=t.edge_bend_stiffness * k)
    if "tape_rgb_jitter" in drawn:
        rng = np.random.default_rng([int(seed), SEED_SALT, 1])
        j = drawn["tape_rgb_jitter"] * rng.uniform(-1, 1, 3)
        rgb = np.clip(np.asarray(t.rgba[:3], float) + j, 0.0, 1.0)
        changes["rgba"] = (*[float(c) for c in rgb], float(t.rgba[3]))
    return dataclasses.replace(cfg, tape=dataclasses.replace(t, **changes)) if changes else cfg


def apply_to_model(model: Any, drawn: Mapping[str, Any]) -> None:
    """Set the drawn light on a compiled MuJoCo model of the cell (its "key" light and the
    headlight's ambient)."""
    key = model.light("key")
    if "light_azimuth_deg" in drawn or "light_elevation_deg" in drawn:
        d0 = -np.asarray(key.dir, float)
        az = np.radians(drawn.get("light_azimuth_deg", np.degrees(np.arctan2(d0[1], d0[0]))))
        el = np.radians(drawn.get("light_elevation_deg", np.degrees(np.arcsin(np.clip(d0[2], -1, 1)))))
        toward_light = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        key.dir[:] = -toward_light
    if "light_intensity" in drawn:
        key.diffuse[:] = drawn["light_intensity"]
    if "ambient" in drawn:
        model.vis.headlight.ambient[:] = drawn["ambient"]


def apply_to_capture(capture: Capture, drawn: Mapping[str, Any], seed: int) -> Capture:
    """The capture as the estimator gets it: cameras with the drawn calibration error, masks
    with segmentation noise (when drawn). The truth and the scene stay true."""
    rot, trans = drawn.get("calib_rot_deg", 0.0), drawn.get("calib_trans_mm", 0.0)
    noise = drawn.get("mask_noise", 0.0)
    if not rot and not trans and not noise:
        return capture
    rng = np.random.default_rng([int(seed), SEED_SALT, 2])
    noisy = rng.random() < noise
    views = []
    for v in capture.views:
        cam = v.camera
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        if rot or trans:
            dR = cv2.Rodrigues(axis * np.radians(rot))[0]
            center = cam.center + direction * trans * 1e-3
            R = dR @ cam.R
            cam = cam.with_pose(R, -R @ center)
        mask = roughen(v.mask, rng) if noisy else v.mask
        views.append(View(cam, mask, v.ignore, v.image))
    return dataclasses.replace(capture, views=views)
