"""Throughput benchmarks: simulation, recording, policies, sweeps, prompt tracking."""
