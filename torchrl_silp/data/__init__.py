"""Replay buffers and episode handling: the planner-backed demonstration buffer, the mixed demo / interaction
sampler, hindsight relabelling, and the assembly of episodes that span collector batches."""

from torchrl_silp.data.demo_buffer import TRANSITION_KEYS, DemoReplayBuffer, MixedReplay, transition_keys
from torchrl_silp.data.episodes import EpisodeAssembler, cut_episodes
from torchrl_silp.data.her import HER_STRATEGIES, GoalRelabelingReplayBuffer
from torchrl_silp.data.storage import FilledStorageCheckpointer

__all__ = [
    "DemoReplayBuffer",
    "MixedReplay",
    "GoalRelabelingReplayBuffer",
    "EpisodeAssembler",
    "cut_episodes",
    "HER_STRATEGIES",
    "TRANSITION_KEYS",
    "transition_keys",
    "FilledStorageCheckpointer",
]
