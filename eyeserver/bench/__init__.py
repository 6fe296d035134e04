"""Benchmarks: figures measured the same way every time (``eyeserver bench …``)."""
