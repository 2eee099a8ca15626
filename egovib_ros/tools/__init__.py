"""Tools around the package: the live demo, benchmarks, node-process orchestration."""
