"""The PISC rig's model, without ROS and without the simulator: its parameters
(:mod:`.params`: thesis Table 6.1 and every section a node reads), the cart-pole's
mechanics with pendulum inertia (:mod:`.dynamics`: accelerations, energy (2.54), the
linearisation at upright), the DC motor (:mod:`.motor`) and the sensors' conversions
(:mod:`.sensors`, SPEC section 4).

The controllers, the serial driver and the simulator all build on this package; none of
it imports rclpy, numba or the simulator.
"""

__all__ = ["dynamics", "motor", "params", "sensors"]
