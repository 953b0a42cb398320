"""Benchmarks of mpm_monitor (not unit tests): run as ``python -m bench.<module>``, see bench/README.md."""
