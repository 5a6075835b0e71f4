"""SAC-SILP+: train a neural motion planner for the UR5e reach task (the main job).

    python recipes/sac_silp.py                      # the default config
    python recipes/sac_silp.py seed=1 resume=true   # continue a killed run
    python recipes/sac_silp.py silp.demos=false silp.bc=false exploration.mode=none  # plain SAC

Builders live in ``recipes/utils.py``, the loop in ``recipes/loop.py``, the
configuration in ``recipes/config/sac_silp.yaml``.
"""

import sys
from pathlib import Path

import hydra

sys.path.insert(0, str(Path(__file__).parent))
from loop import train  # noqa: E402


@hydra.main(version_base="1.3", config_path="config", config_name="sac_silp")
def main(cfg):
    return train(cfg)


if __name__ == "__main__":
    main()
