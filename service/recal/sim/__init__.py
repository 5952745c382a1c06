"""Tooling for tests and the demo: a simulated wearer, its sensor's forward model and a
simulated device on a real pseudo-terminal."""
