"""Tools around the package: the live demo, benchmarks, node-process orchestration and the
in-process diagnostics reader (watcher) of the demo, the live benchmark and the node tests."""
