"""The repository's research tools around egovib_ros: the experiments that write docs/, the
benchmarks, the live demo and the node orchestration it and the node tests use, and an
independent PR2-hand generator that validates the gap diagnosis.

Not installed with the robot package: `make venv` installs it into the project's venv
beside egovib_ros (`pip install -e research/`), and its commands join `egovib` through
the entry-point group `egovib.commands` (research/pyproject.toml; commands/). It imports
egovib_ros; egovib_ros never imports it (test/test_layers.py).
"""
