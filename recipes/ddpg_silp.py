"""DDPG-SILP+: the SILP+ recipe over DDPGLoss, sharing every builder with sac_silp.py.

    python recipes/ddpg_silp.py                      # the default config
    python recipes/ddpg_silp.py seed=1 resume=true   # continue a killed run
    python recipes/ddpg_silp.py silp.demos=false silp.bc=false exploration.mode=none  # plain DDPG

Builders live in ``recipes/utils.py``, the loop in ``recipes/loop.py``, the
configuration in ``recipes/config/ddpg_silp.yaml`` (on top of ``sac_silp.yaml``).
"""

import sys
from pathlib import Path

import hydra

sys.path.insert(0, str(Path(__file__).parent))
from loop import train  # noqa: E402


@hydra.main(version_base="1.3", config_path="config", config_name="ddpg_silp")
def main(cfg):
    return train(cfg)


if __name__ == "__main__":
    main()
