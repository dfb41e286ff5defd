"""Bringing the PISC graph up: launch files and their reader, the graph runner, the DDS
profile, replay through the nodes, and the ``pisc_bag`` command."""
