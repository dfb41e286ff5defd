"""The DDS environment of a PISC run: discovery on this machine, PISC's Fast DDS profile.

pisc_graph gives it to its own nodes and to every process it starts; a variable the
environment sets already is left as it is (the user's own profile or discovery range).
"""

from __future__ import annotations

from collections.abc import MutableMapping

from pisc_msgs_py.config import package_dir

__all__ = ["DISCOVERY_RANGE", "FASTDDS_PROFILE", "FASTDDS_PROFILES", "dds_environment"]

# ROS 2 (Jazzy) discovery range: LOCALHOST, SUBNET (the ROS default), OFF or SYSTEM_DEFAULT
DISCOVERY_RANGE = "ROS_AUTOMATIC_DISCOVERY_RANGE"
# Fast DDS 2.14 (the Jazzy wheels) reads its XML profiles from this variable
# (FASTDDS_DEFAULT_PROFILES_FILE is Fast DDS 3's name; 2.14 does not read it)
FASTDDS_PROFILES = "FASTRTPS_DEFAULT_PROFILES_FILE"
# the profile: reliable writers ask for acknowledgements every 100 ms, not every 3 s
FASTDDS_PROFILE = package_dir("pisc_bringup", "config") / "fastdds.xml"


def dds_environment(env: MutableMapping[str, str]) -> MutableMapping[str, str]:
    """``env`` with discovery on this machine (docs/safety.md) and PISC's Fast DDS
    profile (docs/architecture.md), where it does not say otherwise already."""
    env.setdefault(DISCOVERY_RANGE, "LOCALHOST")
    env.setdefault(FASTDDS_PROFILES, str(FASTDDS_PROFILE))
    return env
