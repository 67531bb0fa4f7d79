"""What the mse rule's filter holds at once: the joint (N n x N n) matrices of its runs (the memory estimate reads it
beside the filter, :meth:`designer.rule.GainRule.memory_parts`)."""

__all__ = ["MEMORY_BUDGET", "JOINT_COPIES"]

MEMORY_BUDGET = 2**28  # bytes of joint (N n x N n) matrices its filter holds at once by one sub-batch of runs
JOINT_COPIES = 24  # joint matrices alive at once per run (covariance, certificate, predictions, T, eigenvectors, ...)
