"""PISC's rig as Gymnasium environments: the real motor, sensors and latency, domain
randomisation from PISC's distribution files, and a vector environment on the compiled
kernel. ``import pisc_gym`` registers ``pisc/SwingUp-v0`` and ``pisc/Catch-v0``."""

from gymnasium.envs.registration import register

__all__ = ["ENV_IDS"]

ENV_IDS = {"pisc/SwingUp-v0": "swing_up", "pisc/Catch-v0": "catch"}

for _id, _task in ENV_IDS.items():
    register(id=_id, entry_point="pisc_gym.env:PiscEnv",
             vector_entry_point="pisc_gym.vector:PiscVectorEnv", kwargs={"task": _task})
