"""Stereo and phase-to-height calibration procedures over capture bundles."""
