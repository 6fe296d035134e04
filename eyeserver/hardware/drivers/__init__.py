"""Drivers of real devices: each speaks its device's own protocol behind the interfaces of
:mod:`eyeserver.hardware.base`, and is tested against an emulator of that protocol
(:mod:`eyeserver.hardware.emulators`)."""
