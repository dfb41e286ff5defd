"""PISC bags: the recorder node and command, MCAP writing, indexing, repair and reading columns."""
