"""DDPG-SILP+: the main job's recipe over DDPGLoss (``config/ddpg_silp.yaml``).

    python recipes/ddpg_silp.py
"""

import hydra

from torchrl_silp.recipes.sac_silp import train


@hydra.main(version_base="1.3", config_path="config", config_name="ddpg_silp")
def main(cfg):
    return train(cfg)


if __name__ == "__main__":
    main()
