"""Experiments that write docs/: the paper's tables and figures, the simulator's validation,
the gap diagnosis's blind validation, the real quadcopter flights."""
