"""depthstation: measure depth-camera noise and accuracy over distance x inclination."""

__version__ = "0.1.0"
__all__ = ["__version__"]
