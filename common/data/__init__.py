"""Shared data readers and generators: EuRoC ASL layout and the synthetic multi-robot set."""
