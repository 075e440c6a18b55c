"""Experiments: whole studies built from the commands of every stage (record, train, sweep, diagnose, report)."""
