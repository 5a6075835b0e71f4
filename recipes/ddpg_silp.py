"""DDPG-SILP+: the main job's recipe over DDPGLoss (``config/ddpg_silp.yaml``).

    python recipes/ddpg_silp.py
"""

import sys
from pathlib import Path

import hydra

sys.path.insert(0, str(Path(__file__).parent))
from sac_silp import train  # noqa: E402


@hydra.main(version_base="1.3", config_path="config", config_name="ddpg_silp")
def main(cfg):
    return train(cfg)


if __name__ == "__main__":
    main()
