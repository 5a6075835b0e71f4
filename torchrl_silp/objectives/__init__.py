"""Losses: the SILP+ objective wrapping an actor-critic loss."""

from torchrl_silp.objectives.silp import BC_FILTERS, SILPLoss

__all__ = ["SILPLoss", "BC_FILTERS"]
