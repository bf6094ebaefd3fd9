"""QR front end: detection, payload classification, the paper's Algorithms 1-6, PnP."""
