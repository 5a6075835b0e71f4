"""DDPG-SILP+: the main job's recipe over DDPGLoss (``config/ddpg_silp.yaml``).

    python recipes/ddpg_silp.py
"""

if __name__ == "__main__":  # the command line is checked before the recipe is imported
    from torchrl_silp.recipes.preflight import main

    main("ddpg_silp", "torchrl_silp.recipes.sac_silp:train")
