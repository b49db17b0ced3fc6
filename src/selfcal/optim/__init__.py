"""Shared numerical optimisation: the one Levenberg-Marquardt driver (:mod:`selfcal.optim.lm`)."""

from .lm import LeastSquaresResult, Model, irls, levenberg_marquardt, levenberg_marquardt_batch

__all__ = ["LeastSquaresResult", "Model", "irls", "levenberg_marquardt", "levenberg_marquardt_batch"]
