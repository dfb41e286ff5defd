"""PISC serial driver for the PIC16F877A rig (SPEC section 4).

``protocol`` (frame codec and lock-hunting parser, pure), ``link`` (the serial port,
pyserial), ``driver`` (the driver's decisions, pure), ``driver_node`` (the rclpy shell),
``bench`` (``pisc_parser_bench``).
"""

__all__ = ["driver", "link", "protocol"]
