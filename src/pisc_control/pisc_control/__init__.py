"""PISC controllers: estimator, swing-up, catch, switching supervisor, PI current loop.

Each law written once, on floats for one rig (run as it is by the nodes, compiled by
numba for the batch, applied element by element to arrays), and one rclpy shell per
node (``*_node.py``).
"""

__all__ = ["adaptation", "catch", "current_loop", "estimator", "excitation", "floatmath",
           "supervisor", "swing_up"]
