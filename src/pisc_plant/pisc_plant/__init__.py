"""The PISC rig simulator: cart-pole with pendulum inertia, DC motor, sensors, end stops.

Pure numpy cores (:mod:`.dynamics`, :mod:`.motor`, :mod:`.sensors`,
:mod:`.integrators`, :mod:`.plant`), the rclpy shell :mod:`.plant_node`, and the
virtual rig :mod:`.virtual_rig` (the plant behind a pseudo-terminal, speaking the PIC's
serial protocol).
"""

__all__ = ["dynamics", "integrators", "motor", "params", "plant", "sensors"]
