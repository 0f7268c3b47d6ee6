"""Benchmarks: each module is one command printing ratios against a baseline measured in the same run."""
