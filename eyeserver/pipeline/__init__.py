"""Pure numerics of the reconstruction: arrays in, arrays out; no I/O, no logging."""
