from torchrl_silp.sim.twin import MujocoTwin, ServoGains

__all__ = ["MujocoTwin", "ServoGains"]
