"""The estimator's output pinned on captures the project makes itself (sample_like 0-3):
tip, nodes and cost to 1e-9, and the verdict. A change that moves them must say so (and
regenerate tests/data/golden_estimates.json on purpose); a restructure must not."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tapecell.estimator import estimate
from tapecell.estimator.synthetic import sample_like

GOLDEN = json.loads((Path(__file__).parent / "data" / "golden_estimates.json").read_text())


@pytest.mark.parametrize("seed", sorted(GOLDEN, key=int))
def test_estimate_is_pinned(seed):
    est = estimate(sample_like(int(seed)))
    want = GOLDEN[seed]
    assert np.allclose(est.tip_position, want["tip"], atol=1e-9, rtol=0)
    assert np.allclose(est.nodes, want["nodes"], atol=1e-9, rtol=0)
    assert est.cost == pytest.approx(want["cost"], abs=1e-9)
    assert est.verdict.value == want["verdict"]
