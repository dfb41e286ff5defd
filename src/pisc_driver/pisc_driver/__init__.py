"""PISC serial driver for the PIC16F877A rig (SPEC section 4).

``protocol`` (frame codec and lock-hunting parser, pure), ``link`` (the serial port,
pyserial), ``driver`` (the driver's decisions, pure), ``driver_node`` (the rclpy shell).
The parser's benchmark, which needs the simulator, is ``pisc_bench.parser_bench``
(``pisc_parser_bench``): a rig computer with the driver does not install the simulator.
"""

__all__ = ["driver", "link", "protocol"]
