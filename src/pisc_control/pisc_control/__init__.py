"""PISC controllers: estimator, swing-up, catch, switching supervisor, PI current loop.

Pure numpy cores that broadcast over any leading shape, and one rclpy shell per node
(``*_node.py``).
"""

__all__ = ["catch", "current_loop", "estimator", "supervisor", "swing_up"]
