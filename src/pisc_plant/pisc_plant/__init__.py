"""The PISC rig simulator: cart-pole with pendulum inertia, DC motor, sensors, end stops.

Pure numpy cores (:mod:`.dynamics`, :mod:`.motor`, :mod:`.sensors`,
:mod:`.integrators`, :mod:`.plant`) and the rclpy shell :mod:`.plant_node`.
"""

__all__ = ["dynamics", "integrators", "motor", "params", "plant", "sensors"]
