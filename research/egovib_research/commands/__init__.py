"""The `egovib` commands of the repository (bench, demo, figures, gap validate, live-bench,
real): each module's register(subparsers) adds one, as egovib_ros.cli's command modules
do. research/pyproject.toml names them in the entry-point group `egovib.commands`, each
entry point named for the command line it adds ("gap validate": under `egovib gap`)."""
