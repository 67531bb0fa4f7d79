"""Estimators that consume models from :mod:`designer` (consensus EKF, particle filters)."""
