"""Transfer to physics: the MuJoCo twin of a reach task and closed-loop execution of a policy on it (extra ``sim``)."""

from torchrl_silp.sim.transfer import NOISE_LEVELS, SCENARIOS, Perception, reaching_trials, run_transfer, scenario_tasks
from torchrl_silp.sim.twin import MujocoTwin, ServoGains, mujoco_labels

__all__ = ["MujocoTwin", "ServoGains", "mujoco_labels", "Perception", "NOISE_LEVELS", "SCENARIOS", "scenario_tasks",
           "reaching_trials", "run_transfer"]
