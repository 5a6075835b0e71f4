"""The library's named choices and evaluation seeds, in a module that imports nothing.

The components that take these values import them from here, and so does the recipes' config
check (``recipes/schema.py``), which runs before torch is imported: one definition for both.
"""

__all__ = [
    "BC_FILTERS", "COLLISION_TYPES", "DEFAULT_TEST_SEED", "DEFAULT_VALIDATION_SEED", "DEMO_ROWS",
    "GP_EXPLORATION_MODES", "GUARDS", "HER_STRATEGIES", "INSERT_NODES", "SEARCH_METHODS",
]

# CollisionHandling: 0 ends the episode, 1 puts the arm back and drops the step, 2 puts it back and keeps it
COLLISION_TYPES = (0, 1, 2)
# plan_demonstrations / ExperienceRoadmap.search: Dijkstra on the roadmap, or its greedy descent
SEARCH_METHODS = ("exact", "greedy")
# plan_demonstrations: how an edge longer than one action is cut into steps (equal ones, or by halving)
INSERT_NODES = ("equal", "halving")
# SILPLoss: which demonstration rows the BC term keeps
BC_FILTERS = ("reward", "q", "none")
# SILPLoss: how the BC term takes the demonstration rows of a batch
DEMO_ROWS = ("select", "mask")
# GoalRelabelingReplayBuffer: the values of torchrl.data.replay_buffers.her.HindsightStrategy
HER_STRATEGIES = ("future", "final", "episode", "random")
# GPGuidedExploration.mode
GP_EXPLORATION_MODES = ("gp", "random")
# compile_kwargs(guards=...): what a compiled function re-checks on each call
GUARDS = ("all", "inputs")

DEFAULT_TEST_SEED = 20231101  # the 1000 test tasks every recipe and baseline reports on
# the tasks to tune and to stop on (same distribution, other draws): the test tasks are read once, for the figure reported
DEFAULT_VALIDATION_SEED = 31415926
