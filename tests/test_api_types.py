"""Wrong types at the public API and the public constructors: InputError naming the parameter, before any work.

Each row is a call a design script might make by mistake (a string for a number, a list for a seed, a dict for
an options object, a number for a path, None for a required argument, a float for a count, a tuple of values for
a grid, ...); each must raise :class:`designer.InputError` (the CLI's exit 2) whose message names the parameter,
not a ``TypeError`` or ``AttributeError`` from deep inside, and nothing may be written.
"""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import studies
from designer import (AttackSpec, DesignOptions, FDISignal, Gaussian, GaussianMixture, InputError, Model,
                      PolarVelocityPrior, Sensor, SensorNetwork, TruncatedGaussian, UniformBox)

_X = ca.SX.sym("x", 2)
_NOISE = Gaussian.zero_mean([[0.05]])
_SENSORS = [Sensor(f"s{i}", _X[0] + 0.1 * i * _X[1], _NOISE) for i in range(2)]
_NET = SensorNetwork.from_edges(2, [(0, 1)])
_F = ca.vertcat(_X[0] + 0.1 * _X[1], 0.9 * _X[1])


def _model(**kw):
    args = dict(name="two", x=_X, f=_F, sensors=_SENSORS, process_noise=Gaussian.zero_mean(1e-3 * np.eye(2)),
                prior=Gaussian([0.0, 1.0], 0.1 * np.eye(2)))
    args.update(kw)
    return Model(args.pop("name"), args.pop("x"), args.pop("f"), args.pop("sensors"), **args)


_M = _model()

