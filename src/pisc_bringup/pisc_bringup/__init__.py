"""Running the PISC graph: parameter files, the graph runner, the recorder, run summaries."""

__all__ = ["closed_loop", "graph", "recorder", "summary"]
