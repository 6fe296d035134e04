"""eyeserver: eye surface and pose by single-shot fringe projection for ocular proton therapy."""

__version__ = "0.1.0"
