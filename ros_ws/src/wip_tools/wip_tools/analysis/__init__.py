"""Offline analysis of runs: figures and benchmarks (no ROS imports)."""