# (call, the parameter's name as the message must give it)
CASES = {
    # studies.simulate
    "simulate: steps a string": (lambda: studies.simulate(_M, network=_NET, steps="10"), "steps"),
    "simulate: seed a list": (lambda: studies.simulate(_M, network=_NET, steps=3, seed=[1]), "seed"),
    "simulate: out a number": (lambda: studies.simulate(_M, network=_NET, steps=3, out=5), "out"),
    "simulate: scenario None": (lambda: studies.simulate(None), "scenario"),
    "simulate: overrides a list": (lambda: studies.simulate("indoor-robot", overrides=["process_var"]),
                                   "overrides"),
    "simulate: assignments one string": (lambda: studies.simulate("indoor-robot", assignments="process_var=1"),
                                         "assignments"),
    "simulate: network a string": (lambda: studies.simulate(_M, network="ring", steps=3), "network"),
    "simulate: attacks a dict": (lambda: studies.simulate(_M, network=_NET, attacks={"dos": 0.1}), "attacks"),
    "simulate: inputs a number": (lambda: studies.simulate(_M, network=_NET, inputs=3), "inputs"),
    "simulate: x0 a string": (lambda: studies.simulate(_M, network=_NET, steps=3, x0="zero"), "x0"),
    # studies.design
    "design: options a dict": (lambda: studies.design(_M, network=_NET, options={"mode": "paper"}), "options"),
    "design: steps a float": (lambda: studies.design(_M, network=_NET, steps=3.0), "steps"),
    "design: seed a string": (lambda: studies.design(_M, network=_NET, seed="1"), "seed"),
    "design: epsilon a string": (lambda: studies.design(_M, network=_NET, epsilon="0.1"), "epsilon"),
    "design: mode a number": (lambda: studies.design(_M, network=_NET, mode=1), "mode"),
    "design: out a number": (lambda: studies.design(_M, network=_NET, out=7), "out"),
    "design: design_defaults a dict": (lambda: studies.design(_M, network=_NET, design_defaults={"mode": "paper"}),
                                       "design_defaults"),
    # studies.feasibility
    "feasibility: grid a tuple of values": (lambda: studies.feasibility(_M, ("dos", 0, 0.5, 3), network=_NET),
                                            "grid"),
    "feasibility: grid None": (lambda: studies.feasibility(_M, None, network=_NET), "grid"),
    "feasibility: workers a float": (lambda: studies.feasibility(_M, "dos=0:0.5:2", network=_NET, workers=2.0),
                                     "workers"),
    "feasibility: force a string": (lambda: studies.feasibility(_M, "dos=0:0.5:2", network=_NET, force="yes"),
                                    "force"),
    "feasibility: quiet a string": (lambda: studies.feasibility(_M, "dos=0:0.5:2", network=_NET, quiet="no"),
                                    "quiet"),
    "feasibility: dask a number": (lambda: studies.feasibility(_M, "dos=0:0.5:2", network=_NET, dask=8786),
                                   "dask"),
    "feasibility: backend a string": (lambda: studies.feasibility(_M, "dos=0:0.5:2", network=_NET,
                                                                  backend="processes"), "backend"),
    "feasibility: out a number": (lambda: studies.feasibility(_M, "dos=0:0.5:2", network=_NET, out=3.5), "out"),
    # studies.study
    "study: name None": (lambda: studies.study(None), "name"),
    "study: runs a string": (lambda: studies.study("comparison", runs="4"), "runs"),
    "study: particles a float": (lambda: studies.study("comparison", runs=2, particles=50.0), "particles"),
    "study: seed a list": (lambda: studies.study("comparison", runs=2, seed=[4]), "seed"),
    "study: workers a float": (lambda: studies.study("comparison", runs=2, workers=2.0), "workers"),
    "study: options a dict": (lambda: studies.study("comparison", runs=2, options={"dos": 0.1}), "options"),
    "study: out a number": (lambda: studies.study("comparison", runs=2, out=1), "out"),
    "study: force a string": (lambda: studies.study("comparison", runs=2, force="no"), "force"),
    "study: overrides a list": (lambda: studies.study("comparison", runs=2, overrides=[("dos_prob", 0.1)]),
                                "overrides"),
    "study: scenario a number": (lambda: studies.study("comparison", 3, runs=2), "scenario"),
    # studies.report
    "report: directory None": (lambda: studies.report(None), "directory"),
    "report: directory a number": (lambda: studies.report(3), "directory"),
    # the constructors a design script calls
    "Model: name a number": (lambda: _model(name=3), "name"),
    "Model: sensors None": (lambda: _model(sensors=None), "sensors"),
    "Model: sensors one Sensor": (lambda: _model(sensors=_SENSORS[0]), "sensors"),
    "Model: prior a list": (lambda: _model(prior=[0.0, 1.0]), "prior"),
    "Model: process_noise a matrix": (lambda: _model(process_noise=np.eye(2)), "process_noise"),
    "Sensor: noise a matrix": (lambda: Sensor("a", _X[0], np.eye(1)), "noise"),
    "Sensor: h a string": (lambda: Sensor("a", "x[0]", _NOISE), "h"),
    "Sensor: name a number": (lambda: Sensor(1, _X[0], _NOISE), "name"),
    "SensorNetwork: n_nodes a string": (lambda: SensorNetwork("2", np.ones((2, 2)) - np.eye(2)), "n_nodes"),
    "SensorNetwork.from_edges: edges None": (lambda: SensorNetwork.from_edges(2, None), "edges"),
    "SensorNetwork.from_edges: n_nodes a float": (lambda: SensorNetwork.from_edges(2.0, [(0, 1)]), "n_nodes"),
    "AttackSpec: dos a string": (lambda: AttackSpec(dos="0.1"), "dos"),
    "AttackSpec: signal a dict": (lambda: AttackSpec(signal={"amplitude": 1.0}), "signal"),
    "AttackSpec: delta a string": (lambda: AttackSpec(delta="1"), "delta"),
    "FDISignal: amplitude a string": (lambda: FDISignal(amplitude="big"), "amplitude"),
    "FDISignal: components a string": (lambda: FDISignal(amplitude=1.0, components="x"), "components"),
    "DesignOptions: epsilon a string": (lambda: DesignOptions(epsilon="0.1"), "epsilon"),
    "DesignOptions: sigma a list": (lambda: DesignOptions(sigma=[0.1]), "sigma"),
    "DesignOptions: gate a string": (lambda: DesignOptions(gate="0.1"), "gate"),
    "Gaussian: cov None": (lambda: Gaussian([0.0], None), "cov"),
    "Gaussian.zero_mean: cov None": (lambda: Gaussian.zero_mean(None), "cov"),
    "Gaussian: mean a string": (lambda: Gaussian("0", [[1.0]]), "mean"),
    "GaussianMixture: components None": (lambda: GaussianMixture([1.0], None), "components"),
    "TruncatedGaussian: lower a string": (lambda: TruncatedGaussian([0.0], [1.0], "a", 1.0), "lower"),
    "UniformBox: lower None": (lambda: UniformBox(None, [1.0]), "lower"),
    "PolarVelocityPrior: position_mean a string": (lambda: PolarVelocityPrior("a", np.eye(2), 1.0, 0.1, 0.0, 0.1),
                                                   "position_mean"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_wrong_type_is_an_input_error_naming_the_parameter(case, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # nothing may be written, not even in the current directory
    call, name = CASES[case]
    with pytest.raises(InputError) as exc:
        call()
    assert name in str(exc.value), str(exc.value)
    assert not list(tmp_path.iterdir())


def test_the_table_is_large_enough():
    assert len(CASES) >= 30
    functions = {case.split(":")[0] for case in CASES}
    assert {"simulate", "design", "feasibility", "study", "report", "Model", "Sensor", "SensorNetwork",
            "AttackSpec", "FDISignal", "DesignOptions", "Gaussian"} <= functions
