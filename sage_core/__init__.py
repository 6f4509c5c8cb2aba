"""sage engine: animatable 2D Gaussian surfel head avatars (SAGE).

The engine never prints; it reports progress through callbacks. Heavy dependencies (torch) are
imported by the modules that need them, so importing :mod:`sage_core` itself is cheap.
"""

__version__ = "0.1.0"
