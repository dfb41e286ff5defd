"""PISC benchmarks and the soak: the plant's work-precision, the batch, the lockstep graph, the parser, bags, identification, commissioning, and minutes of real time under load."""
