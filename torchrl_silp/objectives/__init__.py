"""Losses: the SILP+ objective wrapping an actor-critic loss."""

from torchrl_silp.objectives.silp import BC_FILTERS, DEMO_ROWS, SILPLoss

__all__ = ["SILPLoss", "BC_FILTERS", "DEMO_ROWS"]
