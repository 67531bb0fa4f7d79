"""A short design script: load a built-in scenario, inspect its linearisation, simulate it.

Run: ``python examples/design_script.py``
"""
import numpy as np

from studies.scenarios import load_scenario

sc = load_scenario("indoor-robot", {"dos_prob": 0.2})  # override a named parameter
model, net = sc.model, sc.network
print(model, "| network degrees", net.degrees.tolist(), "d_max", net.d_max)

# Jacobians by CasADi automatic differentiation, at the initial pose.
u0 = sc.inputs(1)[0]
F = model.F(sc.x0, 0, u0)
H = [model.H(i, sc.x0) for i in range(model.n_sensors)]
print("F =\n", F.round(4))
print("rank of the stacked camera Jacobians:", np.linalg.matrix_rank(np.vstack(H)))

# Batched evaluation over 10^4 particles drawn from the prior.
rng = np.random.default_rng(2026)
particles = model.prior.sample(rng, 10_000)
print("h_all over particles:", model.h_all(particles).shape)

# A seeded simulation of the scenario.
run = sc.simulate(np.random.default_rng(7))
print("final true pose", run.x[-1].round(3), "measurements", run.z.shape)
