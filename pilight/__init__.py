"""pilight: PI-Light (physics-inspired diffusion for full-image relighting) as a DVC pipeline."""

__version__ = "0.1.0"
