"""Device interfaces, the driver registry, rigs and drivers (real and simulated)."""
