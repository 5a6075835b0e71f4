"""Robot descriptions (URDF), installed as the package ``torchrl_silp.assets``."""
