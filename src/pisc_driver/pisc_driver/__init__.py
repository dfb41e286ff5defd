"""PISC serial driver for the PIC16F877A rig.

Only the package skeleton exists so far; the frame codec, transport and driver node
are issue 3.
"""

__all__: list[str] = []
