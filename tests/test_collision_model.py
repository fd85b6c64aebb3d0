"""The collision check's wrist model against the simulated UR5e's own geometry: MuJoCo's
distances from the wrist's geoms to the part, at random flange poses near the part."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from tapecell.cell.config import load_cell_config
from tapecell.cell.kinematics import dh_frames, ik_nearest
from tapecell.cell.safety import WRIST_LINKS, WRIST_RADIUS_M, SafetyLimits, _cylinder_surface


def test_the_wrist_model_is_never_clear_where_the_simulated_wrist_touches_the_part():
    import mujoco

    from tapecell.sim.cell import SimCell

    cfg = load_cell_config()
    part = next(o for o in SafetyLimits.from_cell(cfg).obstacles if o.name == "part")
    rng = np.random.default_rng(7)
    q0 = np.array([-1.5708, -1.9, 2.2, -1.87, -1.5708, 0.0])
    pairs = []
    with SimCell(cfg, seed=0, n_cameras=2, tool="gripper") as sim:
        m, d = sim.model, sim.data
        part_geom = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "part")
        wrist = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("wrist1_cap", "wrist1", "wrist2", "wrist3")]
        assert min(wrist) >= 0 and part_geom >= 0
        while len(pairs) < 150:
            T = np.eye(4)
            T[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
            T[:3, 3] = [rng.uniform(-0.15, 0.15), rng.uniform(0.35, 0.65), rng.uniform(0.05, 0.3)]
            q = ik_nearest(T, q0)
            if q is None:
                continue
            d.qpos[:6] = q
            mujoco.mj_forward(m, d)
            theirs = min(mujoco.mj_geomDistance(m, d, g, part_geom, 0.3, None) for g in wrist)
            F = dh_frames(q)
            ours = 1.0
            for _, i, j, back in WRIST_LINKS:
                a, b = F[i, :3, 3], F[j, :3, 3]
                a = a - back * (b - a) / np.linalg.norm(b - a)
                ours = min(ours, float(np.min(part.distance(_cylinder_surface(a, b, WRIST_RADIUS_M)))))
            if min(ours, theirs) < 0.05:
                pairs.append((theirs, ours))
    pairs = np.array(pairs)
    # Never clear by the 5 mm clearance where the simulated wrist touches the part ...
    assert not np.any((pairs[:, 0] < 0) & (pairs[:, 1] >= 0.005))
    # ... and never refusing where the simulated wrist is 10 mm clear.
    assert not np.any((pairs[:, 0] >= 0.010) & (pairs[:, 1] < 0.005))
    both = (pairs[:, 0] > 0) & (pairs[:, 1] > 0)
    assert abs(np.median(pairs[both, 1] - pairs[both, 0])) < 0.004
