"""Emulators of real devices' protocols, at the transport level (a pty, loopback TCP or UDP), for
the drivers' tests and for a whole daemon run on fake devices (issue 38)."""
