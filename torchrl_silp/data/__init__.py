"""Replay buffers: the planner-backed demonstration buffer, the mixed demo / interaction sampler, hindsight relabelling."""

from torchrl_silp.data.demo_buffer import TRANSITION_KEYS, DemoReplayBuffer, MixedReplay
from torchrl_silp.data.her import HER_STRATEGIES, GoalRelabelingReplayBuffer

__all__ = ["DemoReplayBuffer", "MixedReplay", "GoalRelabelingReplayBuffer", "HER_STRATEGIES", "TRANSITION_KEYS"]
