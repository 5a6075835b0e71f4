"""Replay buffers: the planner-backed demonstration buffer and the mixed demo / interaction sampler."""

from torchrl_silp.data.demo_buffer import TRANSITION_KEYS, DemoReplayBuffer, MixedReplay

__all__ = ["DemoReplayBuffer", "MixedReplay", "TRANSITION_KEYS"]
