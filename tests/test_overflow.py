"""Numbers that overflow end in a clean refusal or an honest, JSON-valid result, never in an internal error."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from designer.validation import InputError
from designer.verdict import verdict

WRAP = '''"""Two angles, the second multiplied by 1e8 a step (wrapped): the state stays finite, the second is never
measured and its covariance overflows within a few steps."""
import casadi as ca
import numpy as np
from designer import AttackSpec, Gaussian, Model, Sensor, SensorNetwork

STEPS = 30
NETWORK = SensorNetwork.from_edges(2, [(0, 1)])
ATTACKS = AttackSpec(dos=0.2, fdi=0.0)


def model():
    x = ca.SX.sym("x", 2)
    sensors = [Sensor(f"s{i}", x[0], Gaussian.zero_mean([[1.0]])) for i in range(2)]
    f = ca.vertcat(ca.fmod(5 * x[0], 2 * np.pi), ca.fmod(1e8 * x[1], 2 * np.pi))
    return Model("wrap", x, f, sensors, Gaussian.zero_mean(np.diag([0.01, 0.01])),
                 Gaussian([0.1, 0.2], np.diag([0.1, 0.1])))
'''


def _finite_json(x) -> bool:
    if isinstance(x, dict):
        return all(_finite_json(v) for v in x.values())
    if isinstance(x, list):
        return all(_finite_json(v) for v in x)
    return not isinstance(x, float) or math.isfinite(x)


def test_a_state_that_overflows_at_the_first_step_is_named():
    """switching-2d with F of 1e308: the first state leaves the reals (it used to end in 'cannot reshape')."""
    import studies

    with pytest.raises(InputError, match=r"the transition f is not finite at step 1: f\(x\) from x = \["):
        studies.simulate("switching-2d", steps=5, assignments=["F=[[1e308,1e308],[1e308,1e308]]"])


def test_a_scheduled_design_whose_covariance_overflows_writes_valid_json(tmp_path):
    """The trade-off's expected RMSE of a covariance that overflowed is null; schedule.json parses with NaN and
    infinity refused and validates against its schema."""
    import studies
    from studies.schemas import validate

    path = tmp_path / "wrap.py"
    path.write_text(WRAP)
    res = studies.design(str(path), mode="scheduled", steps=30, out=tmp_path / "d")
    text = (tmp_path / "d" / "schedule.json").read_text()
    rec = json.loads(text, parse_constant=lambda c: pytest.fail(f"schedule.json holds {c}"))
    assert _finite_json(rec)
    assert rec["verdict"] == res.verdict == "infeasible" and not rec["feasible"]  # the bound left any meaning
    assert any(r["expected_rmse"] is None for r in rec["rounds_tradeoff"]["rows"])
    validate("schedule", rec)


def test_a_bound_that_overflows_is_vacuous_from_the_step_it_stopped_being_finite():
    """A feasible bound finite until step 3, infinite after (before the judged last 2 W = 4 steps): vacuous, naming
    step 3, and its numbers JSON-valid."""
    trace = np.array([[1.0, 2.0, np.inf, np.inf, np.inf, np.inf, np.inf, np.inf], [1.0] * 8])
    v = verdict(trace, np.full(8, 10.0), feasible=True)
    assert v.verdict == "vacuous" and v.nodes == [0]
    assert "node 0's tr Φ is not finite from step 3 on" in v.reason
    assert _finite_json(v.detail) and json.dumps(v.detail, allow_nan=False)
