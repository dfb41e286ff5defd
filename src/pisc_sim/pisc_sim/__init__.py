"""The PISC rig simulated without ROS: the named configurations and their loading
(:mod:`.configuration`; the parameter files in ``config/``), scenes (:mod:`.scene`;
``scenes/``), and the closed loop of the plant and the controllers' cores, one rig or a
batch (:mod:`.closed_loop`), which the graph reproduces bit for bit.

The analysis, the robustness benchmark and the graph runner build on it; it imports no
rclpy and no launch package.
"""

__all__ = ["closed_loop", "configuration", "scene"]
