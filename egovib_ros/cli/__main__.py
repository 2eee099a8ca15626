"""`python -m egovib_ros.cli`: the egovib console script."""

from egovib_ros.cli import main

raise SystemExit(main())
