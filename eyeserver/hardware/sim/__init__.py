"""The simulated treatment room: the project's default hardware and its test bed."""
