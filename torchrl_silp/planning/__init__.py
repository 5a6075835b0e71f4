"""Experience-based planning (SILP+, sec. 3.2-3.3).

A roadmap over the collision-free states of each episode
(:class:`ExperienceRoadmap`), batched graph search on it (:mod:`.search`) and
the conversion of planned paths to MDP demonstrations with InsertNodes
(:func:`plan_demonstrations`).
"""

from torchrl_silp.planning.demos import paths_to_demonstrations, plan_demonstrations
from torchrl_silp.planning.roadmap import ExperienceRoadmap, split_episodes
from torchrl_silp.planning.search import (
    SEARCH_METHODS,
    Paths,
    all_pairs_distances,
    astar_paths,
    greedy_paths,
    roadmap_paths,
    shortest_paths,
)

__all__ = [
    "ExperienceRoadmap",
    "plan_demonstrations",
    "paths_to_demonstrations",
    "split_episodes",
    "Paths",
    "SEARCH_METHODS",
    "all_pairs_distances",
    "shortest_paths",
    "astar_paths",
    "greedy_paths",
    "roadmap_paths",
]
