"""The paper's estimator (sec. 2.3, 3.1, 3.2, 4.1), reproduced as the reference.

* Cost: XOR of model and object silhouettes over the whole image, normalised by the
  object's area (eq. 5-7), views combined by eq. 11.
* Downhill simplex (Nelder-Mead) with the initial simplex V_i = V_0 + λ_i e_i (eq. 9).
* Sequential optimisation (sec. 3.1): the three angles of node P_i are optimised at a
  time, from P_1 to P_n; the model image holds plate i alone and the object image has
  the region explained by the plates fitted before it deleted (Fig. 3).
* One re-calculation (sec. 4.1): the whole sequential pass runs again with every node's
  simplex re-initialised by eq. 9 around the claimed minimum.

Nothing here is tuned beyond the paper: the initial guess is the flat straight tape and
λ is one fixed step for all angles.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.optimize import minimize

from .capture import Capture
from .silhouette import CostEvaluator, make_target, project_quads, render
from .tape import forward_kinematics, joint_rotations

LAMBDA_RAD = 0.3
"""Step λ_i of the initial simplex (eq. 9) for every angle [rad]."""
PASSES = 2
"""The first estimate plus one re-initialised re-calculation (sec. 4.1)."""
XATOL_RAD = 1e-3
FATOL = 1e-4
MAX_ITER_PER_NODE = 300

Callback = Callable[[int, float, np.ndarray], None]


def initial_simplex(v0: np.ndarray, lam: float = LAMBDA_RAD) -> np.ndarray:
    """Eq. 9: the N+1 vertices V_0 and V_i = V_0 + λ e_i, as an (N+1, N) array."""
    v0 = np.asarray(v0, float)
    return np.vstack([v0, v0 + lam * np.eye(v0.size)])


def _plate_quad(spec, frame_prev: np.ndarray, node_prev: np.ndarray, i: int,
                angles_i: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plate i's quad (1, 4, 3) for its angles, given the fixed frame and node before it."""
    frame = frame_prev @ joint_rotations(angles_i)[0]
    node = node_prev + spec.segment_lengths[i] * frame[:, 0]
    h = 0.5 * spec.width
    quad = np.array([[node_prev + h * frame_prev[:, 1], node + h * frame[:, 1],
                      node - h * frame[:, 1], node_prev - h * frame_prev[:, 1]]])
    return quad, frame, node


def fit_paper(capture: Capture, callback: Callback | None = None) -> tuple[np.ndarray, list[float], int]:
    """Fit the chain by the paper's procedure.

    Returns the (n, 3) angles, the objective after each simplex iteration (of the node
    being optimised, as the paper's optimiser sees it), and the number of cost evaluations.
    """
    spec = capture.tape
    n = spec.n
    angles = np.zeros((n, 3))
    history: list[float] = []
    evaluations = 0
    iteration = 0
    for _ in range(PASSES):
        explained = [np.zeros(v.mask.shape, bool) for v in capture.views]
        frame, node = spec.base_rotation, spec.base_position
        for i in range(n):
            # Fig. 3: the object image for node i lacks what plates 1..i-1 explain.
            node_index = i
            targets = [make_target(v, v.mask & ~e) for v, e in zip(capture.views, explained)]
            evaluator = CostEvaluator(targets)

            def objective(x: np.ndarray, i=i, frame=frame, node=node, ev=evaluator) -> float:
                return ev.cost(_plate_quad(spec, frame, node, i, x)[0])

            def on_iteration(intermediate_result) -> None:  # scipy passes the best vertex
                nonlocal iteration
                iteration += 1
                cost = float(intermediate_result.fun)
                history.append(cost)
                if callback is not None:
                    current = angles.copy()
                    current[node_index] = intermediate_result.x
                    callback(iteration, cost, current)

            res = minimize(objective, angles[i], method="Nelder-Mead", callback=on_iteration,
                           options={"initial_simplex": initial_simplex(angles[i]), "xatol": XATOL_RAD,
                                    "fatol": FATOL, "maxiter": MAX_ITER_PER_NODE})
            evaluations += evaluator.evaluations
            angles[i] = res.x
            quad, frame, node = _plate_quad(spec, frame, node, i, res.x)
            for k, v in enumerate(capture.views):
                cam = v.camera
                explained[k] |= render(project_quads(cam, quad), (cam.height, cam.width)).astype(bool)
    return angles, history, evaluations


def final_costs(capture: Capture, angles: np.ndarray) -> np.ndarray:
    """Per-view eq. 7 cost of the whole chain against the whole object images."""
    evaluator = CostEvaluator([make_target(v) for v in capture.views])
    return evaluator.view_costs(forward_kinematics(capture.tape, angles).quads())
