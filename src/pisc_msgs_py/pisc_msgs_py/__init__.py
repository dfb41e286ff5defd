"""PISC's shared interface layer.

Topic names, QoS and message types (:mod:`.topics`), typed values (:mod:`.types`),
message converters (:mod:`.convert`), the parameter schema (:mod:`.config`) and the
base of every node (:mod:`.base_node`, the only module here that imports rclpy).
"""

__all__ = ["config", "convert", "topics", "types"]
