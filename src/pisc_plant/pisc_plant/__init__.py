"""The PISC rig simulator: the compiled plant kernel (:mod:`.kernel`; its layout,
without numba, :mod:`.layout`), the plant and plant sets (:mod:`.plant`), sampling
(:mod:`.sampled`), the rclpy shell :mod:`.plant_node`, and the virtual rig
:mod:`.virtual_rig` (the plant behind a pseudo-terminal, speaking the PIC's serial
protocol). The model it simulates (parameters, dynamics, motor, sensors) is the package
``pisc_model``.
"""

__all__ = ["kernel", "layout", "plant", "sampled"]
